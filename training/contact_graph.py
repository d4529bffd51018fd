"""Recorded steps as contact graphs: the training data of the contact-graph model.

A step's contact graph has the step's bodies as nodes and its contact points
as edges (each point joins body_a and body_b). No grid: every value is read
at the point itself, with the channel definitions the grid models use
(deepcontact.channels), so the server computes them the same way.

    gs = build_graph_set("data/thesis-train-1-300.h5", GRAPH_INPUTS, GRAPH_TARGETS, max_steps=8000)
    features, targets, ends, dynamic = gs.batch([0, 1, 2])
    # features (P, F) float32, targets (P, T) float32, both raw (SI units);
    # ends (P, 2) int32 rows of `dynamic`, the steps' bodies stacked;
    # dynamic (B, 1) float32, 1 for a body that takes impulses

A GraphSet is saved as one .npz (no pickle) beside the runs that use it.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from deepcontact.channels import CHANNELS, Step, channel_values
from deepcontact.kinematics import BODY_DYNAMIC, contact_physics
from training.grids import GridDataError, iter_steps, open_dataset, select_steps

#: What the contact-graph model reads at each point: geometry, Box2D's own warm
#: start, the velocities the solver starts from, and the effective masses that turn one into the other.
GRAPH_INPUTS = ("normal_x", "normal_y", "separation", "builtin_normal", "builtin_tangent", "new_point",
                "vn", "vt", "vn_builtin", "vt_builtin", "normal_mass", "tangent_mass",
                "jacobi_normal", "jacobi_tangent")
GRAPH_TARGETS = ("correction_normal", "correction_tangent")
#: GRAPH_INPUTS with every impulse, velocity and mass over the step's own scale (Step.scales):
#: the inputs of a network that reads a heavier or faster world as the same problem.
SCALED_GRAPH_INPUTS = tuple(n if CHANNELS[n].unit in ("1", "m") else f"{n}_scaled" for n in GRAPH_INPUTS)


@dataclasses.dataclass
class GraphSet:
    """The contact graphs of some recorded steps, stacked.

    features (N, F) float32 and targets (N, T) float32: per point, raw.
    ends (N, 2) int32: each point's two bodies, rows of its own step's bodies.
    dynamic (M,) bool: per body of every step, stacked.
    point_offsets, body_offsets (S + 1,) int64: step k owns points
        point_offsets[k]:point_offsets[k+1] and bodies body_offsets[k]:...
    builtin (N, 2) float32: Box2D's warm start at each point (N s), for scoring.
    geometry (N, 8) float32: normal (2), tangent (2), and the point relative to
        body A's and body B's centre (2 + 2, m): each point's Jacobian rows.
    masses (N, 2) float32: effective mass along normal and tangent (kg).
    inverse (M, 2) float32: per body, 1/mass and 1/inertia (0 for static bodies).
    The last three let training run the solver's iteration on a prediction's
    error (training.graph_loss).
    speed (M,) float32: per body, its recorded linear speed (m/s), which says
    which bodies move (deepcontact.kinematics.bodies_moving) to a loss.
    """

    features: np.ndarray
    targets: np.ndarray
    ends: np.ndarray
    dynamic: np.ndarray
    point_offsets: np.ndarray
    body_offsets: np.ndarray
    builtin: np.ndarray
    geometry: np.ndarray
    masses: np.ndarray
    inverse: np.ndarray
    speed: np.ndarray
    inputs: tuple[str, ...]
    target_names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.point_offsets) - 1

    def batch(self, steps) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Steps (indices into this set) as one graph: their disjoint union.

        Returns features (P, F), targets (P, T), ends (P, 2) int32 into the
        returned dynamic (B, 1) float32."""
        points, bodies, ends = self._rows(steps)
        return self.features[points], self.targets[points], ends, self.dynamic[bodies, None].astype(np.float32)

    def solver_batch(self, steps) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the solver's iteration needs for the same batch: geometry (P, 8),
        masses (P, 2), inverse (B, 2), rows as in batch(steps)."""
        points, bodies, _ = self._rows(steps)
        return self.geometry[points], self.masses[points], self.inverse[bodies]

    def body_speeds(self, steps) -> np.ndarray:
        """(B,) float32: each body's recorded speed (m/s), rows as in batch(steps)."""
        _, bodies, _ = self._rows(steps)
        return self.speed[bodies]

    def _rows(self, steps):
        steps = np.asarray(steps, np.int64)
        p0, p1 = self.point_offsets[steps], self.point_offsets[steps + 1]
        b0, b1 = self.body_offsets[steps], self.body_offsets[steps + 1]
        # Each step's body rows move to where its bodies land in the batch.
        shift = np.cumsum(np.concatenate([[0], (b1 - b0)[:-1]]))
        points = _ranges(p0, p1)
        ends = self.ends[points] + np.repeat(shift, p1 - p0)[:, None].astype(np.int32)
        return points, _ranges(b0, b1), ends

    def save(self, path: str | os.PathLike) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part.npz", dir=path.parent)
        os.close(fd)
        try:
            arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
            arrays["inputs"] = np.array(self.inputs)
            arrays["target_names"] = np.array(self.target_names)
            np.savez(tmp, **arrays)
            os.chmod(tmp, 0o644)  # mkstemp makes it private
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "GraphSet":
        with np.load(path, allow_pickle=False) as f:
            d = {k: f[k] for k in f.files}
        d["inputs"] = tuple(str(x) for x in d["inputs"])
        d["target_names"] = tuple(str(x) for x in d["target_names"])
        return cls(**d)


def _ranges(starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """Concatenated aranges start..stop, without a Python loop over them."""
    lengths = stops - starts
    if lengths.sum() == 0:
        return np.zeros(0, np.int64)
    offsets = np.repeat(starts - np.cumsum(np.concatenate([[0], lengths[:-1]])), lengths)
    return np.arange(lengths.sum()) + offsets


def build_graph_set(path: str | os.PathLike, inputs=GRAPH_INPUTS, targets=GRAPH_TARGETS, *,
                    max_steps: int | None = None, seed: int = 0, progress=None) -> GraphSet:
    """The contact graphs of the steps with contacts of one recorded file
    (at most max_steps of them, drawn as training.grids.select_steps draws)."""
    for n in (*inputs, *targets):
        if n not in CHANNELS or CHANNELS[n].source != "contacts":
            raise GridDataError(f"{n!r} is not a contact-point channel; the contact-graph model reads "
                                f"channels of the contact points only")
    with open_dataset(path) as ds:
        steps = ds.steps
    index = select_steps(steps, max_steps, seed)
    if len(index) == 0:
        raise GridDataError(f"{path}: no steps with contact points")
    feats, targs, ends, dyn, builtin, n_points, n_bodies = [], [], [], [], [], [], []
    geometry, masses, inverse, speed = [], [], [], []
    # Steps are read one by one and their channels computed many steps at a time (a Python
    # loop over steps costs more than their arithmetic), unless a channel reads the previous step.
    per_call = 1 if any(CHANNELS[n].temporal for n in (*inputs, *targets)) else STEPS_AT_ONCE
    # A batch holds one simulation's steps: its world's physics and scales (Step.scales) are theirs.
    for chunk in _batches((step for _, step in iter_steps(path, steps, index)), per_call,
                          key=iter(steps["seed"][index])):
        world = one_world(chunk)
        c, b = world.contacts, world.bodies
        for out, value in zip((geometry, masses, inverse), contact_physics(b, c)):
            out.append(value)
        speed.append(np.hypot(*b["velocity"].T).astype(np.float32))
        feats.append(channel_values(inputs, world).astype(np.float32))
        targs.append(channel_values(targets, world).astype(np.float32))
        ends.extend(np.stack([s.contacts["body_a"], s.contacts["body_b"]], axis=1).astype(np.int32) for s in chunk)
        dyn.append(b["type"] == BODY_DYNAMIC)
        builtin.append(c["builtin"].astype(np.float32))
        n_points.extend(len(s.contacts) for s in chunk)
        n_bodies.extend(len(s.bodies) for s in chunk)
        if progress is not None:
            progress.update(len(chunk))
    gs = GraphSet(np.concatenate(feats), np.concatenate(targs), np.concatenate(ends), np.concatenate(dyn),
                  np.concatenate([[0], np.cumsum(n_points)]).astype(np.int64),
                  np.concatenate([[0], np.cumsum(n_bodies)]).astype(np.int64),
                  np.concatenate(builtin), np.concatenate(geometry), np.concatenate(masses),
                  np.concatenate(inverse), np.concatenate(speed), tuple(inputs), tuple(targets))
    if not (np.isfinite(gs.features).all() and np.isfinite(gs.targets).all()):
        raise GridDataError(f"{path}: non-finite channel values")
    return gs


def step_iterations(path: str | os.PathLike, max_steps: int | None = None, seed: int = 0) -> np.ndarray:
    """(S,) int64: Box2D's recorded velocity iterations (its built-in warm start) at each step
    build_graph_set(path, max_steps=max_steps, seed=seed) reads, in its order."""
    with open_dataset(path) as ds:
        steps = ds.steps
    return steps["velocity_iterations"][select_steps(steps, max_steps, seed)].astype(np.int64)


def step_converged(path: str | os.PathLike, max_steps: int | None = None, seed: int = 0) -> np.ndarray:
    """(S,) bool, in step_iterations' order: whether Box2D's solve ended under its cap on
    velocity iterations (the recorded scene's) at that step. Where it did not, the recorded
    impulses, and so the step's targets, are the solver's unconverged iterate."""
    from simclient.worlds import spec_from_dict

    with open_dataset(path) as ds:
        cap = spec_from_dict(ds.scene).solver.velocity_iterations
    return step_iterations(path, max_steps, seed) < cap


#: Steps whose channels build_graph_set computes in one call: about 40,000 points of the thesis world.
STEPS_AT_ONCE = 256


def _batches(items: Iterator, size: int, key: Iterator | None = None) -> Iterator[list]:
    """Lists of at most `size` items in order; with `key` (one value per item), a list also ends
    where the key changes."""
    batch, last = [], None
    for item in items:
        k = next(key) if key is not None else None
        if batch and (len(batch) == size or k != last):
            yield batch
            batch = []
        batch.append(item)
        last = k
    if batch:
        yield batch


def one_world(steps: list[Step]) -> Step:
    """Steps of one recorded file as one Step: bodies and points concatenated, each
    step's body_a/body_b moved past the bodies of the steps before it, no previous step.

    A point's channels read its own two bodies and, through the bodies' sums, only
    the points of its own step, in the same order: they equal the steps' own, bit for
    bit, for every channel that is not temporal. One step is returned as it is.
    """
    if len(steps) == 1:
        return steps[0]
    bodies = np.concatenate([s.bodies for s in steps])
    contacts = np.concatenate([s.contacts for s in steps])
    shift = np.repeat(np.cumsum([0] + [len(s.bodies) for s in steps[:-1]]), [len(s.contacts) for s in steps])
    contacts["body_a"] += shift.astype(contacts["body_a"].dtype)
    contacts["body_b"] += shift.astype(contacts["body_b"].dtype)
    oracle = None if steps[0].oracle is None else np.concatenate([s.oracle for s in steps])
    friction = None if steps[0].friction is None else np.concatenate([s.friction for s in steps])
    return Step(bodies, contacts, None, steps[0].physics, oracle, friction)


#: Each geometry column's sign (deepcontact.kinematics.contact_physics) when the world is
#: reflected left to right (x -> -x): the normal's and both lever arms' x change sign, and
#: Box2D's tangent (n_y, -n_x) becomes
#: (n_y, n_x), its y component's sign changed (it is then minus the reflected tangent, which is
#: why tangent channels have Channel.mirror -1).
MIRROR_GEOMETRY = np.array([-1, 1, 1, -1, -1, 1, -1, 1], np.float32)
