"""A step's contact problem solved on a face of its limits: the face route's solve.

At the step's solution every contact point lies on one face of its limits: it lets go
(OPEN, no impulse), sticks (STICKS: no relative velocity), or slides with its friction at
the cone's edge (SLIDES_PLUS, SLIDES_MINUS). Given those labels, the active set, the
solution's impulses solve a linear system: the normal impulses of the points that press and
the tangent ones of those that stick, with no relative normal velocity where a point presses
and no tangent velocity where it sticks (solve_on_face). The face route a server serves
(server.face_route) reads a classifier's answer as such labels, solves the step on them and
admits the result into the cones (deepcontact.admission):

    face = contact_face(impulses, mu)                                   # (P,) int8 labels
    solved = solve_on_face(bodies, points, face, mu, physics)           # (P, 2) N s
    served, residual = solved_on_labels(bodies, points, labels, mu, physics, pressing, share, rounds)

Conventions are deepcontact.kinematics's. A face's system is summed over the pairs of points
that share a dynamic body, and its dual solve's gram from the system's nonzeros, compiled
(deepcontact/_faces.c, built by `make setup`); tests/deepcontact/test_faces.py checks both
against NumPy's dense products.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from deepcontact.admission import ADMISSION_RHO, _monotonic, nearest_admissible
from deepcontact.kinematics import (ContactFrame, Physics, _records, bounce, contact_frame, contact_velocities,
                                    velocities_before_and_after)
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE

try:
    from deepcontact import _faces as _compiled
    from deepcontact import _route as _compiled_route
except ImportError as exc:  # pragma: no cover - a checkout that was never set up
    raise ImportError(
        "deepcontact's compiled faces (deepcontact/_faces.c, _route.c) are not built: "
        "run `make setup` (or `pip install -e .`)"
    ) from exc
# deepcontact/_route.c reads a contact point's key at offset 0 (contact_records.h, POINT_KEY).
if CONTACT_DTYPE.fields["key"][1] != 0:
    raise ImportError("deepcontact.records moved a contact point's key from offset 0, where deepcontact/_route.c "
                      "reads it (contact_records.h, POINT_KEY): change both")


#: contact_face's labels: a point that lets go (no impulse), sticks (both velocities 0),
#: or slides with its friction at the cone's edge, pushing along +t or -t.
OPEN, STICKS, SLIDES_PLUS, SLIDES_MINUS = 0, 1, 2, 3
#: A label written as an impulse (N s): a classifier's answer along the normal where a point
#: presses, and +-this along the tangent where it slides (deepcontact.channels' face targets).
FACE_IMPULSE = 1.0
#: The friction coefficient a face written as labels (face_labels) is read back at by the route
#: (its label_friction): a sliding label's tangent, FACE_IMPULSE, lies at its limit at any friction
#: up to 1, and a point's own may be higher.
LABELS_FRICTION = 0.5


def contact_face(impulses: np.ndarray, mu: np.ndarray, pressing: float = 1e-6, share: float = 0.99) -> np.ndarray:
    """Which face of the contact problem's limits each point's impulses lie on, (P,) int8.

    impulses: (P, 2) (normal, tangent) N s; mu: (P,) friction coefficients. A point
    whose normal impulse is `pressing` N s or less is OPEN; one whose friction is at
    `share` of its limit (mu times the normal impulse) or more SLIDES_PLUS or
    SLIDES_MINUS by the tangent impulse's sign; the rest STICKS. The labels of a
    step's solution are its active set: given them, the solution's impulses solve a
    linear system (solve_on_face).
    """
    c = np.asarray(impulses, np.float64)
    on = c[:, 0] > pressing
    slides = on & (np.abs(c[:, 1]) >= share * np.asarray(mu, np.float64) * c[:, 0])
    face = np.where(on, STICKS, OPEN).astype(np.int8)
    face[slides] = np.where(c[slides, 1] > 0, SLIDES_PLUS, SLIDES_MINUS)
    return face


def face_labels(face: np.ndarray) -> np.ndarray:
    """A face (P,) int8 written as a classifier's labels, (P, 2) float64 N s: FACE_IMPULSE along
    the normal where a point presses (sticks or slides), +-FACE_IMPULSE along the tangent where it
    slides that way, 0 elsewhere. contact_face at a pressing threshold under FACE_IMPULSE reads
    them back as the same face (for friction coefficients up to 1 / 0.99, share 0.99)."""
    face = np.asarray(face)
    labels = np.zeros((len(face), 2))
    labels[face != OPEN, 0] = FACE_IMPULSE
    labels[face == SLIDES_PLUS, 1] = FACE_IMPULSE
    labels[face == SLIDES_MINUS, 1] = -FACE_IMPULSE
    return labels


#: face_errors' kinds of wrong label, after the count of all of them.
FACE_ERRORS = ("open where it presses", "presses where it is open", "sticks where it slides", "slides where it sticks",
               "slides the other way")


def face_errors(face: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(6,) int: how many of a step's (P,) contact_face labels differ from the reference's (P,),
    in all and then by each of FACE_ERRORS."""
    slides, slides_ref = face > STICKS, reference > STICKS
    kinds = [face != reference, (face == OPEN) & (reference != OPEN), (face != OPEN) & (reference == OPEN),
             (face == STICKS) & slides_ref, slides & (reference == STICKS), slides & slides_ref & (face != reference)]
    return np.array([int(k.sum()) for k in kinds])


def repair_face(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray, mu: np.ndarray,
                physics: Physics = Physics(), slack: float = 1e-4,
                restitution: np.ndarray | None = None) -> np.ndarray:
    """Labels for the next solve, read off a face's admitted solve, (P,) int8: one step of a
    primal-dual active-set method (a step of Newton's on the problem's limits).

    impulses: (P, 2) N s, a face's solve made admissible (solve_on_face, then
    nearest_admissible with the face's open points held), so inside every cone; mu: (P,)
    friction coefficients; bodies, points, physics as in contact_velocities. The labels
    are contact_face's of the impulses (a point the admission took to no normal impulse
    lets go, one it took to the cone's edge slides), then corrected by the motion the
    impulses give: a point that lets go but closes faster than `slack` m/s presses
    (STICKS), and one that slides but moves with its friction, not against it, by more
    than `slack`, STICKS. Where the face was the solution's own, its labels come back
    (up to the readings' thresholds); where a few were wrong, a step or two of this
    usually finds them, each a solve on the new labels. restitution: (P,) each point's, or None:
    a point's closing speed is measured from its bounce (kinematics.bounce), as the solve holds it.
    """
    face = contact_face(impulses, mu)
    before, after = velocities_before_and_after(bodies, points, np.asarray(impulses, np.float64), physics)  # (P, 2) m/s
    if restitution is not None:
        after = after.copy()
        after[:, 0] -= bounce(before[:, 0], restitution)
    # Friction pushes against the slip: +t (SLIDES_PLUS) only while the point moves along -t.
    wrong_way = ((face == SLIDES_PLUS) & (after[:, 1] > slack)) | ((face == SLIDES_MINUS) & (after[:, 1] < -slack))
    face[((face == OPEN) & (after[:, 0] < -slack)) | wrong_way] = STICKS
    return face


def solve_on_face(bodies: np.ndarray, points: np.ndarray, face: np.ndarray, mu: np.ndarray,
                  physics: Physics = Physics(), frame: ContactFrame | None = None,
                  damping: float = 0.0, solver: str = "gelsy",
                  restitution: np.ndarray | None = None) -> np.ndarray:
    """The step's contact problem solved as if its solution lay on `face`, (P, 2) N s.

    face: (P,) contact_face labels; mu: (P,) friction coefficients; bodies, points,
    physics as in contact_velocities; restitution: (P,) each point's, or None: a pressing
    point is held at its bounce (kinematics.bounce) where it closes faster than 1 m/s, as
    Box2D's solver holds it, else at rest. The
    unknowns are the normal impulses of the points that press and the tangent ones
    of those that stick; a sliding point's tangent impulse is +-mu times its normal
    one, an open point's impulses are 0. The equations ask for no relative normal
    velocity where a point presses and no tangent velocity where it sticks, after
    gravity and the impulses (J M^-1 J^T, dense). Where the face is the solution's
    own, the bodies' motion comes out exact; the impulses are the least-norm ones
    (the self-stress, which moves no body, is not fixed by the face: admit them,
    nearest_admissible, to let the limits choose it). Nothing is kept in the cones
    here. The system is square but singular in a pile held at more points than it
    has freedoms, and inconsistent where the face is wrong: least squares either way
    (the minimum-norm solution: with `solver` "gelsy" by a complete orthogonal factorization,
    LAPACK's gelsy; with "dual" by minimum_norm_solve, about 2.5 times as fast where the system
    is consistent and a little damped in its weakest directions, gelsy where it is not; the
    system is summed over the point pairs, face_system).
    With `damping` > 0 it is damped least squares instead, (S^T S + l I) x = S^T b with
    l = damping max|S|^2, by Cholesky: the same impulses where the system is consistent and
    well posed, bounded ones where a wrong face makes it inconsistent and near singular (the
    minimum-norm solution there can reach thousands of N s), in about half the time.
    """
    f = contact_frame(bodies, points) if frame is None else frame
    face = np.asarray(face)
    n_points = len(points)
    pressing, sticking = np.flatnonzero(face != OPEN), np.flatnonzero(face == STICKS)
    if len(pressing) == 0:
        return np.zeros((n_points, 2))
    velocity = contact_velocities(bodies, points, physics=physics)  # (P, 2) m/s before any impulse
    velocity[:, 0] -= bounce(velocity[:, 0], restitution)  # what each normal equation must take away
    velocity = velocity.ravel()
    system, rows, slide = face_system_sparse(f, face, mu)
    x = _least_squares(system, -velocity[rows], damping, solver)
    out = np.zeros((n_points, 2))
    out[pressing, 0] = x[:len(pressing)]
    out[pressing, 1] = slide * x[:len(pressing)]
    out[sticking, 1] = x[len(pressing):]
    return out


class SparseSystem(NamedTuple):
    """A face's system S (m, m) as CSR: indptr int32 (m + 1,), indices int32 and data float64
    (nnz,); about 3 % of its entries are not zero."""

    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray

    @property
    def m(self) -> int:
        return len(self.indptr) - 1

    def dense(self) -> np.ndarray:
        """(m, m) float64, the same numbers."""
        out = np.zeros((self.m, self.m))
        out[np.repeat(np.arange(self.m), np.diff(self.indptr)), self.indices] = self.data
        return out


def face_system(frame: ContactFrame, face: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """solve_on_face's linear system on a face's unknowns: (system (m, m) m/s per N s, rows (m,),
    slide (k,)).

    face: (P,) contact_face labels; mu: (P,) friction coefficients. The k pressing points'
    normal impulses come first, then the sticking points' tangent ones; a sliding point's
    column is its normal column plus its tangent one times slide (+-mu). rows are the
    equations' indices into the (2P,) relative velocities (normal 2 i, tangent 2 i + 1), in the
    unknowns' order. The same numbers as kinematics.contact_operator's rows and columns combined so, summed
    over the pairs of points that share a dynamic body (a few thousand) without the (2P, 2P)
    operator (at 160 points that one and its fancy indexing took about 2 ms, and the pairs in
    NumPy about 1 ms), compiled (deepcontact/_faces.c). face_system_sparse gives it as CSR."""
    system, rows, slide = face_system_sparse(frame, face, mu)
    return system.dense(), rows, slide


def face_system_sparse(frame: ContactFrame, face: np.ndarray, mu: np.ndarray
                       ) -> tuple[SparseSystem, np.ndarray, np.ndarray]:
    """face_system's (system, rows, slide) with the system as CSR (SparseSystem), as the compiled
    sum makes it: each entry summed in the order a dense array summed in place would be."""
    face = np.asarray(face)
    n_points = len(face)
    pressing, sticking = np.flatnonzero(face != OPEN), np.flatnonzero(face == STICKS)
    k = len(pressing)
    m = k + len(sticking)
    slide_of = np.where(face == SLIDES_PLUS, 1.0, np.where(face == SLIDES_MINUS, -1.0, 0.0)) * np.asarray(mu, np.float64)
    # Each point's equation row and unknown column, by direction (normal, tangent); -1 where it has none.
    index = np.full((n_points, 2), -1)
    index[pressing, 0] = np.arange(k)
    index[sticking, 1] = k + np.arange(len(sticking))
    f, i64 = frame, np.int64
    indptr, indices, data = _compiled.face_system_sum(
        f.a.astype(i64), f.b.astype(i64), np.ascontiguousarray(f.dynamic, np.uint8),
        *(np.ascontiguousarray(x, np.float64) for x in (f.inv_mass, f.inv_inertia, f.n, f.t, f.ra, f.rb)),
        index.astype(i64).ravel(), np.ascontiguousarray(slide_of), m)
    system = SparseSystem(np.frombuffer(indptr, np.int32), np.frombuffer(indices, np.int32),
                          np.frombuffer(data, np.float64))
    rows = np.concatenate([2 * pressing, 2 * sticking + 1])
    return system, rows, slide_of[pressing]


#: solve_on_face's ways to the minimum-norm least-squares solution.
SOLVERS = ("gelsy", "dual")


def _least_squares(sparse: SparseSystem, rhs: np.ndarray, damping: float, solver: str = "gelsy") -> np.ndarray:
    """solve_on_face's solve of system (m, m) x = rhs (m,): minimum-norm least squares
    (damping 0, by `solver`) or damped, as solve_on_face says. The dual solve reads the sparse
    system; the rest its dense form."""
    import scipy.linalg

    if solver not in SOLVERS:
        raise ValueError(f"solver: one of {SOLVERS}, got {solver!r}")
    if solver == "dual" and damping == 0:
        x = minimum_norm_solve(sparse, rhs)
        if x is not None:
            return x
    system = sparse.dense()
    if damping > 0:
        normal = system.T @ system
        normal.flat[::len(normal) + 1] += damping * float(np.abs(system).max()) ** 2
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(normal, check_finite=False), system.T @ rhs,
                                          check_finite=False)
        except np.linalg.LinAlgError:  # a damping below the product's rounding: the exact route
            pass
    # gelsy asked for, or a system far from consistent
    return scipy.linalg.lstsq(system, rhs, lapack_driver="gelsy", check_finite=False)[0]


#: minimum_norm_solve's ridge on S S^T, relative to its mean diagonal: far below the singular
#: values that a face's system resolves, far above what S S^T's rounding leaves in its null
#: space. A face's system has a clean gap between the two: on the thesis world's largest steps
#: (seed 903, the default's labels) its singular values are above about 1e-6 of the largest or
#: below 1e-12, the right-hand side nowhere in the latter (`deepcontact lab face-solve`). Where
#: the factor still meets a pivot below zero, the compiled solve grows the ridge a hundredfold,
#: at most twice (to 1e-11; face_kernels.h): a pile held at far more points than its bodies have
#: freedoms leaves rounding's pivots larger. On a pyramid of boxes, two points to each face on
#: a face, S is of rank 170 at 358 unknowns, its singular values below 2e-16 of the largest or
#: above 4e-3, and the least ridge met a pivot below zero on every step of 100 points and more
#: (docs/research/2026-12-06-redundant-piles.md).
DUAL_RIDGE = 1e-15
#: minimum_norm_solve's rounds of iterative refinement on S S^T y = b, each from the ridged
#: factor: squaring S squares its condition (1e12 where a singular value is 1e-6 of the
#: largest), so one solve is good to about 1e-4 in S's weakest directions; each round takes
#: that error down about as far again, for two matrix-vector products and two triangular
#: solves (a few per cent of the factorization).
DUAL_REFINEMENTS = 2
#: minimum_norm_solve's test of its answer: |S^T (S x - b)| at most this times |S^T b|.
DUAL_OPTIMALITY = 1e-6


def minimum_norm_solve(system: np.ndarray | SparseSystem, rhs: np.ndarray) -> np.ndarray | None:
    """The minimum-norm solution of a consistent, possibly singular, system S (m, m) x = b (m,),
    through its dual: x = S^T y with S S^T y = b, solved by Cholesky of S S^T + r I (r =
    DUAL_RIDGE times the mean of its diagonal) and DUAL_REFINEMENTS rounds of iterative
    refinement. system: dense (m, m) or a SparseSystem (face_system_sparse's). Whatever y picks up in S S^T's
    null space S^T sends to 0, so a tiny ridge serves. A face's system is singular in every
    pile (more points than freedoms) and consistent where the face is the solution's.

    It is the pseudo-inverse's solution with singular values below about 3e-8 of the largest
    taken as zero: on the thesis world's faces it agrees with numpy's pinv at rcond 1e-10
    better than LAPACK's gelsy does, which keeps directions down to machine precision and on
    about 2 % of the large steps adds an answer along one that is rounding (`deepcontact bench
    face-solve` prints both distances). It runs compiled on S's nonzeros (_faces.dual_solve:
    S is about 3 % full and S S^T under 10 %, so its sparse Cholesky factor in a reverse
    Cuthill-McKee order holds a fifth to a tenth of a dense factor's entries): about 0.28 ms at
    the thesis world's largest steps (300 unknowns), where LAPACK's dense Cholesky of S S^T took
    0.45-0.66 ms and gelsy three to four times that. Where rounding leaves a pivot below zero
    at the largest ridge (DUAL_RIDGE), the dense factorization with gesv's LU. None where the answer is not a least-squares
    solution to DUAL_OPTIMALITY (a wrong face's inconsistent system, whose residual the ridge
    would blow up through y): the caller solves it otherwise.
    """
    from scipy.linalg import lapack

    m = len(rhs)
    if m == 0:
        return np.zeros(0)
    sparse = system if isinstance(system, SparseSystem) else _sparse(np.asarray(system, np.float64))
    x = np.empty(m)
    status = _compiled.dual_solve(sparse.indptr, sparse.indices, sparse.data, np.ascontiguousarray(rhs, np.float64),
                                  DUAL_RIDGE, DUAL_REFINEMENTS, DUAL_OPTIMALITY, x)
    if status == 0:
        return x
    if status == 2:  # not a least-squares answer: the system is far from consistent
        return None
    # Where the sparse factor meets a pivot below zero (rounding in S S^T's null space): the
    # dense factorization, with its LU.
    system = sparse.dense() if isinstance(system, SparseSystem) else np.ascontiguousarray(system, np.float64)
    gram = np.empty((m, m))
    _compiled.sparse_gram(system, m, gram)
    scale = float(np.trace(gram)) / m
    if not scale > 0:
        return np.zeros(m)  # S = 0: every x solves it, 0 the least
    gram.flat[::m + 1] += DUAL_RIDGE * scale
    # Symmetric and, with the ridge, positive definite: Cholesky, half an LU's work. Where rounding
    # leaves a null-space pivot below zero anyway, the LU that pivots past it.
    factor, info = lapack.dpotrf(gram, lower=True, clean=False, overwrite_a=False)
    if info == 0:
        def solve(b):
            return lapack.dpotrs(factor, b, lower=True)
    else:
        lu, piv, info = lapack.dgetrf(gram)

        def solve(b):
            return lapack.dgetrs(lu, piv, b)
    if info != 0:
        return None
    y, info = solve(rhs)
    for _ in range(DUAL_REFINEMENTS):
        if info != 0:
            return None
        # Refined against S S^T itself, not the ridged matrix: the ridge only preconditions.
        correction, info = solve(rhs - system @ (system.T @ y))
        y += correction
    if info != 0:
        return None
    x = system.T @ y
    gradient = system.T @ (system @ x - rhs)
    if not np.linalg.norm(gradient) <= DUAL_OPTIMALITY * np.linalg.norm(system.T @ rhs):
        return None
    return x



def _sparse(system: np.ndarray) -> SparseSystem:
    """A dense (m, m) system as CSR."""
    rows, cols = np.nonzero(system)
    indptr = np.zeros(len(system) + 1, np.int32)
    np.cumsum(np.bincount(rows, minlength=len(system)), out=indptr[1:])
    return SparseSystem(indptr, cols.astype(np.int32), system[rows, cols].astype(np.float64))


def solved_on_labels(bodies: np.ndarray, points: np.ndarray, labels: np.ndarray, mu: np.ndarray,
                     physics: Physics = Physics(), pressing: float = 0.5, share: float = 1.0,
                     rounds: int = 1000, label_friction: float | None = None,
                     frame: ContactFrame | None = None, damping: float = 0.0,
                     solver: str = "gelsy", until: float | None = None,
                     close: float | None = None, relax: float = 1.0, rho: float = ADMISSION_RHO,
                     restitution: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """The warm start of the face route, (P, 2) N s: a classifier's answer read as labels,
    the step solved on them, the result admitted.

    labels: (P, 2) N s, a classifier's answer (train-graph --targets face: about 1 N s along
    the normal where a point presses, +-1 N s along the tangent where it slides), read by
    contact_face as pressing above `pressing` N s and sliding at `share` of its limit (at
    `label_friction` times the normal answer when given, whatever the point's friction); mu:
    (P,) friction coefficients; bodies, points, physics as in contact_velocities. The step
    is solved on those labels (solve_on_face, with its `damping` and `solver`) and moved by the smallest self-stress that
    every cone admits, the labels' open points held at 0 (admission.nearest_admissible, at most
    `rounds` rounds over-relaxed by `relax` at ADMM's penalty `rho`, and none begun after `until`,
    perf_counter() s). The simulation client's
    solved: composite and the server's face cards (deepcontact.modelcard) both serve this.

    close: None, or a speed (m/s): the points labelled open that the solve leaves closing
    faster than that (relative normal velocity below -close) are labelled pressing instead
    (sticking, or sliding where their tangent label says so) and the step solved again before
    the admission. A point said to let go that the solve then drives into its neighbour was
    pressing in the recorded solve at 4 of 5 such points of the validation steps, where the
    opposite test (a pressing label that the solve gives a pull) is right at 1 in 14; served, it
    costs iterations all the same, since a wrong open label drives its truly open neighbours
    shut as well and they are relabelled with it (docs/results.md, "The solve refined, the
    classifier trained on"). Off in the shipped cards.

    Returns (impulses (P, 2) N s, residual): face_residual of the impulses served, how far
    they leave the labels' equations unmet once every cone is kept (0: labels the limits
    let the solve meet; larger: labels whose solve the admission had to move, a face that
    is not this step's). It is read_and_solve, then admit_solved, on one frame.
    """
    frame = contact_frame(bodies, points) if frame is None else frame
    face, solved = read_and_solve(bodies, points, labels, mu, physics, pressing, share, label_friction, frame,
                                  damping, solver, close, restitution)
    return admit_solved(bodies, points, face, solved, mu, physics, rounds, frame, until, relax, rho, restitution)


class CompiledRoute(NamedTuple):
    """route_compiled's answer: impulses (P, 2) N s admitted, their face_residual, the seconds
    of the solve (the labels read and the step solved on them) and of the admission (with the
    residual), the admission's rounds run (0 where the solve's answer was admissible), and
    whether the solve ran in the bodies' space (factors of order 3 D, the dynamic bodies'
    freedoms, in place of the dual's S S^T; route_compiled says where) rather than by the dual."""

    impulses: np.ndarray
    residual: float
    solve_seconds: float
    admit_seconds: float
    rounds_run: int
    in_bodies: bool = False


def prepare_route(bodies: np.ndarray, points: np.ndarray, physics: Physics = Physics(),
                  restitution: np.ndarray | None = None):
    """route_compiled's work that does not depend on the labels, done ahead: the contact frame,
    the velocities before any impulse, each point's bounce and the admission's factorization (an
    opaque object for route_compiled's `prepared`). It runs without the GIL, so a server can do it
    on another core while its classifier answers the same step. restitution: (P,) each point's
    (Box2D's mix of its two fixtures', the larger), or None: no point bounces. Box2D holds a point
    closing faster than 1 m/s before any impulse at the restitution times that speed, apart, rather
    than at rest (b2ContactSolver's velocity bias); the route's solve and the copy's sweeps hold it
    there too."""
    bodies = _records(np.asarray(bodies), BODY_DTYPE, "bodies")
    points = _records(np.asarray(points), CONTACT_DTYPE, "points")
    gx, gy = physics.gravity
    return _compiled_route.prepare(bodies, len(bodies), points, len(points), float(physics.dt), float(gx), float(gy),
                                   _restitution(restitution, len(points)))


def _restitution(restitution: np.ndarray | None, n_points: int) -> np.ndarray | None:
    """restitution as the compiled route takes it: float64 (P,), or None where no point has any."""
    if restitution is None:
        return None
    r = np.ascontiguousarray(restitution, np.float64)
    if r.shape != (n_points,):
        raise ValueError(f"restitution: ({n_points},), got {r.shape}")
    return r if r.any() else None


def sweep_changes(bodies: np.ndarray, points: np.ndarray, starts: np.ndarray, mu: np.ndarray,
                  physics: Physics = Physics(), sweeps: int = 12, prepared=None,
                  restitution: np.ndarray | None = None) -> np.ndarray:
    """(S,) N s: for each start of starts (S, P, 2) N s (normal, tangent), the largest change the
    solver's sweep number `sweeps` would make at any point, on the server's copy of the step:
    Box2D's velocity constraints (each manifold in turn, its tangent impulses held inside mu (P,)
    times their normal ones, then its normal impulses held >= 0, a two-point manifold's as one
    block, as Box2D's block solver; no joints; each point's bounce held as prepare_route's
    `restitution` gives it; deepcontact/_route.c). The
    solver stops after the first sweep that changes
    nothing by more than its threshold, so of two starts the one whose sweep changes less is
    the nearer to where it stops: kinematics.jacobi_change is the one-step, every-point-at-once
    version of this. prepared: prepare_route's for the same bodies, points and physics, or
    None. At most 64 starts; about 1.8 us a sweep a start at 130 points."""
    return _compare_starts(bodies, points, starts, mu, physics, sweeps, prepared, 0.0, restitution=restitution)[0]


class RevoluteRows(NamedTuple):
    """Joints for the server's copy of the step, which sweeps them as Box2D's solver does, before
    the contacts in each sweep: revolute joints (a point constraint, and an angle limit and a
    motor where `limits` gives them; a rigid weld held as one at equal limits) and prismatic ones.

    bodies: (J, 2) int, each joint's body A and body B (the records' rows);
    arms: (J, 4) m, world frame, rA then rB: from each body's centre of mass to its anchor;
    starts: (S, J, 2), each start's joint impulses, one per start of the contact points' starts:
    a revolute or weld joint's point impulse on body B (world, N s: Box2D's m_impulse.x, .y), a
    prismatic joint's across its axis (N s) and its angular one (N m s);
    limits: (J, 13) or None (every joint a revolute one with no limit and no motor):
    server.revolute.limits's table (its kind for the copy, 0 revolute or 1 prismatic; its
    limit's state and impulse; its motor on, impulse, largest impulse in the step and speed; a
    prismatic joint's axis and Box2D's a1, a2, s1, s2); the limits' and motors' impulses start
    every start (the client keeps its own)."""

    bodies: np.ndarray
    arms: np.ndarray
    starts: np.ndarray
    limits: np.ndarray | None = None


def sweeps_to_stop(bodies: np.ndarray, points: np.ndarray, starts: np.ndarray, mu: np.ndarray,
                   physics: Physics, tolerance: float, most: int, prepared=None,
                   joints: RevoluteRows | None = None,
                   restitution: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((S,) int, (S,) N s): for each start of starts (S, P, 2) N s, the sweeps the server's copy
    of the step (as sweep_changes) takes to the client's stopping rule, the first sweep that
    changes nothing by more than `tolerance` N s (> 0), or most + 1 where none of the first
    `most` does; and the change of the last sweep run. Of two starts the one that stops sooner
    is the nearer to where the solver stops; where neither stops within `most` sweeps, the one
    whose last sweep changes less. Comparing the changes at a fixed sweep instead reads noise
    where both starts stop before it (both changes then near zero). At most 64 starts. joints:
    the step's revolute joints and each start's joint impulses, swept as Box2D does (the
    stopping rule, as the client's, reads the contacts' changes alone), or None: the joints left
    out, as the server's routes see a step."""
    if not tolerance > 0:
        raise ValueError(f"tolerance must be > 0 N s, got {tolerance}")
    changes, counts = _compare_starts(bodies, points, starts, mu, physics, most, prepared, float(tolerance), joints,
                                      restitution=restitution)
    return counts, changes


class Islands(NamedTuple):
    """A step's islands as Box2D's solver forms them (bodies joined by contact points and joints,
    never through a static body; a kinematic one joins them), and what each start does on each.
    Box2D sweeps each island on its own and stops it at its own first sweep under the tolerance;
    a step's iterations are its largest island's count (docs/engine.md, "Islands"). So a start
    can be the better one on one island and the worse on another.

    point: (P,) int32, each contact point's island, 0..I-1 in the order of their first points;
    joint: (J,) int32, each joint's, -1 where no contact point is on its island;
    counts: (S, I) int, the sweep each start stops each island at (most + 1 where it does not);
    changes: (S, I) N s, that sweep's largest change on the island (or the last sweep's)."""

    point: np.ndarray
    joint: np.ndarray
    counts: np.ndarray
    changes: np.ndarray

    def best(self) -> np.ndarray:
        """(I,) int: for each island the start that stops it soonest, by the smaller change
        where two stop at the same sweep (or neither stops)."""
        if self.counts.shape[1] == 0:
            return np.zeros(0, np.int64)
        return np.lexsort((self.changes, self.counts), axis=0)[0]

    def compose(self, starts: np.ndarray, joint_starts: np.ndarray | None = None):
        """(start (P, 2), joints (J, ...) or None, chosen (I,)): each island's points (and joints)
        from the start best() picks there; starts (S, P, 2), joint_starts (S, J, ...) or None. A
        joint on no point's island keeps the first start's (joint_starts[0])."""
        chosen = self.best()
        start = np.asarray(starts)[chosen[self.point], np.arange(len(self.point))] if len(self.point) \
            else np.asarray(starts)[0]
        joints = None
        if joint_starts is not None:
            pick = np.where(self.joint >= 0, chosen[np.maximum(self.joint, 0)] if len(chosen) else 0, 0)
            joints = np.asarray(joint_starts)[pick, np.arange(len(self.joint))]
        return start, joints, chosen


def island_sweeps_to_stop(bodies: np.ndarray, points: np.ndarray, starts: np.ndarray, mu: np.ndarray,
                          physics: Physics, tolerance: float, most: int, prepared=None,
                          joints: RevoluteRows | None = None,
                          restitution: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, Islands]:
    """sweeps_to_stop island by island: ((S,) int, (S,) N s, Islands). Each start's count is Box2D's
    for the step, its largest island's count (every island stopped by then; most + 1 where one is
    not), and its change the largest of the islands' changes where they stop; Islands gives each
    island's. The joints join islands as the contact points do."""
    if not tolerance > 0:
        raise ValueError(f"tolerance must be > 0 N s, got {tolerance}")
    changes, counts, islands = _compare_starts(bodies, points, starts, mu, physics, most, prepared, float(tolerance),
                                               joints, by_island=True, restitution=restitution)
    return counts, changes, islands


def _compare_starts(bodies, points, starts, mu, physics: Physics, sweeps: int, prepared, tolerance: float,
                    joints: RevoluteRows | None = None, by_island: bool = False,
                    restitution: np.ndarray | None = None):
    """(changes (S,) N s, sweeps run (S,) int) of compare_starts in deepcontact/_route.c; by_island,
    also an Islands; restitution as prepare_route's (where prepared is None)."""
    bodies = _records(np.asarray(bodies), BODY_DTYPE, "bodies")
    points = _records(np.asarray(points), CONTACT_DTYPE, "points")
    starts = np.ascontiguousarray(starts, np.float64)
    if starts.ndim != 3 or starts.shape[1:] != (len(points), 2) or not 1 <= len(starts) <= 64:
        raise ValueError(f"starts: (S, {len(points)}, 2) with 1 <= S <= 64, got {starts.shape}")
    if len(points) == 0:
        none = np.zeros(len(starts)), np.ones(len(starts), np.int64)
        J = 0 if joints is None else len(joints.bodies)
        return none if not by_island else none + (Islands(np.zeros(0, np.int32), np.full(J, -1, np.int32),
                                                          np.zeros((len(starts), 0), np.int64),
                                                          np.zeros((len(starts), 0))),)
    gx, gy = physics.gravity
    extra = (None, None, None, None)
    if joints is not None:
        extra = (np.ascontiguousarray(joints.bodies, np.int64), np.ascontiguousarray(joints.arms, np.float64),
                 np.ascontiguousarray(joints.starts, np.float64))
        if extra[0].shape != (len(extra[0]), 2) or extra[1].shape != (len(extra[0]), 4) \
                or extra[2].shape != (len(starts), len(extra[0]), 2):
            raise ValueError(f"joints: bodies (J, 2), arms (J, 4), starts ({len(starts)}, J, 2), got "
                             f"{extra[0].shape}, {extra[1].shape}, {extra[2].shape}")
        limits = None
        if joints.limits is not None:
            limits = np.ascontiguousarray(joints.limits, np.float64)
            if limits.shape != (len(extra[0]), 13):
                raise ValueError(f"joints: limits ({len(extra[0])}, 13), got {limits.shape}")
        extra = extra[:3] + (limits,)
    out = _compiled_route.compare_starts(bodies, len(bodies), points, len(points), np.ascontiguousarray(mu, np.float64),
                                         float(physics.dt), float(gx), float(gy), starts, int(sweeps), prepared,
                                         float(tolerance), *extra, bool(by_island),
                                         _restitution(restitution, len(points)))
    changes, counts = np.array(out[0]), np.array(out[1], np.int64)
    if not by_island:
        return changes, counts
    shape = (len(starts), out[6])
    return changes, counts, Islands(np.frombuffer(out[4], np.int32), np.frombuffer(out[5], np.int32),
                                    np.frombuffer(out[2], np.int64).reshape(shape), np.frombuffer(out[3]).reshape(shape))


def route_compiled(bodies: np.ndarray, points: np.ndarray, labels: np.ndarray, mu: np.ndarray,
                   physics: Physics = Physics(), pressing: float = 0.5, share: float = 1.0,
                   label_friction: float | None = None, rounds: int = 1000,
                   until: float | None = None, prepared=None, relax: float = 1.0,
                   rho: float = ADMISSION_RHO, carry: tuple | None = None,
                   slide_in_bodies: bool = True, restitution: np.ndarray | None = None) -> CompiledRoute | None:
    """solved_on_labels with solver "dual", no damping and no `close`, in one compiled call
    (deepcontact/_route.c, on the same kernels as the pieces here): the same numbers to rounding,
    without the NumPy calls between the pieces (about 0.15-0.25 ms of a served step). The solve's
    minimum-norm answer is taken in the bodies' space where it can be (deepcontact/face_kernels.h,
    face_body_solve): with S = L R^T (L = A W^1/2 the face's rows, R = C W^1/2 its columns),
    K = L^T L and G = R^T R of order 3 D, it is L K^+ K^+ L^T b where no point slides and
    R G^-1 K^-1 L^T b where points slide, once the directions K leaves free (a body's own, or
    several bodies' together: boxes that stick to one another sliding on those below) are set
    apart, where R is of full rank on the rest. The dual's answer to
    rounding, on factors a small share of S S^T's where a pile is held at many more points than
    its bodies have freedoms (a pyramid of boxes at 800 points: about 0.8 ms against 15 ms);
    elsewhere the dual. slide_in_bodies False sends a step where points slide to the dual at once
    (a pile of discs: their sliding points leave turnings free, and the bodies' space declines
    nearly every such step after its first factor). Arguments
    as in solved_on_labels; bodies (B,) BODY_DTYPE and points (P,) CONTACT_DTYPE records;
    prepared: prepare_route's for the same bodies, points and physics, or None; carry: None, or
    admission.AdmissionCarry.begin's: the rounds begin where each point's ended on the stream's
    step before, and write where this step's end; restitution: as prepare_route's (where prepared
    is None). None where the
    compiled dual solve declines the labels' system (a pivot below zero, or a system far from
    consistent): solved_on_labels answers those."""
    bodies = _records(np.asarray(bodies), BODY_DTYPE, "bodies")
    points = _records(np.asarray(points), CONTACT_DTYPE, "points")
    mu = np.ascontiguousarray(mu, np.float64)
    read_at = mu if label_friction is None else np.full(len(points), float(label_friction))
    impulses = np.empty((len(points), 2))
    gx, gy = physics.gravity
    outcome, residual, solve_s, admit_s, used, in_bodies = _compiled_route.solve_and_admit(
        bodies, len(bodies), points, len(points), np.ascontiguousarray(labels, np.float64), mu, read_at,
        float(physics.dt), float(gx), float(gy), float(pressing), float(share), int(rounds), float(relax), float(rho),
        _monotonic(until),
        DUAL_RIDGE, DUAL_REFINEMENTS, DUAL_OPTIMALITY, bool(slide_in_bodies), impulses, prepared, carry,
        _restitution(restitution, len(points)))
    if outcome != _compiled_route.SERVED:
        return None
    return CompiledRoute(impulses, residual, solve_s, admit_s, used, bool(in_bodies))


def read_and_solve(bodies: np.ndarray, points: np.ndarray, labels: np.ndarray, mu: np.ndarray,
                   physics: Physics = Physics(), pressing: float = 0.5, share: float = 1.0,
                   label_friction: float | None = None, frame: ContactFrame | None = None,
                   damping: float = 0.0, solver: str = "gelsy",
                   close: float | None = None, restitution: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """solved_on_labels's first half: (face (P,) int8, impulses (P, 2) N s), the labels read as
    a face (contact_face) and the step solved on it (solve_on_face; again on the relabelled face
    where `close` relabels), not yet admitted. Arguments as in solved_on_labels. A server times
    it apart from the admission (the face route's "solve" stage)."""
    frame = contact_frame(bodies, points) if frame is None else frame
    read_at = mu if label_friction is None else np.full(len(points), float(label_friction))
    face = contact_face(labels, read_at, pressing=pressing, share=share)
    solved = solve_on_face(bodies, points, face, mu, physics, frame, damping, solver, restitution)
    if close is not None:
        closing = (face == OPEN) & (contact_velocities(bodies, points, solved, physics)[:, 0] < -close)
        if closing.any():
            relabelled = np.array(labels, np.float64, copy=True)
            # read pressing, and its tangent answer read against a pressing label's normal one
            relabelled[closing, 0] = max(FACE_IMPULSE, np.nextafter(pressing, np.inf))
            face = contact_face(relabelled, read_at, pressing=pressing, share=share)
            solved = solve_on_face(bodies, points, face, mu, physics, frame, damping, solver, restitution)
    return face, solved


def admit_solved(bodies: np.ndarray, points: np.ndarray, face: np.ndarray, solved: np.ndarray, mu: np.ndarray,
                 physics: Physics = Physics(), rounds: int = 1000, frame: ContactFrame | None = None,
                 until: float | None = None, relax: float = 1.0,
                 rho: float = ADMISSION_RHO, restitution: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """solved_on_labels's second half: (impulses (P, 2) N s, residual), a step solved on a face
    (P,) (read_and_solve's `solved`, (P, 2) N s) moved by the smallest self-stress that every cone
    admits, the face's open points held at 0 (admission.nearest_admissible, at most `rounds`
    rounds, none begun after `until`, perf_counter() s), and face_residual of the result.
    Arguments as in solved_on_labels. A server times it apart from the solve (the face route's
    "admit" stage)."""
    admitted = nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, iterations=rounds, frame=frame,
                                  until=until, relax=relax, rho=rho)
    return admitted, face_residual(bodies, points, face, admitted, physics, restitution)


def face_residual(bodies: np.ndarray, points: np.ndarray, face: np.ndarray, impulses: np.ndarray,
                  physics: Physics = Physics(), restitution: np.ndarray | None = None) -> float:
    """How far impulses (P, 2) N s leave a face's equations unmet: the norm of the relative
    velocity where the face (P,) labels ask for none (the normal where a point presses, the
    tangent where it sticks) and of the closing velocity where it says a point lets go, after
    the impulses, over the norm of the relative velocity at those points before any impulse.
    0 for a face the impulses meet exactly. bodies, points, physics as in contact_velocities;
    restitution as solve_on_face's: the normal velocities measured from each point's bounce."""
    before, after = velocities_before_and_after(bodies, points, impulses, physics)
    after = after.copy()
    after[:, 0] -= bounce(before[:, 0], restitution)
    rows = np.concatenate([2 * np.flatnonzero(face != OPEN), 2 * np.flatnonzero(face == STICKS) + 1])
    left = np.concatenate([after.ravel()[rows], np.minimum(after[face == OPEN, 0], 0.0)])
    scale = float(np.linalg.norm(before))
    return float(np.linalg.norm(left)) / scale if scale > 0 else 0.0

