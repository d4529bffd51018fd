"""Grid channels: what each channel of a model's input or target grids holds.

A channel is one value per particle, splatted onto the grid by the transfer
(deepcontact.features). Particles come from one of three sources of a step:

    "bodies"    the dynamic bodies, at their position
    "contacts"  this step's contact points, at their world point
    "previous"  the previous step's contact points (after its solve), at theirs

and a channel reads its value from a `Step`: the step's records plus what is
derived from them (contact velocities, deepcontact.kinematics) and what only
recorded data has (the oracle's impulses, for training targets). The
definitions below are plain data, imported by training and serving alike: a
model card that names a channel is served with exactly this definition.

    step = Step(bodies, contacts, previous=None, physics=Physics.thesis())
    values = channel_values(("vn_builtin", "separation"), step)   # (P, 2)

Units are SI: m, s, kg, N s for impulses.
"""

from __future__ import annotations

import dataclasses
from types import MappingProxyType
from typing import Callable, Mapping, Sequence

import numpy as np

from deepcontact.faces import contact_face, face_labels
from deepcontact.kinematics import BODY_DYNAMIC, Physics, contact_quantities
from deepcontact.records import CONTACT_DTYPE

__all__ = ["CHANNELS", "DEFAULT_INPUTS", "DEFAULT_TARGETS", "NEEDS", "SOURCES", "Channel", "Source", "Step",
           "channel_values", "particle_positions"]


class Step:
    """One step as the channels see it.

    bodies: (B,) BODY_DTYPE indexed by the contacts' body_a/body_b (the
        engine's records, static bodies included).
    contacts: (P,) CONTACT_DTYPE of this step (builtin is Box2D's warm start;
        impulse is filled only in recorded data).
    previous: (P',) CONTACT_DTYPE of the previous step after its solve, or
        None (first step, or a single request): temporal channels are then 0.
    physics: gravity and time step, for the contact velocities.
    oracle: (P, 2) float32 this step's impulses solved from zero to
        convergence (recorded data only), for oracle targets.
    friction: (P,) each contact's friction coefficient (the request's
        point_friction; for recorded data, rebuilt from the scene and seed), or None.

    Derived arrays are computed once, when a channel first asks.
    """

    __slots__ = ("bodies", "contacts", "previous", "physics", "oracle", "friction", "_quantities", "_last_correction",
                 "_scales")

    def __init__(self, bodies: np.ndarray | None, contacts: np.ndarray | None, previous: np.ndarray | None = None,
                 physics: Physics = Physics(), oracle: np.ndarray | None = None, friction: np.ndarray | None = None):
        self.bodies, self.contacts, self.previous = bodies, contacts, previous
        self.physics, self.oracle, self.friction = physics, oracle, friction
        self._quantities = self._last_correction = self._scales = None

    def scales(self) -> tuple[float, float]:
        """(M kg, V m/s): the step's own scale of mass and of velocity, which the *_scaled
        channels divide by, so that a network reads a heavier, stronger-pulled or coarser-stepped
        world as the same problem. M is the median mass of the dynamic bodies, V what gravity
        adds to a velocity in one step (|g| dt); an impulse's scale is M V, what holds a body of
        mass M up for one step. V is at least MIN_SCALE_VELOCITY (a world without gravity).
        Per world, not per point: the median of the bodies is the same on every step of a
        simulation, and on a batch of its steps (training.contact_graph.one_world)."""
        if self._scales is None:
            b = self._bodies("step scales")
            mass = b["mass"][(b["type"] == BODY_DYNAMIC) & (b["mass"] > 0)]
            m = float(np.median(mass)) if len(mass) else 1.0
            v = max(float(np.hypot(*self.physics.gravity)) * float(self.physics.dt), MIN_SCALE_VELOCITY)
            self._scales = (m, v)
        return self._scales

    def velocities(self) -> np.ndarray:
        """(P, 2) m/s: relative (normal, tangent) velocity after gravity."""
        return self._contact_quantities("contact velocities")[0]

    def velocities_after_builtin(self) -> np.ndarray:
        """(P, 2) m/s: the same after Box2D's builtin warm start is applied: what the
        solver's first sweep sees when it warm-starts as Box2D does."""
        return self._contact_quantities("contact velocities")[1]

    def masses(self) -> np.ndarray:
        """(P, 2) kg: each point's effective mass along its normal and tangent."""
        return self._contact_quantities("effective masses")[2]

    def jacobi(self) -> np.ndarray:
        """(P, 2) N s: one Jacobi step from the builtin warm start, -mass x velocity after it:
        the change each point would make alone to stop its relative motion."""
        return -self.masses() * self.velocities_after_builtin()

    def last_correction(self) -> np.ndarray:
        """(P, 2) N s: what the solver added to Box2D's warm start at the same point
        (matched by key) on the previous step, 0 where the point is new or there is no
        previous step. Box2D's warm start is last step's final impulse, so this is
        builtin minus last step's builtin: it needs no solved impulses and is the same
        on recorded data and on a server that keeps a stream's last request."""
        if self._last_correction is None:
            c, p = self.contacts, self.previous
            out = np.zeros((len(c), 2))
            if p is not None and len(p) and len(c):
                order = np.argsort(p["key"], kind="stable")
                keys = p["key"][order]
                j = np.searchsorted(keys, c["key"]).clip(max=len(keys) - 1)
                found = keys[j] == c["key"]
                before = p["builtin"][order[j[found]]].astype(np.float64)
                out[found] = c["builtin"][found].astype(np.float64) - before
            self._last_correction = out
        return self._last_correction

    def point_friction(self) -> np.ndarray:
        """(P,) each contact's friction coefficient."""
        if self.friction is None:
            raise ValueError("the friction channel needs each point's friction")
        return self.friction

    def oracle_impulses(self) -> np.ndarray:
        if self.oracle is None:
            raise ValueError("oracle channels need the oracle's impulses (data generated with --oracle)")
        return self.oracle

    def _contact_quantities(self, what: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # One compiled pass gives all three (deepcontact.kinematics.contact_quantities):
        # cheaper than any one of them was in NumPy.
        if self._quantities is None:
            self._quantities = contact_quantities(self._bodies(what), self.contacts, self.physics)
        return self._quantities

    def _bodies(self, what: str) -> np.ndarray:
        if self.bodies is None:
            raise ValueError(f"{what} need the step's bodies")
        return self.bodies


@dataclasses.dataclass(frozen=True)
class Source:
    """Where the particles of a channel come from.

    records: step -> the structured array of the particles' records (all of
        them; `select` then keeps the particles).
    position_field: the records' field holding the particle position (m).
    select: optional records -> bool mask (N,) of the records that are particles.
    """

    name: str
    records: Callable[[Step], np.ndarray | None]
    position_field: str
    select: Callable[[np.ndarray], np.ndarray] | None = None

    def particles(self, step: Step) -> np.ndarray:
        """The particle records of this source in `step` (no copy when all are particles)."""
        array = self.records(step)
        if array is None:
            if self.name == "previous":  # no previous step: no particles, the channels stay 0
                return _NO_CONTACTS
            raise ValueError(f"channels of source {self.name!r} need the step's {self.name}")
        if self.select is None or len(array) == 0:
            return array
        keep = self.select(array)
        # The ufunc reduction, not keep.all(): this runs on the server's every step.
        return array if np.logical_and.reduce(keep, axis=None) else array.take(np.flatnonzero(keep))


@dataclasses.dataclass(frozen=True)
class Channel:
    """One grid channel.

    extract: (particle records, step) -> (N,) values, one per particle.
    walls: the static box's edge nodes get GridSpec.wall_mass in this channel
        (thesis §8.1: static bodies have no mass in Box2D, so the box's edge
        nodes get 100, "more than one hundred times the mass of the bodies").
    needs: what a request must carry beyond bodies and points for this
        channel (names from NEEDS); the server refuses requests without it.
    temporal: reads the previous step (Step.previous), so a point's value
        depends on more than its own step's records.
    mirror: the value's sign when the world is reflected left to right (x -> -x):
        -1 for x components, angles and angular velocities, and tangent
        components (Box2D's tangent is (n_y, -n_x), which the reflection turns
        into minus the reflected tangent); 1 otherwise.
    """

    name: str
    source: str
    extract: Callable[[np.ndarray, Step], np.ndarray]
    unit: str = ""
    description: str = ""
    walls: bool = False
    needs: tuple[str, ...] = ()
    temporal: bool = False
    mirror: int = 1


def _field(name: str, component: int | None = None) -> Callable[[np.ndarray, Step], np.ndarray]:
    if component is None:
        return lambda a, step: a[name]
    return lambda a, step: a[name][:, component]


def _derived(method: str, component: int) -> Callable[[np.ndarray, Step], np.ndarray]:
    return lambda a, step: getattr(step, method)()[:, component]


def _asinh(method: str, component: int, scale: float) -> Callable[[np.ndarray, Step], np.ndarray]:
    return lambda a, step: np.arcsinh(getattr(step, method)()[:, component] / scale)


#: The least velocity scale (m/s) of Step.scales: a world without gravity still has one.
MIN_SCALE_VELOCITY = 1e-3


def _scaled(channel: "Channel") -> "Channel":
    """`channel` divided by the step's own scale of its unit (Step.scales): N s by M V, m/s by V,
    kg by M; named NAME_scaled, unit 1."""
    power = {"N s": (1, 1), "m/s": (0, 1), "kg": (1, 0)}[channel.unit]

    def extract(a: np.ndarray, step: Step) -> np.ndarray:
        m, v = step.scales()
        return channel.extract(a, step) / (m ** power[0] * v ** power[1])
    return dataclasses.replace(channel, name=f"{channel.name}_scaled", extract=extract, unit="1",
                               description=f"{channel.name} over the step's own scale of {channel.unit} "
                                           f"(Step.scales: mass M, velocity |g| dt)",
                               needs=tuple(sorted(set(channel.needs) | {"physics"})))


def _oracle_minus_builtin(component: int) -> Callable[[np.ndarray, Step], np.ndarray]:
    return lambda a, step: step.oracle_impulses()[:, component] - a["builtin"][:, component]


#: face_correction_*: the friction the recorded files' faces are read at where a step has no
#: friction of its own (Step.friction; the thesis world's, at every pair); a label is written as
#: an impulse of faces.FACE_IMPULSE.
FACE_FRICTION = 0.5


def _face_labels(component: int) -> Callable[[np.ndarray, Step], np.ndarray]:
    """The recorded solve's face (deepcontact.faces.contact_face at the step's friction, else
    FACE_FRICTION) written as impulses: FACE_IMPULSE along the normal where a point presses,
    +-FACE_IMPULSE along the tangent where it slides that way. A network trained on these is
    served as it answers (combine "replace"), whatever the world's scale of impulse."""
    def channel(a: np.ndarray, step: Step) -> np.ndarray:
        mu = np.full(len(a), FACE_FRICTION) if step.friction is None else np.asarray(step.friction, np.float64)
        return face_labels(contact_face(a["impulse"].astype(np.float64), mu))[:, component]
    return channel


def _face_minus_builtin(component: int) -> Callable[[np.ndarray, Step], np.ndarray]:
    """_face_labels minus the builtin warm start: served as a residual, a model's answer is its labels."""
    labels = _face_labels(component)
    return lambda a, step: labels(a, step) - a["builtin"][:, component]


def _new_point(a: np.ndarray, step: Step) -> np.ndarray:
    # Box2D carries no impulse into a point it did not have last step: builtin is then exactly 0.
    return (~a["builtin"].any(axis=1)).astype(np.float64)


_NO_CONTACTS = np.zeros(0, CONTACT_DTYPE)

#: What a channel may need from a request, beyond the bodies and points (see the proto).
NEEDS = {
    "point_bodies": "each point's two bodies (StepRequest.point_bodies)",
    "body_inertia": "the bodies' inertia (StepRequest.body_inertia)",
    "physics": "the time step and gravity (World.dt, World.gravity_x/y)",
    "point_separation": "the points' separation (StepRequest.point_separation)",
    "builtin": "Box2D's builtin warm start (StepRequest.builtin)",
    "point_keys": "the points' keys, equal on every step for the same point (StepRequest.point_keys)",
    "point_friction": "each point's friction coefficient (StepRequest.point_friction)",
}
_VELOCITY = ("point_bodies", "physics")
#: Scales of the *_asinh channels: the solver stops when no impulse changes by more than
#: 1e-4 N s in a sweep (SolverSettings.velocity_threshold), and an effective mass is about 0.4 kg in the thesis world.
_FINE_IMPULSE = 1e-4  # N s
_FINE_VELOCITY = 1e-4  # m/s

SOURCES: Mapping[str, Source] = MappingProxyType({
    "bodies": Source("bodies", lambda s: s.bodies, "position", lambda b: b["type"] == BODY_DYNAMIC),
    "contacts": Source("contacts", lambda s: s.contacts, "point"),
    "previous": Source("previous", lambda s: s.previous, "point"),
})

_DEFINITIONS = (
    # Bodies (dynamic only), at the body's position.
    Channel("mass", "bodies", _field("mass"), "kg", "body mass; static box edges get GridSpec.wall_mass", walls=True),
    Channel("vx", "bodies", _field("velocity", 0), "m/s", "linear velocity, x", mirror=-1),
    Channel("vy", "bodies", _field("velocity", 1), "m/s", "linear velocity, y"),
    Channel("omega", "bodies", _field("angular_velocity"), "rad/s", "angular velocity", mirror=-1),
    Channel("angle", "bodies", _field("angle"), "rad", "body angle", mirror=-1),
    Channel("inertia", "bodies", _field("inertia"), "kg m^2", "rotational inertia about the centre of mass"),
    Channel("radius", "bodies", _field("radius"), "m", "shape radius"),
    # Contact points, at the world contact point.
    Channel("normal_x", "contacts", _field("normal", 0), "1", "contact normal (A to B), x", mirror=-1),
    Channel("normal_y", "contacts", _field("normal", 1), "1", "contact normal (A to B), y"),
    Channel("separation", "contacts", _field("separation"), "m", "signed separation (negative: penetration)",
            needs=("point_separation",)),
    Channel("builtin_normal", "contacts", _field("builtin", 0), "N s", "engine's built-in warm start, normal",
            needs=("builtin",)),
    Channel("builtin_tangent", "contacts", _field("builtin", 1), "N s", "engine's built-in warm start, tangent",
            needs=("builtin",), mirror=-1),
    Channel("friction", "contacts", lambda a, step: step.point_friction(), "1",
            "the point's friction coefficient, sqrt(f_A f_B) of its two bodies' (the face route's slide limit)",
            needs=("point_friction",)),
    Channel("new_point", "contacts", _new_point, "1", "1 for a point new this step (no builtin warm start), else 0",
            needs=("builtin",)),
    Channel("vn", "contacts", _derived("velocities", 0), "m/s",
            "relative normal velocity after this step's gravity (> 0 separates)", needs=_VELOCITY),
    Channel("vt", "contacts", _derived("velocities", 1), "m/s", "relative tangent velocity after gravity",
            needs=_VELOCITY, mirror=-1),
    Channel("vn_builtin", "contacts", _derived("velocities_after_builtin", 0), "m/s",
            "relative normal velocity after gravity and the builtin warm start: the solver's first residual",
            needs=_VELOCITY + ("body_inertia", "builtin")),
    Channel("vt_builtin", "contacts", _derived("velocities_after_builtin", 1), "m/s",
            "relative tangent velocity after gravity and the builtin warm start",
            needs=_VELOCITY + ("body_inertia", "builtin"), mirror=-1),
    Channel("normal_mass", "contacts", _derived("masses", 0), "kg",
            "effective mass along the normal (Box2D's normalMass)", needs=("point_bodies", "body_inertia")),
    Channel("tangent_mass", "contacts", _derived("masses", 1), "kg",
            "effective mass along the tangent (Box2D's tangentMass)", needs=("point_bodies", "body_inertia")),
    Channel("jacobi_normal", "contacts", _derived("jacobi", 0), "N s",
            "one Jacobi step from the builtin warm start: -normal_mass x vn_builtin",
            needs=_VELOCITY + ("body_inertia", "builtin")),
    Channel("jacobi_tangent", "contacts", _derived("jacobi", 1), "N s",
            "one Jacobi step from the builtin warm start: -tangent_mass x vt_builtin",
            needs=_VELOCITY + ("body_inertia", "builtin"), mirror=-1),
    # The same four on a signed logarithmic scale: linear within the solver's tolerance (1e-4 N s,
    # about 1e-4 m/s at these masses), logarithmic beyond it. In a settled pile they are 1e-4 to
    # 1e-3 of their standard deviation, which a standardized input all but hides from the network.
    Channel("vn_builtin_asinh", "contacts", _asinh("velocities_after_builtin", 0, _FINE_VELOCITY), "1",
            "asinh(vn_builtin / 1e-4 m/s)", needs=_VELOCITY + ("body_inertia", "builtin")),
    Channel("vt_builtin_asinh", "contacts", _asinh("velocities_after_builtin", 1, _FINE_VELOCITY), "1",
            "asinh(vt_builtin / 1e-4 m/s)", needs=_VELOCITY + ("body_inertia", "builtin"), mirror=-1),
    Channel("jacobi_normal_asinh", "contacts", _asinh("jacobi", 0, _FINE_IMPULSE), "1",
            "asinh(jacobi_normal / 1e-4 N s)", needs=_VELOCITY + ("body_inertia", "builtin")),
    Channel("jacobi_tangent_asinh", "contacts", _asinh("jacobi", 1, _FINE_IMPULSE), "1",
            "asinh(jacobi_tangent / 1e-4 N s)", needs=_VELOCITY + ("body_inertia", "builtin"), mirror=-1),
    Channel("last_correction_normal", "contacts", _derived("last_correction", 0), "N s",
            "what the solver added to the warm start at this point last step (builtin minus last step's "
            "builtin), normal; 0 at new points", needs=("builtin", "point_keys"), temporal=True),
    Channel("last_correction_tangent", "contacts", _derived("last_correction", 1), "N s",
            "the same, tangent", needs=("builtin", "point_keys"), temporal=True, mirror=-1),
    Channel("warm_start_normal", "contacts", _field("warm_start", 0), "N s", "warm start used, normal"),
    Channel("warm_start_tangent", "contacts", _field("warm_start", 1), "N s", "warm start used, tangent", mirror=-1),
    Channel("impulse_normal", "contacts", _field("impulse", 0), "N s", "final solver impulse, normal"),
    Channel("impulse_tangent", "contacts", _field("impulse", 1), "N s", "final solver impulse, tangent", mirror=-1),
    # Targets of residual models: what the solver adds to Box2D's own warm start.
    Channel("correction_normal", "contacts", lambda c, s: c["impulse"][:, 0] - c["builtin"][:, 0], "N s",
            "final impulse minus the builtin warm start, normal"),
    Channel("correction_tangent", "contacts", lambda c, s: c["impulse"][:, 1] - c["builtin"][:, 1], "N s",
            "final impulse minus the builtin warm start, tangent", mirror=-1),
    Channel("oracle_normal", "contacts", _derived("oracle_impulses", 0), "N s",
            "this step solved from zero to convergence (the oracle), normal"),
    Channel("oracle_tangent", "contacts", _derived("oracle_impulses", 1), "N s", "the oracle's impulse, tangent",
            mirror=-1),
    Channel("oracle_correction_normal", "contacts", _oracle_minus_builtin(0), "N s",
            "the oracle's impulse minus the builtin warm start, normal"),
    Channel("oracle_correction_tangent", "contacts", _oracle_minus_builtin(1), "N s",
            "the oracle's impulse minus the builtin warm start, tangent", mirror=-1),
    Channel("face_correction_normal", "contacts", _face_minus_builtin(0), "N s",
            "the recorded solve's face at the step's friction (else 0.5) written as impulses (1 N s where a point "
            "presses) minus the builtin warm start, normal"),
    Channel("face_correction_tangent", "contacts", _face_minus_builtin(1), "N s",
            "the same, tangent (+-1 N s where a point slides that way, 0 where it sticks)", mirror=-1),
    # The previous step's contact points, at their own positions.
    Channel("previous_builtin_normal", "previous", _field("builtin", 0), "N s",
            "last step's builtin warm start (the impulse of two steps ago), normal", temporal=True),
    Channel("previous_builtin_tangent", "previous", _field("builtin", 1), "N s",
            "last step's builtin warm start, tangent", temporal=True, mirror=-1),
)

_BASE = {c.name: c for c in _DEFINITIONS}
#: The contact-point channels in units of the step's own scales (Step.scales), and the face as labels.
_DEFINITIONS += tuple(_scaled(_BASE[n]) for n in (
    "builtin_normal", "builtin_tangent", "vn", "vt", "vn_builtin", "vt_builtin", "normal_mass", "tangent_mass",
    "jacobi_normal", "jacobi_tangent")) + (
    Channel("face_normal", "contacts", _face_labels(0), "N s",
            "the recorded solve's face at the step's friction written as impulses: 1 N s where a point presses"),
    Channel("face_tangent", "contacts", _face_labels(1), "N s",
            "the same, tangent: +-1 N s where a point slides that way, 0 where it sticks", mirror=-1),
)

#: Every channel by name (read-only).
CHANNELS: Mapping[str, Channel] = MappingProxyType({c.name: c for c in _DEFINITIONS})
if len(CHANNELS) != len(_DEFINITIONS):  # pragma: no cover - a definition error
    raise ImportError("deepcontact.channels: two channels share a name")

#: Thesis §8.1 inputs: four body attributes, then the two contact normal components.
DEFAULT_INPUTS = ("mass", "vx", "vy", "omega", "normal_x", "normal_y")
#: Thesis §8.1 targets: normal and tangent impulse at the contact points.
DEFAULT_TARGETS = ("impulse_normal", "impulse_tangent")


def mirror_signs(names: Sequence[str]) -> np.ndarray:
    """(C,) float32: each channel's sign under a left-right reflection of the world (Channel.mirror)."""
    return np.array([CHANNELS[n].mirror for n in names], np.float32)


def needs(names: Sequence[str]) -> tuple[str, ...]:
    """What requests must carry for these channels (keys of NEEDS), sorted."""
    return tuple(sorted({need for n in names for need in CHANNELS[n].needs}))


def particle_positions(source: str, step: Step) -> np.ndarray:
    """Positions (N, 2) float64 m of the particles of `source` in `step`."""
    src = SOURCES[source]
    return np.asarray(src.particles(step)[src.position_field], dtype=np.float64).reshape(-1, 2)


def channel_values(names: Sequence[str], step: Step) -> np.ndarray:
    """Per-particle values (N, len(names)) float64 of channels that share one source;
    rows line up with `particle_positions(source, step)`."""
    if not names:
        raise ValueError("channel_values needs at least one channel")
    unknown = [n for n in names if n not in CHANNELS]
    if unknown:
        raise ValueError(f"unknown channels {unknown}; known channels: {sorted(CHANNELS)}")
    sources = {CHANNELS[n].source for n in names}
    if len(sources) != 1:
        raise ValueError(f"channels {list(names)} come from several sources {sorted(sources)}")
    records = SOURCES[sources.pop()].particles(step)
    # Filled channel-major (each row a contiguous copy of one field) and
    # returned as an (N, C) view: the transfer works on the (C, N) layout.
    out = np.empty((len(names), len(records)), dtype=np.float64)
    for j, n in enumerate(names):  # loop over channels, not particles
        out[j] = CHANNELS[n].extract(records, step)
    return out.T
