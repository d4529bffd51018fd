"""Impulses admitted into the friction cones: the nearest ones that move the bodies as given.

A warm start made of parts (Box2D's own plus a learned correction, or a step solved on a
face of its limits, deepcontact.faces) can leave friction outside its cone at some points
or pull where a contact can only push. A pile held at more points than its bodies have
freedoms has room to fix that without changing what the start does to any body: a
self-stress, impulses that move nothing (J^T s = 0). nearest_admissible finds the smallest
such change that takes every point into its cone:

    admitted = nearest_admissible(bodies, points, impulses, mu)      # (P, 2) N s
    admitted = nearest_admissible(..., open_points=face == OPEN, until=deadline)

Cones and conventions are Box2D's and deepcontact.kinematics's: (normal, tangent) per
point, normal >= 0 and |tangent| <= mu normal. The rounds and their factorization run
compiled (deepcontact/_admission.c, built by `make setup`);
tests/deepcontact/test_admission.py keeps NumPy's rounds as the reference.
"""

from __future__ import annotations

import time

import numpy as np

from deepcontact.kinematics import ContactFrame, contact_frame, jacobian_transpose_arrays

try:
    from deepcontact import _admission as _compiled
except ImportError as exc:  # pragma: no cover - a checkout that was never set up
    raise ImportError(
        "deepcontact's compiled admission (deepcontact/_admission.c) is not built: "
        "run `make setup` (or `pip install -e .`)"
    ) from exc


#: ADMM's penalty where a caller gives none: large, since reaching the admissible set is what
#: counts and the distance to the start only picks among its points (nearest_admissible).
ADMISSION_RHO = 100.0


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
                       rho: float = ADMISSION_RHO, frame: ContactFrame | None = None,
                       until: float | None = None, relax: float = 1.0) -> np.ndarray:
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
    pile rho = 100 converges in a few hundred rounds, rho = 1 in thousands). `relax` is the
    rounds' over-relaxation (1: plain ADMM; between 1 and 2 each round's affine step is pushed
    past its point, deepcontact/admission_kernels.h).
    Where no such impulses exist (a body held at one point whose push leaves the
    cone) it ends at the cones' point nearest the affine set. `until` (time.perf_counter() s;
    None: none) stops the rounds there, whatever they have reached (checked every 8 rounds; the
    first 8 always run): a served step's deadline. The answer is z:
    inside the cones always. J^T J is factorized once (a sparse Cholesky factor in a minimum
    degree order of the bodies, admission_factors) and the rounds run
    compiled (deepcontact/_admission.c; tests/deepcontact/test_admission.py keeps the
    NumPy rounds as the reference): a few microseconds a round at 140 points, where NumPy's
    were about 0.1 ms.
    """
    c = np.asarray(impulses, np.float64)
    if len(points) == 0:
        return np.zeros((0, 2))
    keep = np.ones(len(points)) if open_points is None else (~np.asarray(open_points, bool)).astype(np.float64)
    if np.array_equal(project_to_cones(c, mu) * keep[:, None], c):
        # Admissible as it is (half of a thesis world's steps under 100 points solved on their labels,
        # `deepcontact lab face-solve`):
        # the rounds would end in the first, at c, after a factorization that costs more than they do.
        return c.copy()
    f = contact_frame(bodies, points) if frame is None else frame
    jt, rows, factor, position = admission_factors(f)
    z = np.empty(2 * len(points))
    _compiled.admission_rounds(*jt, rows, *factor, position, np.ascontiguousarray(c.ravel()),
                               np.ascontiguousarray(mu, np.float64), keep, float(rho), int(iterations),
                               float(tolerance), float(relax), _monotonic(until), z)
    return z.reshape(-1, 2)


def admission_factors(frame: ContactFrame) -> tuple[list, int, list, np.ndarray]:
    """nearest_admissible's factorization of J^T J for a frame, as its compiled rounds take it:
    (J^T's CSR arrays, its rows 3 D, the Cholesky factor C's CSC arrays (lower, each column's
    diagonal first), each row's place in the factor's order). It depends on the frame only, not
    on the impulses to admit: computed once per frame and kept on it. The factor is a sparse
    Cholesky's (_admission.gram_cholesky, deepcontact/sparse_cholesky.h) in a minimum degree
    order of the bodies: about 0.1 ms at the thesis world's median step, and 3,100 entries at
    its largest, where the envelope factor it replaced held 8,000 (each round walks the factor
    twice); SciPy's SuperLU before that took 0.8-0.9 ms, most of it building and converting
    sparse matrices."""
    cached = frame.__dict__.get("_admission_factors")
    if cached is None:
        cached = _admission_factors(frame)
        object.__setattr__(frame, "_admission_factors", cached)  # a cache on a frozen frame, not a field
    return cached


def _admission_factors(f: ContactFrame) -> tuple[list, int, list, np.ndarray]:
    jt_arrays = list(jacobian_transpose_arrays(f))  # at most six entries a column
    rows, cols = len(jt_arrays[0]) - 1, 2 * len(f.n)
    i32 = np.int32
    # J^T J couples two bodies where a point touches both: ordered so (minimum degree on the
    # bodies) its Cholesky factor stays sparse. It is singular where a body's points cannot
    # push it every way (one point, or none); a ridge far below its scale lets one factorization
    # serve, and what it adds in those directions J takes away again.
    order = np.ascontiguousarray((3 * _body_order(f)[:, None] + np.arange(3)).ravel(), i32)
    lp, li, lx = _compiled.gram_cholesky(*jt_arrays, rows, cols, order, 1e-9)
    position = np.empty(rows, i32)
    position[order] = np.arange(rows, dtype=i32)
    factor = [np.frombuffer(lp, i32), np.frombuffer(li, i32), np.frombuffer(lx, np.float64)]
    return jt_arrays, rows, factor, position


def _body_order(f: ContactFrame) -> np.ndarray:
    """The dynamic bodies (as numbered by contact_jacobian's rows) in a minimum degree order of
    the graph that joins two bodies where a point touches both (compiled, _admission.body_order:
    SciPy's reverse Cuthill-McKee, with the sparse graph it needs, took about 0.15 ms a step)."""
    n_dynamic = int(f.dynamic.sum())
    row = np.full(len(f.dynamic), -1, np.int32)
    row[f.dynamic] = np.arange(n_dynamic, dtype=np.int32)
    order = np.empty(n_dynamic, np.int64)
    _compiled.body_order(f.a.astype(np.int64), f.b.astype(np.int64), row, n_dynamic, order)
    return order


def _monotonic(until: float | None) -> float:
    """A time.perf_counter() instant as time.monotonic()'s (the compiled rounds read that clock,
    CLOCK_MONOTONIC); 0.0 for None."""
    if until is None:
        return 0.0
    return max(1e-9, until - time.perf_counter() + time.monotonic())



class AdmissionCarry:
    """A stream's admission state between its steps, by contact point: the rounds of one step
    begin where the same point's ended on the step before (deepcontact/_route.c's carry), so
    that rounds cut short on every step add up along the stream where its points' problems move
    little from step to step. A point new to the stream, or any point after a gap of steps,
    begins cold.

        carry = AdmissionCarry()
        args = carry.begin(points, step)                 # what route_compiled's carry takes
        answer = faces.route_compiled(..., carry=args)
        carry.keep(points, step, args) if answer is not None else carry.forget()

    The rounds' iterate z is carried, their scaled dual s begun at 0 unless dual: the dual is the
    cones' reaction to the step's own start (the solve on this step's labels), which moves with
    the labels; carried too, it cost more sweeps than the cold start on the choosing seeds
    (lab.admission_carry).
    """

    __slots__ = ("_keys", "_state", "_step", "dual")

    def __init__(self, dual: bool = False):
        self._keys, self._state, self._step = np.empty(0, np.uint64), np.empty((0, 4)), None
        self.dual = dual

    def begin(self, points: np.ndarray, step: int) -> tuple:
        """route_compiled's carry for step `step`'s points (P,) CONTACT_DTYPE: (the keys (Q,)
        uint64 and the state (Q, 4) float64 kept on step - 1, none after a gap; the (P, 4)
        float64 buffer the rounds write this step's state to; dual)."""
        fresh = self._step is not None and self._step == step - 1
        keys, state = (self._keys, self._state) if fresh else (self._keys[:0], self._state[:0])
        return keys, state, np.empty((len(points), 4)), self.dual

    def keep(self, points: np.ndarray, step: int, carry: tuple) -> None:
        """Keep the state begin's buffer (carry[2]) got on step `step`, under its points' keys."""
        self._keys, self._state, self._step = np.ascontiguousarray(points["key"]), carry[2], step

    def forget(self) -> None:
        """Drop the state: the next step begins cold (a step the route did not serve)."""
        self._keys, self._state, self._step = self._keys[:0], self._state[:0], None
