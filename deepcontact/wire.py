"""NumPy <-> protobuf for the warm-start service (proto/deepcontact/v1).

Both sides use these functions: the client encodes a step from the engine's
records and decodes the reply; the server decodes the step into records for
the transfer and encodes impulses. Arrays travel as packed little-endian
float32 `bytes`, so encoding is a copy, not a Python loop.
"""

from __future__ import annotations

import functools

import numpy as np

from deepcontact.kinematics import Physics
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from deepcontact.v1 import warmstart_pb2 as pb

BODY_COLUMNS = ("x", "y", "angle", "vx", "vy", "omega", "mass", "radius")
POINT_COLUMNS = ("x", "y", "normal_x", "normal_y")
F32 = np.dtype("<f4")
I32 = np.dtype("<i4")

# x.all() runs a Python-level wrapper in NumPy; decoding is on the server's
# per-step path, so the ufunc reduction is called directly.
_all = functools.partial(np.logical_and.reduce, axis=None)


class WireError(ValueError):
    """A message whose arrays do not fit their declared counts or are not finite.
    `field` names the offending field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


# -- client side -------------------------------------------------------------

def encode_world(lower: tuple[float, float], upper: tuple[float, float],
                 edges: np.ndarray | None = None, physics: Physics | None = None,
                 tolerance: float = 0.0) -> pb.World:
    """Domain (m), static edges (E, 4) float (x0, y0, x1, y1), the step's physics and the
    solver's stopping rule (tolerance, N s; 0: not said)."""
    edges = np.zeros((0, 4), F32) if edges is None else np.ascontiguousarray(edges, F32).reshape(-1, 4)
    world = pb.World(x_min=lower[0], y_min=lower[1], x_max=upper[0], y_max=upper[1],
                     edge_count=len(edges), edges=edges.tobytes(), solver_tolerance=tolerance)
    if physics is not None:
        world.dt, (world.gravity_x, world.gravity_y) = physics.dt, physics.gravity
    return world


def encode_step(step: int, model: str, bodies: np.ndarray, points: np.ndarray, *,
                world: pb.World | None = None, builtin: np.ndarray | None = None,
                impulses: np.ndarray | None = None, friction: np.ndarray | None = None,
                joints: np.ndarray | None = None, revolute: np.ndarray | None = None,
                restitution: np.ndarray | None = None) -> pb.StepRequest:
    """A step from engine records.

    bodies: (B,) BODY_DTYPE in creation order, as the engine exports them
        (static bodies are left out: walls travel in World).
    points: (P,) CONTACT_DTYPE in export order; their bodies travel as rows of
        the dynamic bodies (-1 for static), with the separation and the keys.
    builtin, impulses: optional (P, 2) float (normal, tangent), N s.
    friction: optional (P,) each point's friction coefficient (Box2D's mix of its
        two fixtures'; the engine exports it as points["friction"]).
    joints: optional (J, 2) int each joint's body A and body B (engine body indices,
        Engine.joints); they travel as rows of the moving bodies (-1 for static).
    revolute: optional (J, 15) float32, with joints: each joint as the solve will hold it
        (Engine.revolute: its kind, its anchors on A and B (m), its impulse, then its limit and
        motor); or (J, 7), the first seven alone (no limits or motors sent).
    restitution: optional (P,) each point's restitution (Box2D's mix of its two fixtures', the
        larger; Engine.point_restitution); left out where no point has any.
    """
    moving = bodies["type"] != 0
    dyn = bodies[moving]
    b = np.empty((len(dyn), len(BODY_COLUMNS)), F32)
    b[:, 0:2] = dyn["position"]
    b[:, 2] = dyn["angle"]
    b[:, 3:5] = dyn["velocity"]
    b[:, 5] = dyn["angular_velocity"]
    b[:, 6] = dyn["mass"]
    b[:, 7] = dyn["radius"]
    p = np.empty((len(points), len(POINT_COLUMNS)), F32)
    p[:, 0:2] = points["point"]
    p[:, 2:4] = points["normal"]
    # The engine's body index is its row in `bodies`; on the wire a point names rows of the dynamic bodies.
    row_of = np.cumsum(moving, dtype=np.int32) - 1
    row_of[~moving] = -1
    rows = np.stack([row_of[points["body_a"]], row_of[points["body_b"]]], axis=1)
    msg = pb.StepRequest(step=step, model=model, body_count=len(dyn), bodies=b.tobytes(),
                         point_count=len(points), points=p.tobytes(),
                         point_bodies=rows.astype(I32).tobytes(),
                         point_separation=np.ascontiguousarray(points["separation"], F32).tobytes(),
                         body_inertia=np.ascontiguousarray(dyn["inertia"], F32).tobytes(),
                         point_keys=np.ascontiguousarray(points["key"], "<u8").tobytes())
    if world is not None:
        msg.world.CopyFrom(world)
    if builtin is not None:
        msg.builtin = np.ascontiguousarray(builtin, F32).tobytes()
    if impulses is not None:
        msg.impulses = np.ascontiguousarray(impulses, F32).tobytes()
    if friction is not None:
        msg.point_friction = np.ascontiguousarray(friction, F32).tobytes()
    if restitution is not None and np.any(restitution):
        msg.point_restitution = np.ascontiguousarray(restitution, F32).tobytes()
    if joints is not None and len(joints):
        msg.joint_count = len(joints)
        msg.joint_bodies = np.ascontiguousarray(row_of[np.asarray(joints)], I32).tobytes()
        if revolute is not None:
            revolute = np.asarray(revolute, F32)
            msg.joint_revolute = np.ascontiguousarray(revolute[:, :7]).tobytes()
            if revolute.shape[1] > 7:
                msg.joint_limits = np.ascontiguousarray(revolute[:, 7:]).tobytes()
    return msg


def decode_joint_impulses(reply: pb.Impulses, joint_count: int) -> np.ndarray | None:
    """The joints' start the reply carries, (joint_count, 2) float32 N s on each joint's body B
    (Engine.set_revolute_impulses takes it), or None: the joints keep their own."""
    if not reply.joint_impulses:
        return None
    xy = np.frombuffer(reply.joint_impulses, F32)
    if len(xy) != 2 * joint_count or not _all(np.isfinite(xy)):
        raise WireError("joint_impulses", f"reply carries {len(xy)} values for {joint_count} joints, or not finite")
    return xy.reshape(joint_count, 2)


def decode_impulses(reply: pb.Impulses) -> tuple[np.ndarray, np.ndarray]:
    """(normal (P,), tangent (P,)) float32, N s, in request order."""
    n = reply.point_count
    normal = np.frombuffer(reply.normal, F32)
    tangent = np.frombuffer(reply.tangent, F32)
    if len(normal) != n or len(tangent) != n:
        raise WireError("normal/tangent", f"reply carries {len(normal)}/{len(tangent)} values for {n} points")
    return normal, tangent


# -- server side -------------------------------------------------------------

def _array(msg, field: str, rows: int, cols: int, *, optional: bool = False,
           check: bool = True, dtype: np.dtype = F32) -> np.ndarray | None:
    raw = getattr(msg, field)
    if optional and not raw:
        return None
    expected = rows * cols * dtype.itemsize
    if len(raw) != expected:
        kind = {F32: "float32", I32: "int32"}.get(dtype, str(dtype))
        raise WireError(field, f"{len(raw)} bytes, expected {rows} x {cols} {kind} = {expected}")
    a = np.frombuffer(raw, dtype).reshape(rows, cols)
    if check:
        _check_finite(a, field)
    return a


def _check_finite(a: np.ndarray, field: str) -> None:
    if not _all(np.isfinite(a)):
        raise WireError(field, "holds NaN or infinite values")


def decode_world(world: pb.World) -> tuple[tuple[float, float], tuple[float, float], np.ndarray]:
    """(lower, upper, edges (E, 4) float32); WireError for an empty or non-finite domain."""
    lo = (world.x_min, world.y_min)
    hi = (world.x_max, world.y_max)
    if not np.isfinite(lo + hi).all() or not (hi[0] > lo[0] and hi[1] > lo[1]):
        raise WireError("world", f"domain ({lo[0]}, {lo[1]}) - ({hi[0]}, {hi[1]}) is empty or not finite")
    edges = _array(world, "edges", world.edge_count, 4)
    return lo, hi, edges


def decode_physics(world: pb.World) -> Physics:
    """The step's time and gravity; Physics() (no time, no gravity) when the client sent none."""
    values = (world.dt, world.gravity_x, world.gravity_y)
    if not np.isfinite(values).all() or world.dt < 0:
        raise WireError("world", f"dt {world.dt} and gravity ({world.gravity_x}, {world.gravity_y}) must be "
                                 "finite, dt >= 0")
    return Physics(float(world.dt), (float(world.gravity_x), float(world.gravity_y)))


def decode_tolerance(world: pb.World) -> float:
    """The client's stopping rule (N s), 0.0 when it sent none; WireError where it is not finite
    or below 0."""
    tolerance = world.solver_tolerance
    if not np.isfinite(tolerance) or tolerance < 0:
        raise WireError("world", f"solver_tolerance {tolerance} must be finite and >= 0 N s")
    return float(tolerance)


def _word(dtype: np.dtype, field: str, component: int = 0) -> int:
    """Index of a float32 field's component among a record's 4-byte words."""
    sub, offset = dtype.fields[field][:2]
    if sub.base != F32 or offset % 4:
        raise TypeError(f"{dtype}: field {field!r} is not an aligned little-endian float32")
    return offset // 4 + component


def _runs(words: list[int]) -> tuple[tuple[slice, slice], ...]:
    """[(record words, wire columns)]: the wire columns going to consecutive record words, as slice pairs."""
    runs, start = [], 0
    for j in range(1, len(words) + 1):
        if j == len(words) or words[j] != words[j - 1] + 1:
            runs.append((slice(words[start], words[j - 1] + 1), slice(start, j)))
            start = j
    return tuple(runs)


# Where the wire's columns go in the engine's records, viewed as rows of
# 4-byte words: decoding writes whole runs of columns at once into one zeroed
# (N, words) float32 block and views it as records, instead of assigning
# field by field (two to four NumPy calls instead of ten).
_BODY_RUNS = _runs([_word(BODY_DTYPE, f, c) for f, c in (
    ("position", 0), ("position", 1), ("angle", 0), ("velocity", 0), ("velocity", 1),
    ("angular_velocity", 0), ("mass", 0), ("radius", 0))])  # BODY_COLUMNS, in order
_POINT_RUNS = _runs([_word(CONTACT_DTYPE, f, c) for f, c in (
    ("point", 0), ("point", 1), ("normal", 0), ("normal", 1))])  # POINT_COLUMNS, in order
_BUILTIN_WORDS = slice(_word(CONTACT_DTYPE, "builtin"), _word(CONTACT_DTYPE, "builtin") + 2)
_IMPULSE_WORDS = slice(_word(CONTACT_DTYPE, "impulse"), _word(CONTACT_DTYPE, "impulse") + 2)
_SEPARATION_WORD = _word(CONTACT_DTYPE, "separation")
_INERTIA_WORD = _word(BODY_DTYPE, "inertia")
_BODY_AB_WORDS = slice(CONTACT_DTYPE.fields["body_a"][1] // 4, CONTACT_DTYPE.fields["body_a"][1] // 4 + 2)
if CONTACT_DTYPE.fields["body_b"][1] != CONTACT_DTYPE.fields["body_a"][1] + 4:  # pragma: no cover
    raise ImportError("deepcontact.wire expects body_b right after body_a in CONTACT_DTYPE")
_INDEX_WORD = BODY_DTYPE.fields["index"][1] // 4
_TYPE_WORD = BODY_DTYPE.fields["type"][1] // 4
if BODY_DTYPE.itemsize % 4 or CONTACT_DTYPE.itemsize % 4:  # pragma: no cover - records are all 4-byte words
    raise ImportError("deepcontact.records layouts do not fit deepcontact.wire's decoding")


def _zero_records(dtype: np.dtype, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zeroed (n,) records of dtype, and the same memory as (n, dtype.itemsize / 4)
    float32 words and as int32 words."""
    flat = np.zeros(n * (dtype.itemsize // 4), F32)
    # frombuffer, not flat.view(dtype): a view to a structured dtype runs a
    # Python-level safety check on every call.
    words = flat.reshape(n, dtype.itemsize // 4)
    return np.frombuffer(flat, dtype), words, np.frombuffer(flat, "<i4").reshape(words.shape)


def decode_step(msg: pb.StepRequest, *, max_bodies: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Records for the transfer and the channels, laid out as the engine's are.

    bodies: (B + 1,) BODY_DTYPE, a static stand-in for every wall at row 0,
        then the request's bodies (all dynamic), inertia filled when sent.
    points: (P,) CONTACT_DTYPE with point, normal, builtin and impulse filled
        (zero when absent), and, when sent, separation, key and body_a/body_b
        as rows of `bodies` (0: static).

    WireError names the bad field."""
    if msg.body_count > max_bodies:
        raise WireError("body_count", f"{msg.body_count} exceeds the server's limit of {max_bodies}")
    if msg.point_count > max_points:
        raise WireError("point_count", f"{msg.point_count} exceeds the server's limit of {max_points}")
    n_bodies, n_points = msg.body_count, msg.point_count
    b = _array(msg, "bodies", n_bodies, len(BODY_COLUMNS))
    inertia = _array(msg, "body_inertia", n_bodies, 1, optional=True)
    p = _array(msg, "points", n_points, len(POINT_COLUMNS), check=False)
    builtin = _array(msg, "builtin", n_points, 2, optional=True, check=False)
    impulses = _array(msg, "impulses", n_points, 2, optional=True, check=False)
    separation = _array(msg, "point_separation", n_points, 1, optional=True, check=False)
    rows = _array(msg, "point_bodies", n_points, 2, optional=True, check=False, dtype=I32)
    keys = _array(msg, "point_keys", n_points, 1, optional=True, check=False, dtype=np.dtype("<u8"))
    if rows is not None and n_points and (rows.min() < -1 or rows.max() >= n_bodies):
        raise WireError("point_bodies", f"names rows outside -1..{n_bodies - 1}")

    bodies, words, ints = _zero_records(BODY_DTYPE, n_bodies + 1)
    for dst, src in _BODY_RUNS:
        words[1:, dst] = b[:, src]
    if inertia is not None:
        words[1:, _INERTIA_WORD] = inertia[:, 0]
    ints[:, _INDEX_WORD] = np.arange(n_bodies + 1, dtype=np.int32)
    # Dynamic, or kinematic where the mass is 0 (Box2D gives every dynamic body a mass > 0): moved as
    # sent, never by an impulse. Row 0 stays 0, static: the walls travel as World edges.
    ints[1:, _TYPE_WORD] = np.where(b[:, 6] > 0, 2, 1)
    points, words, ints = _zero_records(CONTACT_DTYPE, n_points)
    for dst, src in _POINT_RUNS:
        words[:, dst] = p[:, src]
    if builtin is not None:
        words[:, _BUILTIN_WORDS] = builtin
    if impulses is not None:
        words[:, _IMPULSE_WORDS] = impulses
    if separation is not None:
        words[:, _SEPARATION_WORD] = separation[:, 0]
    # One finiteness check for the float arrays of the points (the record's
    # other words are zeros); which one is bad matters only when one is.
    if not _all(np.isfinite(words)):
        for field, a in (("points", p), ("builtin", builtin), ("impulses", impulses),
                         ("point_separation", separation)):
            if a is not None:
                _check_finite(a, field)
    if rows is not None:
        ints[:, _BODY_AB_WORDS] = rows + 1  # after the check: these words are integers
    if keys is not None:
        points["key"] = keys[:, 0]
    return bodies, points


def decode_restitution(msg: pb.StepRequest) -> np.ndarray | None:
    """Each point's restitution, (P,) float32, or None when the request sends none (no point
    bounces). WireError when it does not fit point_count or is negative or not finite."""
    return _per_point_coefficient(msg, "point_restitution")


def decode_friction(msg: pb.StepRequest) -> np.ndarray | None:
    """Each point's friction coefficient, (P,) float32, or None when the request sends none.
    WireError when it does not fit point_count or is negative or not finite."""
    return _per_point_coefficient(msg, "point_friction")


def _per_point_coefficient(msg: pb.StepRequest, field: str) -> np.ndarray | None:
    """A (P,) float32 field of one non-negative number a point, or None where it is empty."""
    values = _array(msg, field, msg.point_count, 1, optional=True)
    if values is None:
        return None
    if len(values) and values.min() < 0:
        raise WireError(field, "holds negative values")
    return values[:, 0]


def decode_joints(msg: pb.StepRequest) -> np.ndarray | None:
    """Each joint's two bodies as rows of decode_step's bodies (0: static), (J, 2) int32, or
    None when the request sends none. WireError when they do not fit joint_count or name
    rows outside the request's bodies."""
    if not msg.joint_count and not msg.joint_bodies:
        return None
    rows = _array(msg, "joint_bodies", msg.joint_count, 2, check=False, dtype=I32)
    if len(rows) and (rows.min() < -1 or rows.max() >= msg.body_count):
        raise WireError("joint_bodies", f"names rows outside -1..{msg.body_count - 1}")
    return rows + 1


#: The kinds of joint a request's joint_revolute names (its first column): 0 one the server's copy
#: of a step does not hold, 1 revolute, 2 rigid weld, 3 prismatic.
JOINT_KINDS = (0, 1, 2, 3)


def decode_revolute(msg: pb.StepRequest) -> np.ndarray | None:
    """Each joint as the step's solve will hold it (joint_revolute and joint_limits), (J, 15)
    float32: its kind (JOINT_KINDS); its anchors on body A and body B (world, m); the first two
    components of its impulse (a revolute or weld joint's point impulse on body B, world, N s; a
    prismatic joint's across its axis, N s, and angular, N m s); then its limit's state (0 off or
    inactive, 1 at its lower angle or translation, 2 at its upper, 3 equal limits), the limit's
    impulse, 1 where its motor is on, the motor's impulse, its largest torque (N m) or force (N),
    its speed and a prismatic joint's axis (world), all 0 where the request sends no limits. None
    when the request sends no joint_revolute. WireError when either does not fit joint_count, is
    not finite, or names a kind, state or motor outside theirs, or a negative torque."""
    if not msg.joint_revolute:
        if msg.joint_limits:
            raise WireError("joint_limits", "sent without joint_revolute")
        return None
    rows = _array(msg, "joint_revolute", msg.joint_count, 7)
    if len(rows) and not _all(np.isin(rows[:, 0], JOINT_KINDS)):
        raise WireError("joint_revolute", "names a kind of joint other than 0-3")
    limits = np.zeros((len(rows), 8), F32)
    if msg.joint_limits:
        limits = _array(msg, "joint_limits", msg.joint_count, 8)
        if len(limits) and not _all(np.isin(limits[:, 0], (0, 1, 2, 3)) & np.isin(limits[:, 2], (0, 1))
                                    & (limits[:, 4] >= 0)):
            raise WireError("joint_limits", "states a limit other than 0-3, a motor other than 0 or 1, "
                                            "or a negative torque")
    elif len(rows) and not _all(rows[:, 0] <= 1):
        raise WireError("joint_limits", "missing: weld and prismatic joints need their limits")
    return np.concatenate([rows, limits], 1)


def encode_impulses(step: int, model: str, impulses: np.ndarray, timings: pb.Timings | None = None) -> pb.Impulses:
    """impulses: (P, 2) float (normal, tangent), N s, request order."""
    imp = np.asarray(impulses, F32)
    # tobytes copies a strided column straight into the bytes object.
    reply = pb.Impulses(step=step, model=model, point_count=len(imp),
                        normal=imp[:, 0].tobytes(), tangent=imp[:, 1].tobytes())
    if timings is not None:
        reply.timings.CopyFrom(timings)
    return reply
