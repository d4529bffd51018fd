"""What the server can answer a step with: ONNX models and simple providers.

Every predictor maps a step's records to one (normal, tangent) impulse per
contact point, in the request's order, and says what its stages cost:

    impulses, stages = predictor.predict(bodies, points, domain, step)
    # impulses (P, 2) float32, N s; stages {"p2g": s, "inference": s, "g2p": s}

`ModelPredictor` runs P2G -> ONNX -> G2P with its card's GridSpec and the
shared transfer code (deepcontact.transfer), exactly as training did.
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

from deepcontact.gridspec import GridSpec
from deepcontact.modelcard import ModelCard
from deepcontact.transfer import g2p, p2g, world_to_grids

Domain = tuple[tuple[float, float], tuple[float, float]]


class GridMismatch(ValueError):
    """A fixed-size model asked for a grid of another size."""


class Predictor:
    name: str
    kind: str
    fixed_grid: bool = False
    gridspec: GridSpec | None = None

    def predict(self, bodies: np.ndarray, points: np.ndarray, domain: Domain,
                step: int) -> tuple[np.ndarray, dict[str, float]]:
        raise NotImplementedError

    def check_domain(self, domain: Domain) -> None:
        """Raise GridMismatch if this predictor cannot serve that domain."""


class _DomainSpecs:
    """The model's GridSpec moved to a request's domain (same resolution, h,
    kernel, channels, normalization), cached per domain."""

    def __init__(self, base: GridSpec, fixed: bool, name: str):
        self.base, self.fixed, self.name = base, fixed, name
        self._cache: dict[Domain, GridSpec] = {}
        self._lock = threading.Lock()

    def get(self, domain: Domain) -> GridSpec:
        spec = self._cache.get(domain)
        if spec is not None:
            return spec
        b = self.base
        spec = GridSpec.for_domain(domain[0], domain[1], b.resolution, b.h, kernel=b.kernel, inputs=b.inputs,
                                   targets=b.targets, normalization=dict(b.normalization),
                                   wall_mass=b.wall_mass, walls=b.walls)
        if self.fixed and spec.shape != b.shape:
            raise GridMismatch(
                f"model {self.name!r} takes {b.shape[0]}x{b.shape[1]} grids only; this world's domain "
                f"{domain[0]}-{domain[1]} at {b.resolution} m needs {spec.shape[0]}x{spec.shape[1]}")
        with self._lock:
            if len(self._cache) > 64:  # many distinct domains: keep memory bounded
                self._cache.clear()
            self._cache[domain] = spec
        return spec


class ModelPredictor(Predictor):
    """An exported CNN with its card. `infer` runs the ONNX session, directly or
    through a micro-batcher (server.batching)."""

    def __init__(self, card: ModelCard, onnx_path: Path, *, intra_op_threads: int = 1,
                 inter_op_threads: int = 1):
        import onnxruntime as ort

        self.card = card
        self.name = card.name
        self.kind = card.kind
        self.fixed_grid = card.fixed_grid
        self.gridspec = card.gridspec
        options = ort.SessionOptions()
        options.intra_op_num_threads = intra_op_threads
        options.inter_op_num_threads = inter_op_threads
        options.log_severity_level = 3
        self.session = ort.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
        inputs = [i.name for i in self.session.get_inputs()]
        outputs = [o.name for o in self.session.get_outputs()]
        if card.input_name not in inputs or card.output_name not in outputs:
            raise ValueError(f"{onnx_path}: card names input {card.input_name!r} and output "
                             f"{card.output_name!r}, the model has {inputs} and {outputs}")
        self._specs = _DomainSpecs(card.gridspec, card.fixed_grid, card.name)
        self.infer = self.run_session

    def run_session(self, x: np.ndarray) -> np.ndarray:
        """x (B, ny, nx, Cin) float32 normalized -> (B, ny, nx, Cout)."""
        return self.session.run([self.card.output_name], {self.card.input_name: x})[0]

    def check_domain(self, domain: Domain) -> None:
        self._specs.get(domain)

    def predict(self, bodies, points, domain, step):
        spec = self._specs.get(domain)
        t0 = time.perf_counter()
        grids = world_to_grids(bodies, points, spec, outside="drop")
        x = spec.normalize(grids, "inputs")[None]
        t1 = time.perf_counter()
        y = self.infer(np.ascontiguousarray(x, np.float32))
        t2 = time.perf_counter()
        out = spec.denormalize(y[0], "targets")
        impulses, _ = g2p(out, points["point"], spec, outside="drop")
        if self.card.residual:
            impulses = impulses + points["builtin"]
        t3 = time.perf_counter()
        return impulses.astype(np.float32, copy=False), {"p2g": t1 - t0, "inference": t2 - t1, "g2p": t3 - t2}


@dataclasses.dataclass
class ConstantPredictor(Predictor):
    """The same (normal, tangent) for every point: `zero` and `bad`."""

    name: str
    normal: float
    tangent: float
    kind: str = "provider"

    def predict(self, bodies, points, domain, step):
        out = np.empty((len(points), 2), np.float32)
        out[:, 0], out[:, 1] = self.normal, self.tangent
        return out, {}


@dataclasses.dataclass
class RandomPredictor(Predictor):
    """Thesis §8.2.2: normal U(0, 5), tangent U(-2, 2) N s; the stream of
    numbers depends only on (seed, step), so runs repeat."""

    seed: int = 0
    name: str = "random"
    kind: str = "provider"

    def predict(self, bodies, points, domain, step):
        rng = np.random.default_rng([self.seed, step])
        out = np.empty((len(points), 2), np.float32)
        out[:, 0] = rng.uniform(0.0, 5.0, len(points))
        out[:, 1] = rng.uniform(-2.0, 2.0, len(points))
        return out, {}


class GridIdentityPredictor(Predictor):
    """P2G of the impulses sent in the request, then G2P back (thesis §8.2.4)."""

    name = "grid-identity"
    kind = "provider"

    def __init__(self, gridspec: GridSpec):
        self.gridspec = gridspec
        self._specs = _DomainSpecs(gridspec, False, self.name)

    def predict(self, bodies, points, domain, step):
        spec = self._specs.get(domain)
        t0 = time.perf_counter()
        grid, _ = p2g(points["point"], points["impulse"], spec, outside="drop")
        t1 = time.perf_counter()
        out, _ = g2p(grid, points["point"], spec, outside="drop")
        t2 = time.perf_counter()
        return out.astype(np.float32, copy=False), {"p2g": t1 - t0, "g2p": t2 - t1}


def providers(random_seed: int = 0) -> list[Predictor]:
    """The providers every server offers besides its models."""
    return [
        ConstantPredictor("zero", 0.0, 0.0),
        RandomPredictor(seed=random_seed),
        ConstantPredictor("bad", 50.0, 50.0),
        GridIdentityPredictor(GridSpec.thesis()),
    ]


def load_models(folder: Path, *, intra_op_threads: int = 1, inter_op_threads: int = 1) -> list[ModelPredictor]:
    """Every `*.onnx` in folder with its `*.json` card. A model without a card,
    or a card that does not match its model, stops the server with a message."""
    models = []
    for onnx_path in sorted(Path(folder).glob("*.onnx")):
        card = ModelCard.load(onnx_path.with_suffix(".json"))
        models.append(ModelPredictor(card, onnx_path, intra_op_threads=intra_op_threads,
                                     inter_op_threads=inter_op_threads))
    return models
