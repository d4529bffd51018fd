"""What the server can answer a step with: ONNX models and simple providers.

Every predictor maps a step's records to one (normal, tangent) impulse per
contact point, in the request's order, and says what its stages cost and who
answered, in a Prediction:

    answer = predictor.predict(bodies, points, world, step, previous)
    answer.impulses    # (P, 2) float32, N s
    answer.stages      # seconds by stage: {"p2g": s, "inference": s, "g2p": s} for a grid model
    answer.served_by   # None, or what answered in the predictor's place (a face route's fallback)

`world` is what a stream declares once (the grids' domain, the physics);
`previous` the stream's last step's points (None on its first step and for
single requests), for temporal channels. `predictor.requires` names what a
request must carry beyond bodies and points (deepcontact.channels.NEEDS); a
predictor that requires "point_friction" is also given the points' friction
(`predict(..., friction=...)`, (P,) from StepRequest.point_friction).

`ModelPredictor` runs P2G -> ONNX -> G2P with its card's GridSpec and the
shared transfer code (deepcontact.transfer), exactly as training did; the
contact points' kernel weights are computed once per step, in the input
splat, and reused for the output transfer (a TransferPlan). `GraphPredictor`
runs a contact-graph network on the points (features -> ONNX -> its combine,
"g2p"). A graph card with `face` is served by server.face_route.FaceRoutePredictor:
its classifier a GraphPredictor, the step solved on its labels and admitted.
`load_model` picks the class from the card and builds each whole.
The providers need no world state: `zero`, `random` (thesis §8.2.2 ranges:
normal U(0, 5), tangent U(-2, 2), seeded per step), `bad` (50, 50) and
`grid-identity` (the request's own impulses splatted and read back: the
thesis's Grid model, which measures what the transfer loses).
"""

from __future__ import annotations

import dataclasses
import threading
import time
from pathlib import Path

import numpy as np

from deepcontact.channels import Step, channel_values, needs
from deepcontact.envelope import Envelope
from deepcontact.features import world_to_grids
from deepcontact.gridspec import GridSpec
from deepcontact.kinematics import BODY_DYNAMIC, Physics, contact_physics, points_at_rest
from deepcontact.modelcard import ModelCard, ModelCardError
from deepcontact.step_gate import StepGate, step_features
from deepcontact.transfer import plan

Domain = tuple[tuple[float, float], tuple[float, float]]


@dataclasses.dataclass(frozen=True)
class World:
    """What a stream declares once: the domain its grids cover (m), the step's physics and the
    client's stopping rule (tolerance, N s: its solver stops after the first sweep that changes no
    impulse by more; 0 where the client did not say)."""

    domain: Domain
    physics: Physics = Physics()
    tolerance: float = 0.0


# The most grid nodes a request's domain may need, by default (`deepcontact serve
# --max-grid-nodes`): 512 x 512, a 128 m square at the thesis's 0.25 m (its world
# needs 61 x 61). A domain is the client's to declare; without a bound, one finite
# but huge domain makes the server allocate grids of any size, and the operating
# system kills it.
MAX_GRID_NODES = 512 * 512


class GridMismatch(ValueError):
    """A predictor asked for a grid it cannot serve: a fixed-size model's other
    size, or one with more nodes than the server's bound (MAX_GRID_NODES by default)."""


#: Every stage a predictor may time, each a field NAME_us of the reply's Timings: a grid
#: model's p2g, inference and g2p; a graph model's features, inference and g2p (its combine);
#: the face route's features, inference, solve and admit.
STAGES = ("p2g", "features", "inference", "g2p", "solve", "admit")


#: Prediction.unfamiliar where the predictor did not judge the step against its envelope.
NOT_JUDGED = object()


@dataclasses.dataclass(frozen=True)
class Prediction:
    """A predictor's answer to one step.

    impulses: (P, 2) float32 N s, (normal, tangent) at each contact point in the request's order.
    stages: seconds spent in each of STAGES that the predictor ran (a provider: none).
    served_by: None where the predictor's own answer is served; else what answered in its place,
        a fallback card's name or "builtin" (Box2D's warm start, the request's builtin impulses),
        which the service puts on the reply (Impulses.served_by).
    joint_impulses: where the answer starts the request's revolute joints too (server.revolute),
        (J, 2) float32 N s on each joint's body B, request order; None: they keep their own.
    unfamiliar: where the predictor judged the step against its own envelope (joints not
        judged), Envelope.unfamiliar's verdict: None inside, else why; NOT_JUDGED elsewhere. The
        service's reply says the same (Impulses.familiar) without judging the step again.
    """

    impulses: np.ndarray
    stages: dict[str, float] = dataclasses.field(default_factory=dict)
    served_by: str | None = None
    unfamiliar: object = NOT_JUDGED
    joint_impulses: np.ndarray | None = None  # (J, 2) float32 N s, the revolute joints' start, or None (their own)


class Predictor:
    name: str
    kind: str
    description: str = ""  # one line: what it is (a model's card says; ListModels returns it)
    fixed_grid: bool = False
    gridspec: GridSpec | None = None
    requires: tuple[str, ...] = ()
    batchable: bool = False  # infer(x) on one (1, ny, nx, C) grid, which server.batching can stack
    takes_deadline: bool = False  # predict(..., deadline=) may answer otherwise to meet it
    takes_memory: bool = False  # predict(..., memory=) keeps state along a stream (a dict per stream and model)
    takes_restitution: bool = False  # predict(..., restitution=) reads each point's restitution (P,) or None
    # At points on jointed bodies, which no model speaks for (server.joints), Box2D's start
    # extrapolated in time along the stream (deepcontact.temporal) rather than as it is.
    extrapolates_jointed: bool = False
    envelope: Envelope | None = None  # what the model was trained on (its card's trained_on); None: not recorded
    wins_where_trained: bool = False  # its card records a measured gain over Box2D's start there

    def predict(self, bodies: np.ndarray, points: np.ndarray, world: World, step: int,
                previous: np.ndarray | None = None) -> Prediction:
        """The step's Prediction: impulses (P, 2) float32 N s, the stages' seconds, and
        served_by where another answer than this predictor's own is served."""
        raise NotImplementedError

    def check_domain(self, domain: Domain) -> None:
        """Raise GridMismatch if this predictor cannot serve that domain."""

    def warm_up(self, domain: Domain) -> float:
        """Prepare to serve grids of this domain's shape; seconds spent (0 when nothing to do)."""
        return 0.0


class _Normalization:
    """``spec.normalize(grid, "inputs")`` and ``spec.denormalize(grid, "targets")``
    for whole grids of the spec's shape, bit for bit.

    GridSpec broadcasts a row of per-channel constants over the grid's rows;
    here the constants are laid out over the whole grid once, so each step
    runs flat float32 operations, about twice as fast.
    """

    def __init__(self, spec: GridSpec):
        self.shape_in = (1, spec.ny, spec.nx, len(spec.inputs))
        self.shape_out = (spec.ny, spec.nx, len(spec.targets))
        self.in_mean, self.in_inv_std = self._tiled(spec, spec.inputs)
        self.out_mean, self.out_inv_std = self._tiled(spec, spec.targets)

    @staticmethod
    def _tiled(spec: GridSpec, channels) -> tuple[np.ndarray, np.ndarray]:
        """(mean, 1/std) per node and channel, (ny * nx * C,) float32, as GridSpec computes them."""
        mean, std = spec.normalization_arrays(channels)
        return np.tile(mean, spec.n_nodes), np.tile(np.float32(1.0) / std, spec.n_nodes)

    def inputs(self, grid: np.ndarray) -> np.ndarray:
        """Raw (ny, nx, Cin) float32 C-contiguous input grid -> the model's input
        (1, ny, nx, Cin) float32, normalized in place (one grid less to write)."""
        x = grid.reshape(-1)
        np.subtract(x, self.in_mean, out=x)
        x *= self.in_inv_std
        return x.reshape(self.shape_in)

    def targets(self, y: np.ndarray) -> np.ndarray:
        """The model's output (1, ny, nx, Cout) -> raw (ny, nx, Cout) float32 targets."""
        out = np.divide(y.reshape(-1), self.out_inv_std, dtype=np.float32)
        out += self.out_mean
        return out.reshape(self.shape_out)


class _DomainSpecs:
    """The model's GridSpec moved to a request's domain (same resolution, h,
    kernel, channels, normalization), cached per domain, with its
    :class:`_Normalization` when asked for one."""

    def __init__(self, base: GridSpec, fixed: bool, name: str, normalization: bool = False,
                 max_nodes: int = MAX_GRID_NODES):
        self.base, self.fixed, self.name = base, fixed, name
        self.normalization, self.max_nodes = normalization, max_nodes
        self._cache: dict[Domain, tuple[GridSpec, _Normalization | None]] = {}
        self._lock = threading.Lock()

    def get(self, domain: Domain) -> GridSpec:
        return self.entry(domain)[0]

    def entry(self, domain: Domain) -> tuple[GridSpec, _Normalization | None]:
        entry = self._cache.get(domain)
        if entry is not None:
            return entry
        b = self.base
        # The base spec with only its geometry moved: no field can be left behind.
        moved = GridSpec.for_domain(domain[0], domain[1], b.resolution, b.h)
        spec = dataclasses.replace(b, origin=moved.origin, shape=moved.shape)
        if spec.n_nodes > self.max_nodes:
            raise GridMismatch(
                f"this world's domain {domain[0]}-{domain[1]} at {b.resolution} m needs a "
                f"{spec.shape[0]}x{spec.shape[1]} grid, more than the server's {self.max_nodes:,} nodes "
                "(deepcontact serve --max-grid-nodes)")
        if self.fixed and spec.shape != b.shape:
            raise GridMismatch(
                f"model {self.name!r} takes {b.shape[0]}x{b.shape[1]} grids only; this world's domain "
                f"{domain[0]}-{domain[1]} at {b.resolution} m needs {spec.shape[0]}x{spec.shape[1]}")
        entry = (spec, _Normalization(spec) if self.normalization else None)
        with self._lock:
            if len(self._cache) > 64:  # many distinct domains: keep memory bounded
                self._cache.clear()
            self._cache[domain] = entry
        return entry


def _session(onnx_path: Path, intra_op_threads: int, inter_op_threads: int):
    """An ONNX Runtime CPU session with the server's thread counts. The other session
    options stay at ONNX Runtime's defaults: none measured faster (docs/performance.md)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = intra_op_threads
    options.inter_op_num_threads = inter_op_threads
    options.log_severity_level = 3
    return ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])


class ModelPredictor(Predictor):
    """An exported CNN with its card. `infer` runs the ONNX session, directly or
    through a micro-batcher (server.batching)."""

    batchable = True

    def __init__(self, card: ModelCard, onnx_path: Path, *, intra_op_threads: int = 1,
                 inter_op_threads: int = 1, max_grid_nodes: int = MAX_GRID_NODES):
        self.card = card
        self.name = card.name
        self.kind = card.kind
        self.description = card.description
        self.envelope, self.wins_where_trained = card.envelope, card.wins_where_trained
        self.fixed_grid = card.fixed_grid
        self.gridspec = card.gridspec
        self.session = _session(onnx_path, intra_op_threads, inter_op_threads)
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if card.input_name not in inputs or card.output_name not in outputs:
            raise ValueError(f"{onnx_path}: card names input {card.input_name!r} and output "
                             f"{card.output_name!r}, the model has {inputs} and {outputs}")
        self._specs = _DomainSpecs(card.gridspec, card.fixed_grid, card.name, normalization=True,
                                   max_nodes=max_grid_nodes)
        self.requires = tuple(sorted(set(needs(card.gridspec.inputs) + _combine_needs(card.combine))))
        if "point_friction" in self.requires:  # the grids are built without it (deepcontact.features)
            raise ModelCardError(f"{card.name}: a grid model cannot read the friction channel; a graph model can")
        self.infer = self.run_session
        self._warm_shapes: set[tuple[int, ...]] = set()
        self._warm_lock = threading.Lock()
        # The card's own grid first: a server that has started serves its shape at once.
        self._warm_shape((1, *card.gridspec.shape, len(card.gridspec.inputs)))

    def run_session(self, x: np.ndarray) -> np.ndarray:
        """x (B, ny, nx, Cin) float32 normalized -> (B, ny, nx, Cout)."""
        return self.session.run([self.card.output_name], {self.card.input_name: x})[0]

    def check_domain(self, domain: Domain) -> None:
        self._specs.get(domain)

    def warm_up(self, domain: Domain) -> float:
        """ONNX Runtime plans memory and picks kernels on a session's first run of an
        input shape, several times a normal step's cost (tens of ms for a 60x60 grid):
        run that once on zeros when a stream declares its world, not on its first step.
        Raises GridMismatch like check_domain."""
        _spec, norm = self._specs.entry(domain)
        return self._warm_shape(norm.shape_in)

    def _warm_shape(self, shape: tuple[int, ...]) -> float:
        if shape in self._warm_shapes:
            return 0.0
        with self._warm_lock:  # streams declaring the same new world at once warm it once
            if shape in self._warm_shapes:
                return 0.0
            t0 = time.perf_counter()
            self.run_session(np.zeros(shape, np.float32))  # straight to the session, not the batcher
            self._warm_shapes.add(shape)
            return time.perf_counter() - t0

    @property
    def warm_shapes(self) -> frozenset[tuple[int, ...]]:
        """Input shapes (1, ny, nx, Cin) this model has run."""
        return frozenset(self._warm_shapes)

    def predict(self, bodies, points, world, step, previous=None):
        spec, norm = self._specs.entry(world.domain)
        t0 = time.perf_counter()
        # The contact points' stencil weights come out of the input splat and
        # serve the output transfer too.
        grid, contacts = world_to_grids(bodies, points, spec, previous=previous, physics=world.physics,
                                        outside="drop", return_plan=True)
        x = norm.inputs(grid)  # == spec.normalize(grid, "inputs")[None]; grid is overwritten
        t1 = time.perf_counter()
        y = self.infer(x)
        t2 = time.perf_counter()
        out = norm.targets(y)  # == spec.denormalize(y[0], "targets")
        impulses, _ = contacts.g2p(out)  # == g2p(out, points["point"], spec, outside="drop")
        impulses = combine(self.card.combine, impulses, points["builtin"], self.card.correction_scale,
                           self.card.correction_threshold, _rest(self.card.combine, bodies, points))
        t3 = time.perf_counter()
        return Prediction(impulses.astype(np.float32, copy=False),
                          {"p2g": t1 - t0, "inference": t2 - t1, "g2p": t3 - t2})


#: A graph model's ONNX inputs (training/graph_model.py, to_onnx), and those a network with probes adds.
GRAPH_INPUT_NAMES = ("points", "ends", "dynamic")
PHYSICS_INPUT_NAMES = ("geometry", "masses", "inverse")


class GraphPredictor(Predictor):
    """The contact-graph model (card kind "graph", training/graph_model.py): no
    grids; the card's input channels are read at each contact point, the
    network passes messages between the points through their bodies, and its
    output is the correction at each point. Serves any domain. A card with
    `face` is served by server.face_route.FaceRoutePredictor, which runs one
    of these as its classifier."""

    def __init__(self, card: ModelCard, onnx_path: Path, *, intra_op_threads: int = 1,
                 inter_op_threads: int = 1, max_grid_nodes: int = MAX_GRID_NODES):  # no grid: any domain
        if card.face is not None:
            raise ModelCardError(f"{card.name}: a card with face is served by server.face_route.FaceRoutePredictor "
                                 "(load_model builds it)")
        self.card, self.name, self.kind, self.description = card, card.name, card.kind, card.description
        self.envelope, self.wins_where_trained = card.envelope, card.wins_where_trained
        self.gridspec = card.gridspec
        self.session = _session(onnx_path, intra_op_threads, inter_op_threads)
        names = {i.name for i in self.session.get_inputs()}
        # A network with probes (training/graph_model.py) also reads the contact problem's operator.
        self.physics = names == set(GRAPH_INPUT_NAMES + PHYSICS_INPUT_NAMES)
        if (names != set(GRAPH_INPUT_NAMES) and not self.physics) \
                or card.output_name not in [o.name for o in self.session.get_outputs()]:
            raise ValueError(f"{onnx_path}: a graph model takes points, ends and dynamic (and, with probes, "
                             f"geometry, masses and inverse) and returns {card.output_name!r}; this one takes "
                             f"{sorted(names)}")
        spec = card.gridspec
        self.inputs = spec.inputs
        self.in_mean, self.in_std = (a.astype(np.float32) for a in spec.normalization_arrays(spec.inputs))
        self.out_mean, self.out_std = (a.astype(np.float32) for a in spec.normalization_arrays(spec.targets))
        physics_needs = ("point_bodies", "body_inertia") if self.physics else ()
        self.gate = StepGate.from_dict(card.step_gate) if card.step_gate is not None else None
        gate_needs = ("builtin", "point_separation") if self.gate is not None else ()
        self.requires = tuple(sorted(set(needs(spec.inputs) + _combine_needs(card.combine) + ("point_bodies",)
                                         + physics_needs + gate_needs)))
        self.new_point = self.inputs.index("new_point") if "new_point" in self.inputs else None
        self.infer = self.run_session
        first = (np.zeros((1, 8), np.float32), np.ones((1, 2), np.float32), np.zeros((1, 2), np.float32))
        self.run_session(np.zeros((1, len(self.inputs)), np.float32), np.zeros((1, 2), np.int32),
                         np.zeros((1, 1), np.float32), *(first if self.physics else ()))
        # (the first run plans memory: not on a served step)

    def run_session(self, points: np.ndarray, ends: np.ndarray, dynamic: np.ndarray,
                    geometry: np.ndarray | None = None, masses: np.ndarray | None = None,
                    inverse: np.ndarray | None = None) -> np.ndarray:
        """points (P, F) float32 normalized, ends (P, 2) int32, dynamic (B, 1) float32 -> (P, T);
        with probes also geometry (P, 8), masses (P, 2) kg and inverse (B, 2), float32
        (deepcontact.kinematics.contact_physics)."""
        feed = {"points": points, "ends": ends, "dynamic": dynamic}
        if self.physics:
            feed.update(geometry=geometry, masses=masses, inverse=inverse)
        return self.session.run([self.card.output_name], feed)[0]

    def predict(self, bodies, points, world, step, previous=None, friction=None) -> Prediction:
        """As Predictor.predict, with stages features (the point channels, normalized),
        inference and g2p (the output's denormalization and combine, and the step gate's
        verdict), each summed over the card's passes. friction: (P,) each point's friction
        coefficient, which a network reading the friction channel needs (the request's
        point_friction)."""
        return self._predict(bodies, points, world, step, previous, friction, self.infer)

    def _predict(self, bodies, points, world, step, previous, friction, infer) -> Prediction:
        """predict's answer with `infer` (as run_session) answering the network's part."""
        t0 = time.perf_counter()
        if len(points) == 0:
            return Prediction(np.zeros((0, 2), np.float32))
        if "point_friction" in self.requires and friction is None:
            raise ValueError(f"{self.name} needs each point's friction")
        stages = {"features": 0.0, "inference": 0.0, "g2p": 0.0}
        ends = np.stack([points["body_a"], points["body_b"]], axis=1).astype(np.int32, copy=False)
        dynamic = (bodies["type"] == BODY_DYNAMIC).astype(np.float32)[:, None]
        # The operator does not depend on the warm start: one computation serves every pass.
        physics = contact_physics(bodies, points) if self.physics else ()
        warm, new = points, None
        for _ in range(self.card.passes):
            x = channel_values(self.inputs, Step(bodies, warm, previous, world.physics,
                                                 friction=friction)).astype(np.float32)
            if self.new_point is not None:  # new to Box2D, whatever an earlier pass served there
                if new is None:
                    new = x[:, self.new_point].copy()
                x[:, self.new_point] = new
            x -= self.in_mean
            x /= self.in_std
            t1 = time.perf_counter()
            y = infer(x, ends, dynamic, *physics)
            t2 = time.perf_counter()
            out = y * self.out_std + self.out_mean
            impulses = combine(self.card.combine, out, warm["builtin"], self.card.correction_scale,
                               self.card.correction_threshold, _rest(self.card.combine, bodies, warm))
            t3 = time.perf_counter()
            stages["features"] += t1 - t0
            stages["inference"] += t2 - t1
            stages["g2p"] += t3 - t2
            t0 = t3
            if self.card.passes > 1:
                warm = points.copy()
                warm["builtin"] = impulses
        if self.gate is not None:
            if not self.gate.serves_model(step_features(bodies, points, impulses)):
                impulses = points["builtin"].copy()  # Box2D's own warm start: the gate expects the model to lose here
            stages["g2p"] += time.perf_counter() - t0
        return Prediction(impulses.astype(np.float32, copy=False), stages)


def _combine_needs(how: str) -> tuple[str, ...]:
    """What a request must carry for this combine (channels.NEEDS keys)."""
    if how == "moving":
        return ("builtin", "point_bodies")
    return ("builtin",) if how in ("residual", "new-points", "persisting") else ()


def _rest(how: str, bodies: np.ndarray, points: np.ndarray) -> np.ndarray | None:
    return points_at_rest(bodies, points) if how == "moving" else None


def combine(how: str, predicted: np.ndarray, builtin: np.ndarray, scale: float = 1.0,
            threshold: float = 0.0, rest: np.ndarray | None = None) -> np.ndarray:
    """The warm start served, (P, 2) N s, from the model's output and the
    request's builtin warm start (both (P, 2)); see deepcontact.modelcard.
    A residual model's correction is dropped where its normal part is at most
    `threshold` N s, and multiplied by `scale` elsewhere. rest: (P,) bool, the
    points on bodies at rest, for "moving" (deepcontact.kinematics.points_at_rest)."""
    if how == "persisting":  # the correction at points Box2D already warm-starts only
        predicted = predicted * builtin.any(axis=1)[:, None]
        how = "residual"
    elif how == "moving":  # the correction on moving bodies only
        if rest is None:
            raise ValueError('combine "moving" needs the points at rest')
        predicted = predicted * ~rest[:, None]
        how = "residual"
    if how == "residual":
        if threshold > 0.0:
            predicted = predicted * (np.abs(predicted[:, :1]) > threshold)
        return builtin + scale * predicted if scale != 1.0 else predicted + builtin
    if how == "new-points":
        new = ~builtin.any(axis=1)  # Box2D carries no impulse into a point it has not seen
        return np.where(new[:, None], predicted, builtin)
    return predicted


@dataclasses.dataclass
class ConstantPredictor(Predictor):
    """The same (normal, tangent) for every point: `zero` and `bad`."""

    name: str
    normal: float
    tangent: float
    kind: str = "provider"
    description: str = "the same impulse at every point"

    def predict(self, bodies, points, world, step, previous=None):
        out = np.empty((len(points), 2), np.float32)
        out[:, 0], out[:, 1] = self.normal, self.tangent
        return Prediction(out)


@dataclasses.dataclass
class RandomPredictor(Predictor):
    """Thesis §8.2.2: normal U(0, 5), tangent U(-2, 2) N s; the stream of
    numbers depends only on (seed, step), so runs repeat."""

    seed: int = 0
    name: str = "random"
    kind: str = "provider"
    description: str = "the thesis's random warm start: normal U(0, 5), tangent U(-2, 2) N s"

    def predict(self, bodies, points, world, step, previous=None):
        rng = np.random.default_rng([self.seed, step])
        out = np.empty((len(points), 2), np.float32)
        out[:, 0] = rng.uniform(0.0, 5.0, len(points))
        out[:, 1] = rng.uniform(-2.0, 2.0, len(points))
        return Prediction(out)


class GridIdentityPredictor(Predictor):
    """P2G of the impulses sent in the request, then G2P back (thesis §8.2.4)."""

    name = "grid-identity"
    kind = "provider"
    description = "the request's own impulses through the grids and back: what the transfer loses (the thesis's Grid)"

    def __init__(self, gridspec: GridSpec, max_grid_nodes: int = MAX_GRID_NODES):
        self.gridspec = gridspec
        self._specs = _DomainSpecs(gridspec, False, self.name, max_nodes=max_grid_nodes)

    def check_domain(self, domain: Domain) -> None:
        self._specs.get(domain)

    def predict(self, bodies, points, world, step, previous=None):
        spec = self._specs.get(world.domain)
        t0 = time.perf_counter()
        # One set of weights for both directions: == g2p(p2g(point, impulse), point).
        points_plan = plan(points["point"], spec, outside="drop")
        grid, _ = points_plan.p2g(points["impulse"])
        t1 = time.perf_counter()
        out, _ = points_plan.g2p(grid)
        t2 = time.perf_counter()
        return Prediction(out.astype(np.float32, copy=False), {"p2g": t1 - t0, "g2p": t2 - t1})


def providers(random_seed: int = 0, max_grid_nodes: int = MAX_GRID_NODES) -> list[Predictor]:
    """The providers every server offers besides its models."""
    return [
        ConstantPredictor("zero", 0.0, 0.0),
        RandomPredictor(seed=random_seed),
        ConstantPredictor("bad", 50.0, 50.0),
        GridIdentityPredictor(GridSpec.thesis(), max_grid_nodes),
    ]


def load_models(folder: Path, *, intra_op_threads: int = 1, inter_op_threads: int = 1,
                max_grid_nodes: int = MAX_GRID_NODES, skip_bad: bool = False) -> list[Predictor]:
    """One predictor per card (`*.json`) in folder, in the cards' order, each running the
    ONNX file its card names (as load_model builds them).

    Every card and ONNX file is checked (server.model_folder): a card that does not read,
    names a missing or broken ONNX file or one that does not match it, an alias of a bad
    card, a face whose fallback card is bad, an ONNX file that does not parse or that no
    card names. Any bad file stops the server with one ModelCardError naming them all, so a
    deployment does not serve part of its models by accident; with skip_bad the good ones
    are served and each bad one is logged."""
    from server import model_folder

    folder = Path(folder)
    problems = model_folder.FolderProblems(folder)
    cards = model_folder.read_cards(folder, problems)
    model_folder.check_onnx_files(folder, cards, problems)
    loaded: dict[Path, Predictor] = {}
    # Cards without a fallback first: a face card whose fallback is bad is then told so.
    for path, card in sorted(cards.items(), key=lambda item: (item[1].face is not None, item[0])):
        problem = model_folder.dependency_problem(path, card, problems)
        if problem is None:
            try:
                loaded[path] = load_model(path, card, intra_op_threads=intra_op_threads,
                                          inter_op_threads=inter_op_threads, max_grid_nodes=max_grid_nodes)
            except Exception as exc:  # any reason one card cannot be served is that card's problem
                problem = model_folder.describe(exc)
        if problem is not None:
            problems.add(path, problem)
    if not skip_bad:
        problems.raise_if_any()
    problems.log_skipped()
    return [loaded[path] for path in sorted(loaded)]


def load_model(path: Path, card: ModelCard | None = None, *, intra_op_threads: int = 1,
               inter_op_threads: int = 1, max_grid_nodes: int = MAX_GRID_NODES,
               _routes: tuple[str, ...] = ()) -> Predictor:
    """The predictor of one card (`card`: the card at `path`, when already read): a
    ModelPredictor for a grid model, a GraphPredictor for kind "graph" (a
    server.mirror_image.MirroredGraphPredictor where the card says mirror), and for a graph card
    with `face` a server.face_route.FaceRoutePredictor, built with its classifier (a
    GraphPredictor of the card's network) and its fallback card's predictor (a route of its
    own where that card has a face).
    ModelCardError naming the card for anything that keeps it from being served, also
    an ONNX file ONNX Runtime cannot load (its own errors name neither card nor flag)."""
    from server.model_folder import plain_name

    path = Path(path)
    card = ModelCard.load(path) if card is None else card
    if not plain_name(card.onnx_file):  # a card serves a file of its own folder, never a path out of it
        raise ModelCardError(f"{path}: names {card.onnx_file!r}, not a file name in {path.parent}")
    onnx_path = card.onnx_path(path)
    if not onnx_path.is_file():
        raise ModelCardError(f"{path}: names {card.onnx_file}, which is not in {path.parent}")
    if card.kind == "graph" and card.mirror:
        from server.mirror_image import MirroredGraphPredictor as cls
    else:
        cls = GraphPredictor if card.kind == "graph" else ModelPredictor
    # A face card's network is its classifier: the card without the route (and without a gate,
    # which judges the route's answer, not the labels).
    network = card if card.face is None else dataclasses.replace(card, face=None, step_gate=None)
    threads = {"intra_op_threads": intra_op_threads, "inter_op_threads": inter_op_threads}
    try:
        predictor = cls(network, onnx_path, **threads, max_grid_nodes=max_grid_nodes)
    except Exception as exc:
        if not type(exc).__module__.startswith("onnxruntime"):  # ours say which file and what does not match
            raise
        # onnxruntime's own (InvalidProtobuf, InvalidGraph, Fail, ...) name neither the card nor the folder.
        raise ModelCardError(f"{path}: ONNX Runtime cannot serve {card.onnx_file} "
                             f"({type(exc).__name__}: {' '.join(str(exc).split())})") from None
    if card.face is None:
        return predictor
    from server.face_route import FaceRoutePredictor

    fallback = _face_fallback(path, card, _routes, **threads, max_grid_nodes=max_grid_nodes)
    return FaceRoutePredictor(card, predictor, fallback)


def _face_fallback(path: Path, card: ModelCard, routes: tuple[str, ...] = (), **load) -> Predictor | None:
    """The predictor of the card a face card at `path` falls back to (served where its labels
    look wrong, past max_points, outside its classifier's training, or late:
    deepcontact.modelcard), None where it names none (Box2D's warm start). A face card there is
    another route, tried in turn; routes: the face cards already on the way here.
    ModelCardError for a name that is not a card beside it, or a chain of routes that comes
    back to one of its own."""
    from server.model_folder import plain_name

    fallback = card.face["fallback"]
    if fallback is None:
        return None
    if not plain_name(f"{fallback}.json"):
        raise ModelCardError(f"{path}: its face falls back to {fallback!r}, not a card's name in {path.parent}")
    routes = (*routes, card.name)
    if fallback in routes:
        raise ModelCardError(f"{path}: its face falls back in a circle ({' -> '.join([*routes, fallback])}); "
                             f"end the chain at a card without a face")
    fallback_path = path.with_name(f"{fallback}.json")
    fallback_card = ModelCard.load(fallback_path)
    return load_model(fallback_path, fallback_card, _routes=routes, **load)
