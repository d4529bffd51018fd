"""Relative velocities at contact points, as the contact solver first sees them.

Box2D's sequential-impulse solver (b2ContactSolver) works on each contact
point's relative velocity along its normal and tangent. At the start of a
step's velocity iterations that velocity is the bodies' velocity after this
step's gravity (v += g dt), and, with warm starting, after the starting
impulses have been applied (b2ContactSolver::WarmStart). These are what the
warm start has to get right: a perfect warm start leaves no normal velocity
at touching points, and the solver's iterations remove what is left.

    vel = contact_velocities(bodies, points)                        # before any impulse
    vel = contact_velocities(bodies, points, warm=points["builtin"])  # after the builtin warm start
    # (P, 2) float64 m/s: (normal, tangent); normal > 0 separates A and B

Conventions follow Box2D 2.3: the normal points from body A to body B, the
tangent is (n_y, -n_x) (b2Cross(normal, 1)), an impulse P = jn n + jt t acts
+P on B and -P on A at the contact point, and the relative velocity is
v_B + w_B x r_B - v_A - w_A x r_A with r the contact point relative to the
body's centre of mass. Bodies are placed on their origin (the centre of mass
of every shape the scenes build: circles and centred boxes).

`bodies` is indexed by the contact records' `body_a`/`body_b`: the engine's
records (creation order, static bodies included) or any array laid out the
same way, such as the server's decoded step (a static stand-in at row 0).
Bodies that are not dynamic (type != 2) neither move nor take impulses.
Velocities and effective masses are computed by deepcontact/_kinematics.c,
built by `make setup`, straight from the records in one call: on a few hundred
points NumPy's per-call overhead was most of the server's feature stage. It
gives NumPy's numbers to the bit (tests/deepcontact/test_kinematics.py keeps
the NumPy implementation as the reference), so what models were trained on
is what they are served. The probes' dense linear algebra (contact_jacobian,
body_space_part) stays in NumPy on a ContactFrame.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE

try:
    from deepcontact import _kinematics as _compiled
except ImportError as exc:  # pragma: no cover - a checkout that was never set up
    raise ImportError(
        "deepcontact's compiled kinematics (deepcontact/_kinematics.c) are not built: "
        "run `make setup` (or `pip install -e .`)"
    ) from exc

BODY_DYNAMIC = 2

#: The record fields the compiled kernel reads, by the offsets it was built with.
_LAYOUT = (
    (BODY_DTYPE, _compiled.BODY_SIZE, {"type": _compiled.BODY_TYPE, "position": _compiled.BODY_POSITION,
                                       "velocity": _compiled.BODY_VELOCITY,
                                       "angular_velocity": _compiled.BODY_ANGULAR_VELOCITY,
                                       "mass": _compiled.BODY_MASS, "inertia": _compiled.BODY_INERTIA}),
    (CONTACT_DTYPE, _compiled.POINT_SIZE, {"body_a": _compiled.POINT_BODY_A, "body_b": _compiled.POINT_BODY_B,
                                           "point": _compiled.POINT_POINT, "normal": _compiled.POINT_NORMAL,
                                           "builtin": _compiled.POINT_BUILTIN}),
)
for _dtype, _size, _offsets in _LAYOUT:
    if _dtype.itemsize != _size or any(_dtype.fields[f][1] != o for f, o in _offsets.items()):
        raise ImportError("deepcontact/_kinematics.c reads records laid out otherwise than deepcontact.records: "
                          "rebuild it (`make setup`) after changing either")
_EMPTY = np.zeros(0)


@dataclasses.dataclass(frozen=True)
class Physics:
    """What the solver adds to the bodies' velocities before the first iteration.

    dt: time step (s); gravity: (gx, gy) (m/s^2). Physics() is no gravity at all.
    """

    dt: float = 0.0
    gravity: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def thesis(cls) -> "Physics":
        return cls(0.01, (0.0, -9.8))


def _inverse(x: np.ndarray, dynamic: np.ndarray) -> np.ndarray:
    """1/x for dynamic bodies with x > 0, else 0 (static bodies have infinite mass)."""
    ok = dynamic & (x > 0)
    return np.where(ok, 1.0 / np.where(ok, x, 1.0), 0.0)


def _cross(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """2-D cross product r x v of (N, 2) arrays: (N,)."""
    return r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]


@dataclasses.dataclass(frozen=True)
class ContactFrame:
    """What every quantity at a step's contact points starts from, computed once.

    a, b: (P,) body rows of each point; dynamic (B,) bool; inv_mass (B,) 1/kg and
    inv_inertia (B,) 1/(kg m^2), 0 for bodies that are not dynamic; n, t (P, 2)
    normal and tangent; ra, rb (P, 2) m, the point relative to each body's centre.
    """

    a: np.ndarray
    b: np.ndarray
    dynamic: np.ndarray
    inv_mass: np.ndarray
    inv_inertia: np.ndarray
    n: np.ndarray
    t: np.ndarray
    ra: np.ndarray
    rb: np.ndarray


def contact_frame(bodies: np.ndarray, points: np.ndarray) -> ContactFrame:
    """The ContactFrame of points (P,) CONTACT_DTYPE between bodies (B,) BODY_DTYPE."""
    a = points["body_a"].astype(np.intp)
    b = points["body_b"].astype(np.intp)
    if len(points) and (a.min() < 0 or b.min() < 0 or max(a.max(), b.max()) >= len(bodies)):
        raise ValueError(f"contact points name bodies outside 0..{len(bodies) - 1}")
    dynamic = bodies["type"] == BODY_DYNAMIC
    centre = bodies["position"].astype(np.float64)
    p = points["point"].astype(np.float64)
    n = points["normal"].astype(np.float64)
    return ContactFrame(a, b, dynamic, _inverse(bodies["mass"].astype(np.float64), dynamic),
                        _inverse(bodies["inertia"].astype(np.float64), dynamic), n,
                        np.stack([n[:, 1], -n[:, 0]], axis=1), p - centre[a], p - centre[b])


def after_impulses(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray) -> np.ndarray:
    """A copy of bodies (B,) BODY_DTYPE with their velocities after impulses (P, 2) N s
    (normal, tangent) act at points (P,) CONTACT_DTYPE: +P on body B, -P on body A, on
    dynamic bodies only (the others take no impulse). What a contact problem solved
    around fixed impulses at some points starts from."""
    f = contact_frame(bodies, points)
    push = impulses[:, :1] * f.n + impulses[:, 1:] * f.t  # (P, 2) N s, on B
    n_bodies = len(bodies)
    dv = np.zeros((n_bodies, 2))
    for k in range(2):  # x and y, each summed over the points of every body in one call
        dv[:, k] = (np.bincount(f.b, push[:, k], n_bodies) - np.bincount(f.a, push[:, k], n_bodies))
    dw = np.bincount(f.b, _cross(f.rb, push), n_bodies) - np.bincount(f.a, _cross(f.ra, push), n_bodies)
    out = bodies.copy()
    out["velocity"] += (dv * f.inv_mass[:, None]).astype(np.float32)
    out["angular_velocity"] += (dw * f.inv_inertia).astype(np.float32)
    return out


def _records(array: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """`array` as C-contiguous records of `dtype` (no copy when it already is)."""
    if array.dtype == dtype and array.flags.c_contiguous:
        return array
    needed = {"bodies": _LAYOUT[0][2], "points": _LAYOUT[1][2]}[what]
    missing = sorted(set(needed) - set(array.dtype.names or ()))
    if missing:
        raise ValueError(f"{what} lack the fields {missing}")
    out = np.zeros(len(array), dtype)
    for name in needed:
        out[name] = array[name]
    return out


def _kinematics(bodies: np.ndarray, points: np.ndarray, physics: Physics, warm, velocities: bool,
                warmed: bool, masses: bool) -> tuple[np.ndarray | None, np.ndarray | None, np.ndarray | None]:
    """One call of the compiled kernel: the outputs asked for, (P, 2) float64 each, or None.

    warm: None, (P, 2) impulses (N s), or "builtin" for the points' own builtin field,
    read in place."""
    bodies = _records(np.asarray(bodies), BODY_DTYPE, "bodies")
    points = _records(np.asarray(points), CONTACT_DTYPE, "points")
    n_points = len(points)
    if warm is None:
        mode, given = _compiled.WARM_NONE, _EMPTY
    elif isinstance(warm, str):
        if warm != "builtin":
            raise ValueError(f"warm must be impulses or 'builtin', got {warm!r}")
        mode, given = _compiled.WARM_BUILTIN, _EMPTY
    else:
        given = np.ascontiguousarray(warm, np.float64)
        if given.shape != (n_points, 2):
            raise ValueError(f"warm must be ({n_points}, 2), got {given.shape}")
        mode = _compiled.WARM_GIVEN
    out = [np.empty((n_points, 2)) if want else None for want in (velocities, warmed, masses)]
    gx, gy = physics.gravity
    _compiled.point_kinematics(bodies, len(bodies), points, n_points, mode, given, float(physics.dt), float(gx),
                               float(gy), *(_EMPTY if o is None else o for o in out))
    return out[0], out[1], out[2]


def contact_velocities(bodies: np.ndarray, points: np.ndarray, warm: np.ndarray | None = None,
                       physics: Physics = Physics()) -> np.ndarray:
    """Relative (normal, tangent) velocity at each contact point, (P, 2) float64 m/s.

    bodies: (B,) BODY_DTYPE indexed by the points' body_a/body_b.
    points: (P,) CONTACT_DTYPE (point, normal, body_a, body_b are read).
    warm: optional (P, 2) (normal, tangent) impulses, N s, applied to the
        bodies first, as Box2D applies a warm start.
    physics: this step's gravity and time step, added to dynamic bodies first.
    """
    before, after, _ = _kinematics(bodies, points, physics, warm, warm is None, warm is not None, False)
    return before if warm is None else after


def effective_masses(bodies: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Each point's effective mass along its normal and its tangent, (P, 2) float64 kg.

    k = 1 / (1/m_A + 1/m_B + (r_A x d)^2 / I_A + (r_B x d)^2 / I_B) for the
    direction d (normal, then tangent): the impulse that changes the relative
    velocity along d by 1 m/s when this point acts alone, Box2D's normalMass
    and tangentMass. A point between two bodies that cannot move gets 0.
    bodies, points: as in contact_velocities.
    """
    return _kinematics(bodies, points, Physics(), None, False, False, True)[2]


def contact_physics(bodies: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the contact problem's operator J M^-1 J^T is made of, float32, as a contact-graph
    network with probes reads it (training/graph_model.py): geometry (P, 8), the normal, the
    tangent and the point relative to the centres of A and of B (m); masses (P, 2), the
    effective masses (kg, effective_masses); inverse (B, 2), each body's 1/mass (1/kg) and
    1/inertia (1/(kg m^2)), 0 for bodies that are not dynamic. bodies, points: as in
    contact_velocities. Training data and the server both take them from here."""
    frame = contact_frame(bodies, points)
    geometry = np.concatenate([frame.n, frame.t, frame.ra, frame.rb], axis=1).astype(np.float32)
    inverse = np.stack([frame.inv_mass, frame.inv_inertia], axis=1).astype(np.float32)
    return geometry, effective_masses(bodies, points).astype(np.float32), inverse


def contact_quantities(bodies: np.ndarray, points: np.ndarray,
                       physics: Physics = Physics()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What the point channels read, in one pass: (velocities, velocities after the
    points' builtin warm start, effective masses), each (P, 2) float64 (m/s, m/s, kg),
    equal to contact_velocities(bodies, points, physics=physics),
    contact_velocities(bodies, points, points["builtin"], physics) and
    effective_masses(bodies, points)."""
    return _kinematics(bodies, points, physics, "builtin", True, True, True)


def contact_jacobian(bodies: np.ndarray, points: np.ndarray, frame: ContactFrame | None = None):
    """J^T as a dense (3 D, 2 P) float64 matrix: what point impulses do to the bodies.

    Column 2 i is point i's normal direction and 2 i + 1 its tangent; rows are
    the D dynamic bodies' (x, y, angular) generalized impulses (N s, N s,
    N m s) in the order of `np.flatnonzero(frame.dynamic)`. A (P, 2) impulse
    array `c` reaches the bodies as `J^T @ c.ravel()`. Dense on purpose: it is
    for probes and small worlds (a few hundred points), not the serving path.
    bodies, points, frame: as in contact_velocities.
    """
    f = contact_frame(bodies, points) if frame is None else frame
    row = np.full(len(f.dynamic), -1)
    row[f.dynamic] = np.arange(int(f.dynamic.sum()))
    jt = np.zeros((3 * int(f.dynamic.sum()), 2 * len(points)))
    cols = np.arange(len(points))
    for k, d in enumerate((f.n, f.t)):  # two directions, not a loop over points
        for body, r, sign in ((f.b, f.rb, 1.0), (f.a, f.ra, -1.0)):
            on = row[body] >= 0
            base, col = 3 * row[body[on]], 2 * cols[on] + k
            jt[base, col] += sign * d[on, 0]
            jt[base + 1, col] += sign * d[on, 1]
            jt[base + 2, col] += sign * _cross(r[on], d[on])
    return jt


def contact_jacobian_sparse(frame: ContactFrame):
    """contact_jacobian as a scipy.sparse CSR matrix (3 D, 2 P), built without the dense one:
    at most six entries a column (three for each dynamic body of the point). The serving
    path's form (nearest_admissible, solve_on_face); built once per frame and kept on it,
    so a step's solve and admission share it."""
    cached = frame.__dict__.get("_sparse_jacobian")
    if cached is None:
        cached = _jacobian_sparse(frame)
        object.__setattr__(frame, "_sparse_jacobian", cached)  # a cache on a frozen frame, not a field
    return cached


def _jacobian_sparse(f: ContactFrame):
    from scipy import sparse

    row = np.full(len(f.dynamic), -1)
    row[f.dynamic] = np.arange(int(f.dynamic.sum()))
    cols = np.arange(len(f.n))
    r_all, c_all, v_all = [], [], []
    for k, d in enumerate((f.n, f.t)):  # two directions and two bodies, not a loop over points
        for body, r, sign in ((f.b, f.rb, 1.0), (f.a, f.ra, -1.0)):
            on = row[body] >= 0
            base, col = 3 * row[body[on]], 2 * cols[on] + k
            r_all += [base, base + 1, base + 2]
            c_all += [col] * 3
            v_all += [sign * d[on, 0], sign * d[on, 1], sign * _cross(r[on], d[on])]
    shape = (3 * int(f.dynamic.sum()), 2 * len(f.n))
    if not r_all:
        return sparse.csr_matrix(shape)
    # coo -> csr sums duplicates, as contact_jacobian's += does (a point between two parts of one body)
    return sparse.csr_matrix((np.concatenate(v_all), (np.concatenate(r_all), np.concatenate(c_all))), shape=shape)


def body_space_part(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray,
                    frame: ContactFrame | None = None) -> np.ndarray:
    """The least-norm point impulses that move the bodies as `impulses` do, (P, 2) N s.

    impulses: (P, 2) (normal, tangent) N s. The result r has J^T r = J^T impulses
    (the same net impulse and torque on every dynamic body, so the same velocities
    after it is applied) and is orthogonal to every self-stress, the impulses with
    J^T s = 0 that move no body. impulses - r is the self-stress part: in a pile
    held at more points than its bodies have freedoms it is not fixed by the
    bodies' motion at all.
    """
    if len(points) == 0:
        return np.zeros((0, 2))
    jt = contact_jacobian(bodies, points, frame)
    c = np.asarray(impulses, np.float64).ravel()
    y, *_ = np.linalg.lstsq(jt.T, c, rcond=None)  # min |J y - c|: J y is c's part in range(J)
    return (jt.T @ y).reshape(-1, 2)


def body_space_part_of(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray, chosen: np.ndarray,
                       frame: ContactFrame | None = None) -> np.ndarray:
    """The least-norm point impulses that move the `chosen` bodies as `impulses` do and
    no other body, (P, 2) N s.

    impulses: (P, 2) (normal, tangent) N s; chosen: (B,) bool over `bodies`. The result
    r has J^T r = J^T impulses on every chosen dynamic body and J^T r = 0 on the others
    (in the least-squares sense where a body's points cannot push it every way); with
    every body chosen it is body_space_part. It splits a change of motion between bodies.
    """
    if len(points) == 0:
        return np.zeros((0, 2))
    f = contact_frame(bodies, points) if frame is None else frame
    jt = contact_jacobian(bodies, points, f)
    keep = np.repeat(np.asarray(chosen, bool)[f.dynamic], 3)  # rows: (x, y, angular) of each dynamic body
    target = np.where(keep, jt @ np.asarray(impulses, np.float64).ravel(), 0.0)
    r, *_ = np.linalg.lstsq(jt, target, rcond=None)  # the least-norm r with J^T r = target
    return r.reshape(-1, 2)


#: Below this speed (m/s) a body counts as at rest (points_at_rest): about what gravity adds
#: in a step of 1 ms, far below a falling body's and far above a settled pile's drift.
REST_SPEED = 0.01


def points_at_rest(bodies: np.ndarray, points: np.ndarray, speed: float = REST_SPEED) -> np.ndarray:
    """(P,) bool: the points whose dynamic bodies both move slower than `speed` (m/s,
    linear velocity as recorded). A point on a settled pile: its bodies' velocities, and
    what a model reads from them, are near 0 there."""
    moving = bodies_moving(bodies, speed)
    return ~(moving[points["body_a"]] | moving[points["body_b"]])


def bodies_moving(bodies: np.ndarray, speed: float = REST_SPEED) -> np.ndarray:
    """(B,) bool: the dynamic bodies whose recorded linear velocity is `speed` (m/s) or more."""
    return (np.hypot(*bodies["velocity"].T) >= speed) & (bodies["type"] == BODY_DYNAMIC)


def project_to_cones(impulses: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """The nearest impulses inside each point's friction cone, (P, 2) N s.

    impulses: (P, 2) (normal, tangent) N s; mu: (P,) friction coefficients. The
    cone is Box2D's: normal >= 0 and |tangent| <= mu normal, a wedge in the
    (normal, tangent) plane. A point outside it goes to the nearer edge, or to 0
    where it lies in the wedge's polar cone (normal + mu |tangent| <= 0).
    """
    c = np.asarray(impulses, np.float64)
    n, t = c[:, 0], c[:, 1]
    inside = np.abs(t) <= mu * n
    along = np.maximum(n + mu * np.abs(t), 0.0) / (1.0 + mu * mu)  # length along the edge (1, +-mu)
    out = np.stack([along, np.sign(t) * mu * along], axis=1)
    return np.where(inside[:, None], c, out)


def nearest_admissible(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray, mu: np.ndarray,
                       open_points: np.ndarray | None = None, iterations: int = 1000, tolerance: float = 1e-5,
                       rho: float = 100.0, frame: ContactFrame | None = None,
                       until: float | None = None) -> np.ndarray:
    """The impulses nearest `impulses` that move the bodies as they do and that every
    point's limits admit, (P, 2) N s.

    impulses: (P, 2) (normal, tangent) N s; mu: (P,) friction coefficients;
    open_points: optional (P,) bool, points held at no impulse (contacts that let go).
    The answer differs from `impulses` by a self-stress only (J^T x = J^T c, to
    `tolerance`), chosen as small as possible: the load moved around a pile that
    takes a start off its limits without changing what it does to any body.

    The problem is min |x - c|^2 over the affine set J^T x = J^T c and the cones, a
    small quadratic program; it is solved by ADMM with the two projections as its
    steps (x onto the affine set, z onto the cones), at most `iterations` rounds,
    stopping when x and z agree, and z moved, by under `tolerance` N s at every
    point. `rho` is ADMM's penalty: large, because the distance to c only picks
    among the admissible points and reaching the set is what counts (on a settled
    pile rho = 100 converges in a few hundred rounds, rho = 1 in thousands).
    Where no such impulses exist (a body held at one point whose push leaves the
    cone) it ends at the cones' point nearest the affine set. `until` (time.perf_counter() s;
    None: none) stops the rounds there, whatever they have reached (checked every 8 rounds; the
    first 8 always run): a served step's deadline. The answer is z:
    inside the cones always. J^T J is factorized once (a Cholesky factor in the envelope
    of a reverse Cuthill-McKee order of the bodies, admission_factors) and the rounds run
    compiled (deepcontact/_kinematics.c; tests/deepcontact/test_kinematics.py keeps the
    NumPy rounds as the reference): a few microseconds a round at 140 points, where NumPy's
    were about 0.1 ms.
    """
    c = np.asarray(impulses, np.float64)
    if len(points) == 0:
        return np.zeros((0, 2))
    keep = np.ones(len(points)) if open_points is None else (~np.asarray(open_points, bool)).astype(np.float64)
    if np.array_equal(project_to_cones(c, mu) * keep[:, None], c):
        # Admissible as it is (half of a thesis world's steps under 100 points solved on their labels,
        # `deepcontact bench face-solve`):
        # the rounds would end in the first, at c, after a factorization that costs more than they do.
        return c.copy()
    f = contact_frame(bodies, points) if frame is None else frame
    jt, rows, factors, perms = admission_factors(f)
    z = np.empty(2 * len(points))
    _compiled.admission_rounds(*jt, rows, *factors, *perms, np.ascontiguousarray(c.ravel()),
                               np.ascontiguousarray(mu, np.float64), keep, float(rho), int(iterations),
                               float(tolerance), _monotonic(until), z)
    return z.reshape(-1, 2)


def admission_factors(frame: ContactFrame) -> tuple[list, int, list, list]:
    """nearest_admissible's factorization of J^T J for a frame, as its compiled rounds take it:
    (J^T's CSR arrays, its rows 3 D, the sparse L and U factors' CSC arrays, their row and column
    permutations). It depends on the frame only, not on the impulses to admit: computed once per
    frame and kept on it. The factor is Cholesky's, in C (_kinematics.envelope_cholesky), in the
    envelope of a reverse Cuthill-McKee order of the bodies: about 0.4 against SciPy's SuperLU's
    0.8-0.9 ms at the thesis world's largest steps (300 rows), most of that SciPy's building and
    converting of sparse matrices; the envelope holds about twice SuperLU's entries, so the
    rounds walk more (0.7 against 0.55 ms for 60). (Begun on a thread of its own while a
    server's classifier ran, SuperLU's took nothing off the route on two cores: the GIL's share
    of it was most of it.)"""
    cached = frame.__dict__.get("_admission_factors")
    if cached is None:
        cached = _admission_factors(frame)
        object.__setattr__(frame, "_admission_factors", cached)  # a cache on a frozen frame, not a field
    return cached


def _admission_factors(f: ContactFrame) -> tuple[list, int, list, list]:
    jt = contact_jacobian_sparse(f)  # at most six entries a column
    rows, cols = jt.shape
    i32 = np.int32
    jt_arrays = [jt.indptr.astype(i32), jt.indices.astype(i32), np.ascontiguousarray(jt.data, np.float64)]
    if not rows:  # no dynamic body: nothing to keep
        return jt_arrays, rows, [np.zeros(1, i32), np.zeros(0, i32), np.zeros(0)] * 2, [np.zeros(0, i32)] * 2
    # J^T J couples two bodies where a point touches both: ordered so (reverse Cuthill-McKee on
    # the bodies) its Cholesky factor stays in a narrow envelope, which each round walks twice.
    order = np.ascontiguousarray((3 * _body_order(f)[:, None] + np.arange(3)).ravel(), i32)
    room = rows * (rows + 1) // 2
    lp, up, inverse = np.empty(rows + 1, i32), np.empty(rows + 1, i32), np.empty(rows, i32)
    li, ui, ld, ud = np.empty(room, i32), np.empty(room, i32), np.empty(room), np.empty(room)
    # J^T J is singular where a body's points cannot push it every way (one point, or none);
    # a ridge far below its scale lets one factorization serve, and what it adds in those
    # directions J takes away again.
    entries = _compiled.envelope_cholesky(*jt_arrays, rows, cols, order, 1e-9, lp, li, ld, up, ui, ud, inverse)
    factors = [lp, li[:entries].copy(), ld[:entries].copy(), up, ui[:entries].copy(), ud[:entries].copy()]
    return jt_arrays, rows, factors, [inverse, inverse]


def _body_order(f: ContactFrame) -> np.ndarray:
    """The dynamic bodies (as numbered by contact_jacobian's rows) in reverse Cuthill-McKee
    order of the graph that joins two bodies where a point touches both."""
    from scipy import sparse
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    n_dynamic = int(f.dynamic.sum())
    row = np.full(len(f.dynamic), -1)
    row[f.dynamic] = np.arange(n_dynamic)
    a, b = row[f.a], row[f.b]
    both = (a >= 0) & (b >= 0)
    graph = sparse.csr_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n_dynamic, n_dynamic))
    return reverse_cuthill_mckee(graph + graph.T, symmetric_mode=True).astype(np.int64)


def _monotonic(until: float | None) -> float:
    """A time.perf_counter() instant as time.monotonic()'s (the compiled rounds read that clock,
    CLOCK_MONOTONIC); 0.0 for None."""
    if until is None:
        return 0.0
    return max(1e-9, until - time.perf_counter() + time.monotonic())


#: contact_face's labels: a point that lets go (no impulse), sticks (both velocities 0),
#: or slides with its friction at the cone's edge, pushing along +t or -t.
OPEN, STICKS, SLIDES_PLUS, SLIDES_MINUS = 0, 1, 2, 3
#: A label written as an impulse (N s): a classifier's answer along the normal where a point
#: presses, and +-this along the tangent where it slides (deepcontact.channels' face targets).
FACE_IMPULSE = 1.0


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
                physics: Physics = Physics(), slack: float = 1e-4) -> np.ndarray:
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
    usually finds them, each a solve on the new labels.
    """
    face = contact_face(impulses, mu)
    after = contact_velocities(bodies, points, np.asarray(impulses, np.float64), physics)  # (P, 2) m/s
    # Friction pushes against the slip: +t (SLIDES_PLUS) only while the point moves along -t.
    wrong_way = ((face == SLIDES_PLUS) & (after[:, 1] > slack)) | ((face == SLIDES_MINUS) & (after[:, 1] < -slack))
    face[((face == OPEN) & (after[:, 0] < -slack)) | wrong_way] = STICKS
    return face


def solve_on_face(bodies: np.ndarray, points: np.ndarray, face: np.ndarray, mu: np.ndarray,
                  physics: Physics = Physics(), frame: ContactFrame | None = None,
                  damping: float = 0.0, solver: str = "gelsy") -> np.ndarray:
    """The step's contact problem solved as if its solution lay on `face`, (P, 2) N s.

    face: (P,) contact_face labels; mu: (P,) friction coefficients; bodies, points,
    physics as in contact_velocities (restitution 0, as the scenes build). The
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
    velocity = contact_velocities(bodies, points, physics=physics).ravel()  # (2P,) m/s before any impulse
    system, rows, slide = face_system(f, face, mu)
    x = _least_squares(system, -velocity[rows], damping, solver)
    out = np.zeros((n_points, 2))
    out[pressing, 0] = x[:len(pressing)]
    out[pressing, 1] = slide * x[:len(pressing)]
    out[sticking, 1] = x[len(pressing):]
    return out


def face_system(frame: ContactFrame, face: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """solve_on_face's linear system on a face's unknowns: (system (m, m) m/s per N s, rows (m,),
    slide (k,)).

    face: (P,) contact_face labels; mu: (P,) friction coefficients. The k pressing points'
    normal impulses come first, then the sticking points' tangent ones; a sliding point's
    column is its normal column plus its tangent one times slide (+-mu). rows are the
    equations' indices into the (2P,) relative velocities (normal 2 i, tangent 2 i + 1), in the
    unknowns' order. The same numbers as contact_operator's rows and columns combined so, summed
    over the pairs of points that share a dynamic body (a few thousand) without the (2P, 2P)
    operator (at 160 points that one and its fancy indexing took about 2 ms, and the pairs in
    NumPy about 1 ms), compiled (deepcontact/_kinematics.c).
    """
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
    system = np.zeros((m, m))
    f, i64 = frame, np.int64
    _compiled.face_system_sum(f.a.astype(i64), f.b.astype(i64), np.ascontiguousarray(f.dynamic, np.uint8),
                              *(np.ascontiguousarray(x, np.float64) for x in (f.inv_mass, f.inv_inertia, f.n, f.t,
                                                                              f.ra, f.rb)),
                              index.astype(i64).ravel(), np.ascontiguousarray(slide_of), m, system)
    rows = np.concatenate([2 * pressing, 2 * sticking + 1])
    return system, rows, slide_of[pressing]


#: solve_on_face's ways to the minimum-norm least-squares solution.
SOLVERS = ("gelsy", "dual")


def _least_squares(system: np.ndarray, rhs: np.ndarray, damping: float, solver: str = "gelsy") -> np.ndarray:
    """solve_on_face's solve of system (m, m) x = rhs (m,): minimum-norm least squares
    (damping 0, by `solver`) or damped, as solve_on_face says."""
    import scipy.linalg

    if damping > 0:
        normal = system.T @ system
        normal.flat[::len(normal) + 1] += damping * float(np.abs(system).max()) ** 2
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(normal, check_finite=False), system.T @ rhs,
                                          check_finite=False)
        except np.linalg.LinAlgError:  # a damping below the product's rounding: the exact route
            pass
    if solver not in SOLVERS:
        raise ValueError(f"solver: one of {SOLVERS}, got {solver!r}")
    x = minimum_norm_solve(system, rhs) if solver == "dual" else None
    if x is None:  # gelsy asked for, or a system far from consistent
        x = scipy.linalg.lstsq(system, rhs, lapack_driver="gelsy", check_finite=False)[0]
    return x


#: minimum_norm_solve's ridge on S S^T, relative to its mean diagonal: far below the singular
#: values that a face's system resolves, far above what S S^T's rounding leaves in its null
#: space. A face's system has a clean gap between the two: on the thesis world's largest steps
#: (seed 903, the default's labels) its singular values are above about 1e-6 of the largest or
#: below 1e-12, the right-hand side nowhere in the latter (`deepcontact bench face-solve`).
DUAL_RIDGE = 1e-15
#: minimum_norm_solve's rounds of iterative refinement on S S^T y = b, each from the ridged
#: factor: squaring S squares its condition (1e12 where a singular value is 1e-6 of the
#: largest), so one solve is good to about 1e-4 in S's weakest directions; each round takes
#: that error down about as far again, for two matrix-vector products and two triangular
#: solves (a few per cent of the factorization).
DUAL_REFINEMENTS = 2
#: minimum_norm_solve's test of its answer: |S^T (S x - b)| at most this times |S^T b|.
DUAL_OPTIMALITY = 1e-6


def minimum_norm_solve(system: np.ndarray, rhs: np.ndarray) -> np.ndarray | None:
    """The minimum-norm solution of a consistent, possibly singular, system S (m, m) x = b (m,),
    through its dual: x = S^T y with S S^T y = b, solved by Cholesky of S S^T + r I (r =
    DUAL_RIDGE times the mean of its diagonal; gesv's LU where rounding leaves a pivot below
    zero) and DUAL_REFINEMENTS rounds of iterative refinement. Whatever y picks up in S S^T's
    null space S^T sends to 0, so a tiny ridge serves. A face's system is singular in every
    pile (more points than freedoms) and consistent where the face is the solution's.

    It is the pseudo-inverse's solution with singular values below about 3e-8 of the largest
    taken as zero: on the thesis world's faces it agrees with numpy's pinv at rcond 1e-10
    better than LAPACK's gelsy does, which keeps directions down to machine precision and on
    about 2 % of the large steps adds an answer along one that is rounding (`deepcontact bench
    face-solve` prints both distances). S S^T is summed from S's nonzeros in C
    (_kinematics.sparse_gram; S is about 3 % full); the whole is three to four times cheaper
    than gelsy at 300 unknowns. None where the answer is not a least-squares solution to
    DUAL_OPTIMALITY (a wrong face's inconsistent system, whose residual the ridge would blow
    up through y): the caller solves it otherwise.
    """
    from scipy.linalg import lapack

    m = len(rhs)
    if m == 0:
        return np.zeros(0)
    system = np.ascontiguousarray(system, np.float64)
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


def contact_operator(frame: ContactFrame) -> np.ndarray:
    """J M^-1 J^T as a dense (2 P, 2 P) float64 matrix, m/s per N s: the relative (normal,
    tangent) velocity at each point (rows 2 i, 2 i + 1) that a unit impulse at each point
    causes. Built from the pairs of points that share a dynamic body (_point_pairs), not from
    a product of Jacobians."""
    n_points = len(frame.n)
    i, j, blocks = _point_pairs(frame)
    at = (2 * i)[:, None, None] * (2 * n_points) + np.arange(2)[None, :, None] * (2 * n_points) \
        + (2 * j)[:, None, None] + np.arange(2)[None, None, :]
    return np.bincount(at.ravel(), blocks.ravel(), minlength=4 * n_points * n_points).reshape(2 * n_points, 2 * n_points)


def _point_pairs(frame: ContactFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every ordered pair of points (i, j) that push on one dynamic body, once per body they
    share: (i (Q,), j (Q,), blocks (Q, 2, 2) m/s per N s), blocks[q, d, e] the relative velocity
    along direction d (normal, tangent) at point i that a unit impulse along e at point j causes
    through that body. contact_operator is their sum; a thesis pile has a few thousand."""
    f = frame
    point, body, push = [], [], []  # each point's push on each of its dynamic bodies
    for b, r, sign in ((f.b, f.rb, 1.0), (f.a, f.ra, -1.0)):
        on = np.flatnonzero(f.dynamic[b])
        g = np.empty((len(on), 2, 3))  # (direction: normal, tangent) x (x, y, angular)
        for k, d in enumerate((f.n, f.t)):  # two directions, not a loop over points
            g[:, k, 0], g[:, k, 1], g[:, k, 2] = sign * d[on, 0], sign * d[on, 1], sign * _cross(r[on], d[on])
        point.append(on)
        body.append(b[on])
        push.append(g)
    point, body, push = np.concatenate(point), np.concatenate(body), np.concatenate(push)
    order = np.argsort(body, kind="stable")
    point, body, push = point[order], body[order], push[order]
    start = np.searchsorted(body, body, side="left")
    count = np.searchsorted(body, body, side="right") - start
    i = np.repeat(np.arange(len(body)), count)  # every ordered pair of pushes on one body
    j = start[i] + np.arange(len(i)) - np.repeat(np.cumsum(count) - count, count)
    inverse = np.stack([f.inv_mass, f.inv_mass, f.inv_inertia], axis=1)[body[i]]  # (pairs, 3)
    blocks = np.einsum("pdc,pc,pec->pde", push[i], inverse, push[j])  # (pairs, 2, 2)
    return point[i], point[j], blocks


def solved_on_labels(bodies: np.ndarray, points: np.ndarray, labels: np.ndarray, mu: np.ndarray,
                     physics: Physics = Physics(), pressing: float = 0.5, share: float = 1.0,
                     rounds: int = 1000, label_friction: float | None = None,
                     frame: ContactFrame | None = None, damping: float = 0.0,
                     solver: str = "gelsy", until: float | None = None,
                     close: float | None = None) -> tuple[np.ndarray, float]:
    """The warm start of the face route, (P, 2) N s: a classifier's answer read as labels,
    the step solved on them, the result admitted.

    labels: (P, 2) N s, a classifier's answer (train-graph --targets face: about 1 N s along
    the normal where a point presses, +-1 N s along the tangent where it slides), read by
    contact_face as pressing above `pressing` N s and sliding at `share` of its limit (at
    `label_friction` times the normal answer when given, whatever the point's friction); mu:
    (P,) friction coefficients; bodies, points, physics as in contact_velocities. The step
    is solved on those labels (solve_on_face, with its `damping` and `solver`) and moved by the smallest self-stress that
    every cone admits, the labels' open points held at 0 (nearest_admissible, at most
    `rounds` rounds, and none begun after `until`, perf_counter() s). The simulation client's
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
    is not this step's).
    """
    frame = contact_frame(bodies, points) if frame is None else frame
    read_at = mu if label_friction is None else np.full(len(points), float(label_friction))
    face = contact_face(labels, read_at, pressing=pressing, share=share)
    solved = solve_on_face(bodies, points, face, mu, physics, frame, damping, solver)
    if close is not None:
        closing = (face == OPEN) & (contact_velocities(bodies, points, solved, physics)[:, 0] < -close)
        if closing.any():
            relabelled = np.array(labels, np.float64, copy=True)
            # read pressing, and its tangent answer read against a pressing label's normal one
            relabelled[closing, 0] = max(FACE_IMPULSE, np.nextafter(pressing, np.inf))
            face = contact_face(relabelled, read_at, pressing=pressing, share=share)
            solved = solve_on_face(bodies, points, face, mu, physics, frame, damping, solver)
    admitted = nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, iterations=rounds, frame=frame,
                                  until=until)
    return admitted, face_residual(bodies, points, face, admitted, physics)


def face_residual(bodies: np.ndarray, points: np.ndarray, face: np.ndarray, impulses: np.ndarray,
                  physics: Physics = Physics()) -> float:
    """How far impulses (P, 2) N s leave a face's equations unmet: the norm of the relative
    velocity where the face (P,) labels ask for none (the normal where a point presses, the
    tangent where it sticks) and of the closing velocity where it says a point lets go, after
    the impulses, over the norm of the relative velocity at those points before any impulse.
    0 for a face the impulses meet exactly. bodies, points, physics as in contact_velocities."""
    before, after, _ = _kinematics(bodies, points, physics, np.asarray(impulses, np.float64), True, True, False)
    rows = np.concatenate([2 * np.flatnonzero(face != OPEN), 2 * np.flatnonzero(face == STICKS) + 1])
    left = np.concatenate([after.ravel()[rows], np.minimum(after[face == OPEN, 0], 0.0)])
    scale = float(np.linalg.norm(before))
    return float(np.linalg.norm(left)) / scale if scale > 0 else 0.0
