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

from deepcontact.kinematics import ContactFrame, contact_frame, contact_jacobian_sparse

try:
    from deepcontact import _admission as _compiled
except ImportError as exc:  # pragma: no cover - a checkout that was never set up
    raise ImportError(
        "deepcontact's compiled admission (deepcontact/_admission.c) is not built: "
        "run `make setup` (or `pip install -e .`)"
    ) from exc


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
    frame and kept on it. The factor is Cholesky's, in C (_admission.envelope_cholesky), in the
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

