"""NumPy <-> protobuf for the warm-start service (proto/deepcontact/v1).

Both sides use these functions: the client encodes a step from the engine's
records and decodes the reply; the server decodes the step into records for
the transfer and encodes impulses. Arrays travel as packed little-endian
float32 `bytes`, so encoding is a copy, not a Python loop.
"""

from __future__ import annotations

import numpy as np

from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from deepcontact.v1 import warmstart_pb2 as pb

BODY_COLUMNS = ("x", "y", "angle", "vx", "vy", "omega", "mass", "radius")
POINT_COLUMNS = ("x", "y", "normal_x", "normal_y")
F32 = np.dtype("<f4")


class WireError(ValueError):
    """A message whose arrays do not fit their declared counts or are not finite.
    `field` names the offending field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


# -- client side -------------------------------------------------------------

def encode_world(lower: tuple[float, float], upper: tuple[float, float],
                 edges: np.ndarray | None = None) -> pb.World:
    """Domain (m) and static edges (E, 4) float (x0, y0, x1, y1)."""
    edges = np.zeros((0, 4), F32) if edges is None else np.ascontiguousarray(edges, F32).reshape(-1, 4)
    return pb.World(x_min=lower[0], y_min=lower[1], x_max=upper[0], y_max=upper[1],
                    edge_count=len(edges), edges=edges.tobytes())


def encode_step(step: int, model: str, bodies: np.ndarray, points: np.ndarray, *,
                world: pb.World | None = None, builtin: np.ndarray | None = None,
                impulses: np.ndarray | None = None) -> pb.StepRequest:
    """A step from engine records.

    bodies: (B,) BODY_DTYPE (static bodies are left out: walls travel in World).
    points: (P,) CONTACT_DTYPE in export order.
    builtin, impulses: optional (P, 2) float (normal, tangent), N s.
    """
    dyn = bodies[bodies["type"] != 0]
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
    msg = pb.StepRequest(step=step, model=model, body_count=len(dyn), bodies=b.tobytes(),
                         point_count=len(points), points=p.tobytes())
    if world is not None:
        msg.world.CopyFrom(world)
    if builtin is not None:
        msg.builtin = np.ascontiguousarray(builtin, F32).tobytes()
    if impulses is not None:
        msg.impulses = np.ascontiguousarray(impulses, F32).tobytes()
    return msg


def decode_impulses(reply: pb.Impulses) -> tuple[np.ndarray, np.ndarray]:
    """(normal (P,), tangent (P,)) float32, N s, in request order."""
    n = reply.point_count
    normal = np.frombuffer(reply.normal, F32)
    tangent = np.frombuffer(reply.tangent, F32)
    if len(normal) != n or len(tangent) != n:
        raise WireError("normal/tangent", f"reply carries {len(normal)}/{len(tangent)} values for {n} points")
    return normal, tangent


# -- server side -------------------------------------------------------------

def _array(msg, field: str, rows: int, cols: int, *, optional: bool = False) -> np.ndarray | None:
    raw = getattr(msg, field)
    if optional and not raw:
        return None
    expected = rows * cols * F32.itemsize
    if len(raw) != expected:
        raise WireError(field, f"{len(raw)} bytes, expected {rows} x {cols} float32 = {expected}")
    a = np.frombuffer(raw, F32).reshape(rows, cols)
    if not np.isfinite(a).all():
        raise WireError(field, "holds NaN or infinite values")
    return a


def decode_world(world: pb.World) -> tuple[tuple[float, float], tuple[float, float], np.ndarray]:
    """(lower, upper, edges (E, 4) float32); WireError for an empty or non-finite domain."""
    lo = (world.x_min, world.y_min)
    hi = (world.x_max, world.y_max)
    if not np.isfinite(lo + hi).all() or not (hi[0] > lo[0] and hi[1] > lo[1]):
        raise WireError("world", f"domain ({lo[0]}, {lo[1]}) - ({hi[0]}, {hi[1]}) is empty or not finite")
    edges = _array(world, "edges", world.edge_count, 4)
    return lo, hi, edges


def decode_step(msg: pb.StepRequest, *, max_bodies: int, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Records for the transfer: bodies (B,) BODY_DTYPE (all dynamic) and
    points (P,) CONTACT_DTYPE with point, normal, builtin and impulse filled
    (builtin and impulse zero when absent). WireError names the bad field."""
    if msg.body_count > max_bodies:
        raise WireError("body_count", f"{msg.body_count} exceeds the server's limit of {max_bodies}")
    if msg.point_count > max_points:
        raise WireError("point_count", f"{msg.point_count} exceeds the server's limit of {max_points}")
    b = _array(msg, "bodies", msg.body_count, len(BODY_COLUMNS))
    p = _array(msg, "points", msg.point_count, len(POINT_COLUMNS))
    builtin = _array(msg, "builtin", msg.point_count, 2, optional=True)
    impulses = _array(msg, "impulses", msg.point_count, 2, optional=True)

    bodies = np.zeros(len(b), BODY_DTYPE)
    bodies["index"] = np.arange(1, len(b) + 1)
    bodies["type"] = 2
    bodies["position"] = b[:, 0:2]
    bodies["angle"] = b[:, 2]
    bodies["velocity"] = b[:, 3:5]
    bodies["angular_velocity"] = b[:, 5]
    bodies["mass"] = b[:, 6]
    bodies["radius"] = b[:, 7]
    points = np.zeros(len(p), CONTACT_DTYPE)
    points["point"] = p[:, 0:2]
    points["normal"] = p[:, 2:4]
    if builtin is not None:
        points["builtin"] = builtin
    if impulses is not None:
        points["impulse"] = impulses
    return bodies, points


def encode_impulses(step: int, model: str, impulses: np.ndarray, timings: pb.Timings | None = None) -> pb.Impulses:
    """impulses: (P, 2) float (normal, tangent), N s, request order."""
    imp = np.asarray(impulses, F32)
    reply = pb.Impulses(step=step, model=model, point_count=len(imp),
                        normal=np.ascontiguousarray(imp[:, 0]).tobytes(),
                        tangent=np.ascontiguousarray(imp[:, 1]).tobytes())
    if timings is not None:
        reply.timings.CopyFrom(timings)
    return reply
