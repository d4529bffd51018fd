"""What a model was trained on, and whether a step lies inside it.

A network trained on piles of discs in a box has seen nothing of a stack of boxes, a body on a
joint or another time step, and its warm start there can cost many times Box2D's own. A card's
`trained_on` records the worlds its training data held, as an Envelope; the server tests every
step it answers against it and says, in the reply, whether the step is familiar and, where not,
why (`Impulses.familiar`, `Impulses.unfamiliar`). The client's guard (simclient.guard) trusts a
model on a familiar world from its first step and holds an unfamiliar one to Box2D's start until
its own trial solves say the model wins there.

    envelope = Envelope.from_scenes([thesis_spec_dict, family_spec_dict])   # what training saw
    reason = envelope.unfamiliar(bodies, points, friction, physics, joints)  # None: familiar

The test reads only what a request carries, so any client's world can be judged: a body is a
disc where its rotational inertia about its centre of mass is that of a uniform disc of its
bounding radius (I = m r^2 / 2); polygons, several fixtures and shapes off the body's centre
are not. Each range is widened by `SLACK` of itself on either side: a model is not lost at
0.56 m having seen 0.55 m.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

#: Each range of an envelope is widened by this share of its upper end on either side.
SLACK = 0.1
#: A body is a disc where I / (m r^2) lies within this of 1/2 (float32 rounding, thin margins).
DISC_TOLERANCE = 0.02
#: The shape kinds an envelope can hold: discs, and every other body (polygons, several fixtures).
SHAPES = ("disc", "other")


@dataclasses.dataclass(frozen=True)
class Envelope:
    """The worlds a model's training data held. Ranges are (low, high), inclusive.

    shapes: the body kinds seen ("disc", "other"); radius: the bodies' bounding radius (m);
    density: discs' mass over area (kg/m^2); friction: the points' friction coefficient;
    gravity: its magnitude (m/s^2); dt: the time step (s); joints, kinematic: whether bodies on
    joints, and kinematic bodies, were seen."""

    shapes: tuple[str, ...] = ("disc",)
    radius: tuple[float, float] = (0.5, 0.5)
    density: tuple[float, float] = (1.0, 1.0)
    friction: tuple[float, float] = (0.5, 0.5)
    gravity: tuple[float, float] = (9.8, 9.8)
    dt: tuple[float, float] = (0.01, 0.01)
    joints: bool = False
    kinematic: bool = False

    def __post_init__(self) -> None:
        ranges = (self.radius, self.density, self.friction, self.gravity, self.dt)
        if not self.shapes or set(self.shapes) - set(SHAPES) or not all(
                len(r) == 2 and all(isinstance(x, (int, float)) and math.isfinite(x) for x in r)
                and 0 <= r[0] <= r[1] for r in ranges):
            raise ValueError(f"an envelope holds shapes among {SHAPES} and ranges (low, high) with "
                             f"0 <= low <= high, got {self}")

    # -- the card ---------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {f.name: list(v) if isinstance(v, tuple) else v
                for f in dataclasses.fields(self) for v in [getattr(self, f.name)]}

    @classmethod
    def from_dict(cls, d: Any) -> "Envelope":
        """ValueError, in one line, for anything but an envelope's dict."""
        names = {f.name for f in dataclasses.fields(cls)}
        if not isinstance(d, dict) or set(d) - names:
            raise ValueError(f"trained_on: an object with keys among {sorted(names)}, got {d!r}")
        try:
            return cls(**{k: tuple(float(x) if k != "shapes" else x for x in v) if isinstance(v, list) else v
                          for k, v in d.items()})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"trained_on: {exc}") from None

    @classmethod
    def from_scenes(cls, scenes: list[dict]) -> "Envelope":
        """The union of the project's scenes (simclient.scene.SceneSpec as the data files' `scene`
        attribute holds it: bodies, radius, polygons, friction, density, gravity, solver.dt).
        A scene with polygons adds "other" (boxes of their circle's area)."""
        if not scenes:
            raise ValueError("an envelope of no scenes")
        radius = [r for s in scenes for r in s["radius"]]
        # A box of the same area as its circle has a bounding radius sqrt(pi/2) times the circle's.
        boxed = [math.sqrt(math.pi / 2) * max(s["radius"]) for s in scenes if s.get("polygons", 0) > 0]
        friction = [f for s in scenes for f in s["friction"]]
        density = [s["density"] for s in scenes]
        gravity = [s["gravity"] for s in scenes]
        dt = [s["solver"]["dt"] for s in scenes]
        shapes = ("disc", "other") if boxed else ("disc",)
        return cls(shapes=shapes, radius=(min(radius), max(radius + boxed)), density=(min(density), max(density)),
                   friction=(min(friction), max(friction)), gravity=(min(gravity), max(gravity)), dt=(min(dt), max(dt)))

    @classmethod
    def of_records(cls, bodies: np.ndarray, points: np.ndarray, physics: list, joints: bool) -> "Envelope":
        """The envelope of recorded simulations of a user's world: bodies (B,) BODY_DTYPE (any
        sample of the file's), points (P,) CONTACT_DTYPE, physics [(dt s, gx, gy m/s^2)] one per
        simulation; joints whether its worlds have joints (the records do not say)."""
        dynamic = bodies[bodies["type"] == 2]
        if not len(dynamic) or not len(physics):
            raise ValueError("an envelope of no bodies")
        mass, inertia, radius = (dynamic[k].astype(np.float64) for k in ("mass", "inertia", "radius"))
        disc = np.abs(inertia / (mass * radius * radius) - 0.5) <= DISC_TOLERANCE
        density = mass[disc] / (np.pi * radius[disc] ** 2) if disc.any() else np.array([1.0])
        friction = points["friction"].astype(np.float64) if len(points) else np.array([0.5])
        p = np.asarray(physics, np.float64).reshape(-1, 3)
        gravity = np.hypot(p[:, 1], p[:, 2])
        return cls(shapes=tuple(s for s, seen in (("disc", disc.any()), ("other", (~disc).any())) if seen),
                   radius=(float(radius.min()), float(radius.max())), density=(float(density.min()), float(density.max())),
                   friction=(float(friction.min()), float(friction.max())), gravity=(float(gravity.min()), float(gravity.max())),
                   dt=(float(p[:, 0].min()), float(p[:, 0].max())), joints=bool(joints),
                   kinematic=bool((bodies["type"] == 1).any()))

    def union(self, other: "Envelope") -> "Envelope":
        """The envelope of both: every shape either saw, each range spanning both."""
        def span(a, b):
            return (min(a[0], b[0]), max(a[1], b[1]))

        return Envelope(shapes=tuple(s for s in SHAPES if s in self.shapes or s in other.shapes),
                        **{k: span(getattr(self, k), getattr(other, k)) for k in ("radius", "density", "friction",
                                                                                  "gravity", "dt")},
                        joints=self.joints or other.joints, kinematic=self.kinematic or other.kinematic)

    # -- a step -----------------------------------------------------------------
    def _inside(self, bodies, points, friction, physics, joints) -> bool:
        """unfamiliar's test without its reasons: True where the step lies inside."""
        if joints is not None and len(joints) and not self.joints:
            return False
        if physics.dt > 0 and not (_within(physics.dt, physics.dt, self.dt)
                                   and _within(*(2 * [math.hypot(*physics.gravity)]), self.gravity)):
            return False
        if friction is not None and len(friction) and not _within(float(friction.min()), float(friction.max()),
                                                                   self.friction):
            return False
        touched = np.zeros(len(bodies), bool)
        touched[points["body_a"]] = touched[points["body_b"]] = True
        touched[0] = False  # the walls
        mass, inertia, radius = bodies["mass"][touched], bodies["inertia"][touched], bodies["radius"][touched]
        if not len(mass):
            return True
        if (mass <= 0).any():
            return False  # kinematic bodies: the detailed test decides
        area = np.pi * radius.astype(np.float64) ** 2
        disc = np.abs(inertia / (mass * radius * radius) - 0.5) <= DISC_TOLERANCE
        if "other" not in self.shapes and not disc.all():
            return False
        density = mass[disc] / area[disc]
        return _within(float(radius.min()), float(radius.max()), self.radius) and (
            not len(density) or _within(float(density.min()), float(density.max()), self.density))

    def unfamiliar(self, bodies: np.ndarray, points: np.ndarray, friction: np.ndarray | None, physics,
                   joints: np.ndarray | None) -> str | None:
        """Why a step lies outside the envelope, in a few words, or None where it lies inside.

        bodies: (B + 1,) BODY_DTYPE as deepcontact.wire.decode_step gives them (row 0 the walls'
        static stand-in; mass 0 a kinematic body); points: (P,) CONTACT_DTYPE; friction: (P,)
        each point's coefficient, or None (not judged); physics: deepcontact.kinematics.Physics
        (dt s, gravity m/s^2; dt 0: not sent, not judged); joints: (J, 2) rows of bodies, or
        None. Only the bodies that touch a point are judged: a body far from every contact
        changes nothing of the step's problem. A familiar step is told in a few array passes
        (it is asked on every served step); the reasons are worked out only where it is not."""
        if self._inside(bodies, points, friction, physics, joints):
            return None
        reasons = []
        if joints is not None and len(joints) and not self.joints:
            reasons.append(f"{len(joints)} joints")
        touched = np.zeros(len(bodies), bool)
        touched[points["body_a"]] = touched[points["body_b"]] = True
        touched[0] = False  # the walls
        moving = bodies[touched]
        mass = moving["mass"].astype(np.float64)
        kinematic = mass <= 0
        if kinematic.any() and not self.kinematic:
            reasons.append(f"{int(kinematic.sum())} kinematic bodies")
        dynamic = moving[~kinematic]
        m, r = mass[~kinematic], dynamic["radius"].astype(np.float64)
        disc = np.abs(dynamic["inertia"] / np.maximum(m * r * r, 1e-30) - 0.5) <= DISC_TOLERANCE
        if "other" not in self.shapes and not disc.all():
            reasons.append(f"{int((~disc).sum())} of {len(disc)} bodies not discs")
        reasons += _outside("radius", r, self.radius, "m")
        reasons += _outside("density", m[disc] / (np.pi * r[disc] ** 2), self.density, "kg/m^2")
        if friction is not None:
            reasons += _outside("friction", np.asarray(friction, np.float64), self.friction, "")
        if physics.dt > 0:
            reasons += _outside("dt", np.array([physics.dt]), self.dt, "s")
            reasons += _outside("gravity", np.array([math.hypot(*physics.gravity)]), self.gravity, "m/s^2")
        return "; ".join(reasons) or None


    # -- a step brought inside ---------------------------------------------------
    def rescaled(self, bodies: np.ndarray, points: np.ndarray, previous: np.ndarray | None, physics):
        """(bodies, points, previous, physics, (kl, km, kv)): the step with its scale brought inside
        the envelope's radius, density and gravity times time step, or the same objects and
        (1, 1, 1) where they lie inside already.

        A step's contact problem keeps its solution's labels (which points let go, stick, slide)
        under three scalings: every length times one factor, with the rotational inertias times
        its square and the angular velocities over it (a world of smaller bodies: the points'
        relative velocities and the operator J M^-1 J^T do not change); every mass and impulse
        times another (a denser world); and every velocity, g dt and impulse times a third (a
        stronger pull or a longer step: the one step's problem, M dv = J^T lambda + M g dt with
        its cones and complementarity, is homogeneous in (v, g dt, lambda)). So a classifier
        trained at one scale can be asked about a step at another, scaled to its own: 1 / kl the
        factor nearest 1 that brings every touched body's bounding radius inside the trained
        radii (none where their spread is wider than the range's), km the touched discs' median
        density then over the nearest density trained on, kv |g| dt over the nearest gravity
        times time step trained on (the physics becomes those). Exact for length and density;
        for gravity and the time step the motion that brought the bodies there differs, the one
        step's problem does not. Arguments as unfamiliar's (previous: the stream's last points,
        or None)."""
        touched = np.zeros(len(bodies), bool)
        touched[points["body_a"]] = touched[points["body_b"]] = True
        touched[0] = False  # the walls
        mass = bodies["mass"][touched].astype(np.float64)
        radius = bodies["radius"][touched].astype(np.float64)
        inertia = bodies["inertia"][touched].astype(np.float64)
        dynamic = mass > 0
        kl = 1.0
        if dynamic.any() and radius[dynamic].min() > 0:
            shortest, longest = float(radius[dynamic].min()), float(radius[dynamic].max())
            low, high = self.radius[0] / shortest, self.radius[1] / longest  # the factors that fit both ends
            if low <= high:
                kl = 1.0 / min(max(1.0, low), high)
        disc = dynamic & (np.abs(inertia / np.maximum(mass * radius * radius, 1e-30) - 0.5) <= DISC_TOLERANCE)
        km = 1.0
        if disc.any():
            density = float(np.median(mass[disc] / (np.pi * (radius[disc] / kl) ** 2)))
            km = density / _nearest(density, self.density) if density > 0 else 1.0
        kv, scaled_physics = 1.0, physics
        g = math.hypot(*physics.gravity)
        if physics.dt > 0 and g > 0:
            g_to, dt_to = _nearest(g, self.gravity), _nearest(physics.dt, self.dt)
            kv = g * physics.dt / (g_to * dt_to)
            scaled_physics = type(physics)(dt_to, (physics.gravity[0] * g_to / g, physics.gravity[1] * g_to / g))
        if all(abs(k - 1.0) <= RESCALE_TOLERANCE for k in (kl, km, kv)):
            return bodies, points, previous, physics, (1.0, 1.0, 1.0)
        b = bodies.copy()
        b["position"], b["radius"] = bodies["position"] / kl, bodies["radius"] / kl
        b["mass"], b["inertia"] = bodies["mass"] / km, bodies["inertia"] / (km * kl * kl)
        b["velocity"], b["angular_velocity"] = bodies["velocity"] / kv, bodies["angular_velocity"] * kl / kv

        def scaled(records):
            if records is None:
                return None
            out = records.copy()
            out["point"], out["separation"] = records["point"] / kl, records["separation"] / kl
            out["builtin"] = records["builtin"] / (km * kv)
            return out
        return b, scaled(points), scaled(previous), scaled_physics, (kl, km, kv)


#: Envelope.rescaled leaves a step as it is where its factors lie this close to 1 (a world at
#: the trained scale, whose float32 records and physics round a little off it).
RESCALE_TOLERANCE = 1e-4


def _nearest(x: float, seen: tuple[float, float]) -> float:
    """The value of `seen` (low, high) nearest x."""
    return min(max(x, seen[0]), seen[1])


def _within(low: float, high: float, seen: tuple[float, float]) -> bool:
    """Whether [low, high] lies inside `seen` widened by SLACK."""
    margin = SLACK * seen[1]
    return low >= seen[0] - margin and high <= seen[1] + margin


def _outside(name: str, values: np.ndarray, seen: tuple[float, float], unit: str) -> list[str]:
    """[a few words] where some of values lie outside `seen` widened by SLACK, else []."""
    if not len(values):
        return []
    low, high = float(values.min()), float(values.max())
    margin = SLACK * seen[1]
    if low >= seen[0] - margin and high <= seen[1] + margin:
        return []
    unit = f" {unit}" if unit else ""
    return [f"{name} {_g(low)}-{_g(high)}{unit}, trained on {_g(seen[0])}-{_g(seen[1])}"]


def _g(x: float) -> str:
    return f"{x:.3g}"
