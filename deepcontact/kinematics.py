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
body_space_part, contact_operator) stays in NumPy on a ContactFrame.

What is built on these lives beside them: the admission of impulses into the friction
cones in deepcontact.admission, a step solved on a face of its limits (the face route's
solve) in deepcontact.faces.
"""

from __future__ import annotations

import dataclasses

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


def velocities_before_and_after(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray,
                                physics: Physics = Physics()) -> tuple[np.ndarray, np.ndarray]:
    """(before, after), each (P, 2) float64 m/s: the relative (normal, tangent) velocity at each
    point before any impulse and after `impulses` (P, 2) N s, in one compiled pass; equal to
    contact_velocities(bodies, points, physics=physics) and contact_velocities(bodies, points,
    impulses, physics). bodies, points, physics: as in contact_velocities."""
    before, after, _ = _kinematics(bodies, points, physics, np.asarray(impulses, np.float64), True, True, False)
    return before, after


def jacobi_change(bodies: np.ndarray, points: np.ndarray, impulses: np.ndarray, mu: np.ndarray,
                  physics: Physics = Physics(), masses: np.ndarray | None = None) -> float:
    """N s: the largest change one projected Jacobi step from `impulses` ((P, 2) N s, normal and
    tangent) would make at any point: each point alone given the impulse that stops its relative
    velocity after them (effective mass times it), the normal kept >= 0 and the tangent inside
    mu (P,) times the normal. The solver stops when a sweep changes no impulse by more than its
    threshold, so of two starts the one with the smaller change is nearer to where it stops; it
    sees no joints. masses: effective_masses(bodies, points), when already computed (P, 2) kg.
    bodies, points, physics: as in contact_velocities. 0.0 for a step without points."""
    if len(points) == 0:
        return 0.0
    start = np.asarray(impulses, np.float64)
    _, after = velocities_before_and_after(bodies, points, start, physics)
    m = effective_masses(bodies, points) if masses is None else masses
    moved = start - m * after
    normal = np.maximum(moved[:, 0], 0.0)
    limit = np.asarray(mu, np.float64) * normal
    tangent = np.clip(moved[:, 1], -limit, limit)
    return float(max(np.abs(normal - start[:, 0]).max(), np.abs(tangent - start[:, 1]).max()))


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
    path's form (deepcontact.admission's factorization); built once per frame and kept on it,
    so every admission of a step (the face route's retries) shares it."""
    cached = frame.__dict__.get("_sparse_jacobian")
    if cached is None:
        cached = _jacobian_sparse(frame)
        object.__setattr__(frame, "_sparse_jacobian", cached)  # a cache on a frozen frame, not a field
    return cached


def _jacobian_sparse(f: ContactFrame):
    from scipy import sparse

    indptr, indices, data = jacobian_transpose_arrays(f)
    return sparse.csr_matrix((data, indices, indptr), shape=(len(indptr) - 1, 2 * len(f.n)))


def jacobian_transpose_arrays(f: ContactFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """J^T as CSR arrays (indptr int32 (3 D + 1,), indices int32, data float64), D the
    dynamic bodies in row order, 2 P columns (each point's normal, then tangent), each row's
    columns increasing: contact_jacobian's nonzeros, compiled (_kinematics.jacobian_transpose;
    SciPy's COO-to-CSR took about 0.17 ms a step). Kept on the frame."""
    cached = f.__dict__.get("_jacobian_arrays")
    if cached is None:
        n_dynamic = int(f.dynamic.sum())
        row = np.full(len(f.dynamic), -1, np.int32)
        row[f.dynamic] = np.arange(n_dynamic, dtype=np.int32)
        rows, n_points = 3 * n_dynamic, len(f.n)
        indptr = np.empty(rows + 1, np.int32)
        indices, data = np.empty(12 * n_points, np.int32), np.empty(12 * n_points)
        i64 = np.int64
        nnz = _compiled.jacobian_transpose(f.a.astype(i64), f.b.astype(i64), row,
                                           *(np.ascontiguousarray(x, np.float64) for x in (f.n, f.t, f.ra, f.rb)),
                                           rows, indptr, indices, data)
        cached = (indptr, indices[:nnz].copy(), data[:nnz].copy())
        object.__setattr__(f, "_jacobian_arrays", cached)  # a cache on a frozen frame, not a field
    return cached


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

#: Box2D's b2_velocityThreshold (m/s): a point closing slower than this does not bounce.
VELOCITY_THRESHOLD = 1.0


def bounce(normal_velocity: np.ndarray, restitution: np.ndarray | None) -> np.ndarray:
    """(P,) m/s, >= 0: the normal velocity Box2D's solver holds each point at (b2ContactSolver's
    velocity bias): its restitution (P,) times its closing speed where its normal velocity
    before any impulse (P,) m/s closes faster than VELOCITY_THRESHOLD, else 0; zeros where
    restitution is None. deepcontact/_route.c's geometry_build computes the same."""
    v = np.asarray(normal_velocity, np.float64)
    if restitution is None:
        return np.zeros_like(v)
    return np.where(v < -VELOCITY_THRESHOLD, -np.asarray(restitution, np.float64) * v, 0.0)


def points_at_rest(bodies: np.ndarray, points: np.ndarray, speed: float = REST_SPEED) -> np.ndarray:
    """(P,) bool: the points whose dynamic bodies both move slower than `speed` (m/s,
    linear velocity as recorded). A point on a settled pile: its bodies' velocities, and
    what a model reads from them, are near 0 there."""
    moving = bodies_moving(bodies, speed)
    return ~(moving[points["body_a"]] | moving[points["body_b"]])


def bodies_moving(bodies: np.ndarray, speed: float = REST_SPEED) -> np.ndarray:
    """(B,) bool: the dynamic bodies whose recorded linear velocity is `speed` (m/s) or more."""
    return (np.hypot(*bodies["velocity"].T) >= speed) & (bodies["type"] == BODY_DYNAMIC)


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

