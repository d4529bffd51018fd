"""Recorded steps -> the arrays a model trains and is scored on (no TensorFlow).

For each selected step of an HDF5 data file (``deepcontact generate``):

    inputs           (N, ny, nx, Cin)  float32  world_to_grids(bodies, points, spec,
                                                 previous=last step's points, physics), raw,
                                                 wall mass included (thesis §8.1)
    targets          (N, ny, nx, Cout) float32  targets_to_grids(step, spec), raw, N s
    point_offsets    (N + 1,)          int64    step k's points are rows offsets[k]:offsets[k+1]
    point_positions  (P, 2)            float32  contact points, m
    point_targets    (P, Cout)         float32  the spec's target channels per point (the
                                                 final impulse, N s, by default)
    point_builtin    (P, 2)            float32  Box2D's own warm start (normal, tangent), N s
    point_new        (P,)              bool     the point is new this step (no builtin)
    point_nodes      (P, S)            int32    SPH G2P as a sparse map (TransferPlan.g2p_operator):
    point_weights    (P, S)            float32  value[p] = sum_s weights[p, s] grid[nodes[p, s]]
    steps            (N,)              int64    row of the file's /steps index

The previous step's points feed temporal channels; the scene's gravity and
time step, contact-velocity channels; the file's /oracle impulses (data made
with ``generate --oracle``), oracle targets.

A :class:`GridSet` is written once per run as ``.npy`` files (no pickle) under
a temporary name and renamed, then memory-mapped, so epochs only gather
batches.  ``meta.json`` records what it was made from; a cache whose meta does
not match is rebuilt.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import h5py
import numpy as np

from deepcontact.channels import Step, channel_values, particle_positions
from deepcontact.features import step_to_grids, targets_to_grids
from deepcontact.gridspec import GridSpec
from deepcontact.transfer import DOMAIN_TOLERANCE, g2p
from deepcontact.kinematics import Physics
from simclient.provider import point_friction
from simclient.scene import body_friction
from simclient.worlds import WorldSpec, spec_from_dict
from training.dataset import Dataset, DatasetError

CACHE_VERSION = 2

#: How points beyond the domain are treated in every transfer of training and
#: evaluation (and recorded in the model card, for the server to do the same).
#: A contact point against a wall can lie a couple of centimetres outside it
#: after a hard impact (30 of 1.04 M points of seeds 1-40 beyond 1 cm, none
#: beyond 2.3 cm): such points are left out of the grids and get 0 from G2P,
#: rather than failing the whole file.
TRANSFER = {"outside": "drop", "tolerance": DOMAIN_TOLERANCE, "g2p": "sph"}

_ARRAYS = ("inputs", "targets", "point_offsets", "point_positions", "point_targets", "point_builtin", "point_new",
           "point_nodes", "point_weights", "steps")
_MAPPED = ("inputs", "targets", "point_nodes", "point_weights")  # the large ones: memory-mapped


class GridDataError(ValueError):
    """Data that cannot be turned into training grids (missing, empty, mismatched, non-finite)."""


def select_steps(steps: np.ndarray, max_steps: int | None = None, seed: int = 0) -> np.ndarray:
    """Rows of a /steps index to use: steps with contact points (nothing to learn
    elsewhere), at most ``max_steps`` of them drawn without replacement with
    ``numpy.random.default_rng(seed)``, in file order.  (N,) int64."""
    index = np.flatnonzero(steps["point_count"] > 0).astype(np.int64)
    if max_steps is not None and max_steps < len(index):
        index = np.sort(np.random.default_rng(seed).choice(index, size=max_steps, replace=False))
    return index


def spec_for_scene(scene: dict, *, resolution: float = 0.25, h: float = 0.5, kernel: str = "poly6",
                   inputs=None, targets=None) -> GridSpec:
    """The grid over a scene's static box (lower-left at the origin), thesis defaults: 0.25 m, h = 0.5 m."""
    kw = {}
    if inputs is not None:
        kw["inputs"] = tuple(inputs)
    if targets is not None:
        kw["targets"] = tuple(targets)
    w, hgt = scene["box_size"]
    return GridSpec.for_domain((0.0, 0.0), (float(w), float(hgt)), resolution, h, kernel, **kw)


def check_scene(spec: GridSpec, scene: dict, path: str | os.PathLike) -> None:
    """Raise GridDataError unless ``spec`` covers exactly the scene's box (what it was made for)."""
    expected = spec_for_scene(scene, resolution=spec.resolution, h=spec.h)
    if expected.shape != spec.shape or expected.origin != spec.origin:
        raise GridDataError(
            f"{path}: scene {scene.get('name')!r} with box {scene.get('box_size')} m needs a "
            f"{expected.shape[0]} x {expected.shape[1]} grid at {spec.resolution} m; the model's grid is "
            f"{spec.shape[0]} x {spec.shape[1]} at origin {spec.origin}")


def open_dataset(path: str | os.PathLike) -> Dataset:
    """:class:`Dataset` with its errors as GridDataError (missing, not HDF5, empty, other schema)."""
    try:
        return Dataset(path)
    except DatasetError as exc:
        raise GridDataError(str(exc)) from None


def iter_steps(path: str | os.PathLike, steps: np.ndarray, index: np.ndarray) -> Iterator[tuple[int, Step]]:
    """Yield ``(row, step)`` for the rows ``index`` (ascending) of ``steps``.

    ``step`` holds the bodies at collide time and the points after the solve,
    the previous step's points of the same simulation (None for its first
    step), the simulation's physics (the seed's where the file keeps it, else
    the scene's), the oracle's impulses when the file has them, and each
    point's friction (a scene's seed gives it, simclient.scene.body_friction,
    as the files of before the records held it; a user's world's points carry
    their own). Reads one simulation's span at a
    time: per-step reads decompress a whole gzip chunk each (about 8 ms a step
    here), a span read once per seed.
    """
    with h5py.File(path, "r") as f:
        scene = spec_from_dict(json.loads(f.attrs["scene"]))
        per_seed = {int(k): Physics(v[0], (v[1], v[2])) for k, v in json.loads(f.attrs.get("physics", "{}")).items()}
        bodies_ds, points_ds, oracle_ds = f["bodies"], f["points"], f.get("oracle")
        seeds = steps["seed"][index]
        bounds = np.flatnonzero(np.diff(seeds)) + 1
        for group in np.split(index, bounds):  # loop over simulations
            first = int(group[0])
            # One step more in front, for the previous points, when it is of the same simulation.
            lead = first - 1 if first > 0 and steps["seed"][first - 1] == steps["seed"][first] else first
            rows = steps[lead:int(group[-1]) + 1]
            b0 = int(rows["body_offset"].min())
            b1 = int((rows["body_offset"] + rows["body_count"]).max())
            p0 = int(rows["point_offset"].min())
            p1 = int((rows["point_offset"] + rows["point_count"]).max())
            bodies, points = bodies_ds[b0:b1], points_ds[p0:p1]
            oracle = oracle_ds[p0:p1] if oracle_ds is not None else None
            seed = int(steps["seed"][first])
            physics = per_seed[seed] if seed in per_seed else scene.physics
            mu = points["friction"].astype(np.float64) if isinstance(scene, WorldSpec) else \
                point_friction(body_friction(scene, seed), points)

            def span(row, offset, count, base):
                return slice(int(row[offset]) - base, int(row[offset]) - base + int(row[count]))

            for i in group:  # loop over steps, not particles
                row = steps[i]
                pts = span(row, "point_offset", "point_count", p0)
                prev = points[span(steps[i - 1], "point_offset", "point_count", p0)] if i > lead else None
                yield int(i), Step(bodies[span(row, "body_offset", "body_count", b0)], points[pts], prev, physics,
                                   None if oracle is None else oracle[pts], mu[pts])


@dataclass
class GridSet:
    """Grids and contact points of the selected steps of one file (see the module docstring)."""

    inputs: np.ndarray
    targets: np.ndarray
    point_offsets: np.ndarray
    point_positions: np.ndarray
    point_targets: np.ndarray
    point_builtin: np.ndarray
    point_new: np.ndarray
    point_nodes: np.ndarray
    point_weights: np.ndarray
    steps: np.ndarray
    meta: dict

    def __len__(self) -> int:
        return len(self.steps)

    def points(self, k: int) -> slice:
        """Rows of the point arrays belonging to step ``k`` of this set."""
        return slice(int(self.point_offsets[k]), int(self.point_offsets[k + 1]))


def _meta(path: Path, spec: GridSpec, index: np.ndarray, ds: Dataset) -> dict[str, Any]:
    st = path.stat()
    raw = spec.with_normalization({})  # normalization does not change raw grids
    return {
        "cache_version": CACHE_VERSION,
        "source": str(path.resolve()),
        "source_size": st.st_size,
        "source_mtime_ns": st.st_mtime_ns,
        "scene": ds.scene,
        "seeds": ds.seeds,
        "gridspec": raw.to_dict(),
        "transfer": TRANSFER,
        "n_steps": int(len(index)),
        "steps_sha256": hashlib.sha256(np.ascontiguousarray(index, dtype=np.int64).tobytes()).hexdigest(),
    }


def build_grid_set(path: str | os.PathLike, spec: GridSpec, index: np.ndarray, out_dir: str | os.PathLike,
                   *, progress: Callable[[int], None] | None = None) -> GridSet:
    """Compute the grids of rows ``index`` of ``path`` into ``out_dir`` and return them memory-mapped.

    Written into a temporary sibling directory and renamed, so a cache is
    either complete or absent.  Transfer errors (non-finite values, points
    outside the domain) raise GridDataError naming the step.
    """
    path, out_dir = Path(path), Path(out_dir)
    ds = open_dataset(path)
    try:
        check_scene(spec, ds.scene, path)
        if len(index) == 0:
            raise GridDataError(f"{path}: no steps with contact points to learn from")
        steps = ds.steps
        meta = _meta(path, spec, index, ds)
    finally:
        ds.close()
    tmp = out_dir.with_name(f".{out_dir.name}.{os.getpid()}.part")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        _write_grid_arrays(tmp, path, spec, steps, index, progress)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")
        shutil.rmtree(out_dir, ignore_errors=True)
        os.replace(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return load_grid_set(out_dir)


def _write_grid_arrays(out: Path, path: Path, spec: GridSpec, steps: np.ndarray, index: np.ndarray,
                       progress: Callable[[int], None] | None) -> None:
    """The .npy files of a GridSet (all but meta.json) for rows ``index`` of ``path``, into ``out``.

    The grids and the points' G2P stencils are written step by step into
    memory-mapped files, so a set larger than memory can be built; the
    per-point arrays are small and saved at the end.
    """
    n, (ny, nx) = len(index), spec.shape
    counts = steps["point_count"][index].astype(np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    mm = np.lib.format.open_memmap
    inputs = mm(out / "inputs.npy", "w+", np.float32, (n, ny, nx, len(spec.inputs)))
    targets = mm(out / "targets.npy", "w+", np.float32, (n, ny, nx, len(spec.targets)))
    stencil = None
    p_pos = np.empty((offsets[-1], 2), np.float32)
    p_tgt = np.empty((offsets[-1], len(spec.targets)), np.float32)
    p_bui = np.empty((offsets[-1], 2), np.float32)
    opts = {"outside": TRANSFER["outside"], "tolerance": TRANSFER["tolerance"]}
    for k, (i, step) in enumerate(iter_steps(path, steps, index)):
        try:
            inputs[k], contacts = step_to_grids(step, spec, return_plan=True, **opts)
            targets[k] = targets_to_grids(step, spec, **opts)
            p_tgt[offsets[k]:offsets[k + 1]] = channel_values(spec.targets, step)
        except ValueError as exc:
            row = steps[i]
            raise GridDataError(f"{path}: seed {row['seed']} step {row['step']}: {exc}") from None
        rows = slice(offsets[k], offsets[k + 1])
        nodes, weights = contacts.g2p_operator()
        if stencil is None:
            shape = (int(offsets[-1]), nodes.shape[1])
            stencil = (mm(out / "point_nodes.npy", "w+", np.int32, shape),
                       mm(out / "point_weights.npy", "w+", np.float32, shape))
        stencil[0][rows], stencil[1][rows] = nodes, weights
        p_pos[rows] = particle_positions("contacts", step)
        p_bui[rows] = step.contacts["builtin"]
        if progress is not None:
            progress(1)
    for a in (inputs, targets, *stencil):
        a.flush()
    del inputs, targets, stencil
    for name, arr in (("point_offsets", offsets), ("point_positions", p_pos), ("point_targets", p_tgt),
                      ("point_builtin", p_bui), ("point_new", ~p_bui.any(axis=1)),
                      ("steps", index.astype(np.int64))):
        np.save(out / f"{name}.npy", arr, allow_pickle=False)


def load_grid_set(out_dir: str | os.PathLike) -> GridSet:
    """A cached GridSet, big arrays memory-mapped (read-only)."""
    out_dir = Path(out_dir)
    meta = json.loads((out_dir / "meta.json").read_text())
    arrays = {name: np.load(out_dir / f"{name}.npy", mmap_mode="r" if name in _MAPPED else None,
                            allow_pickle=False) for name in _ARRAYS}
    return GridSet(meta=meta, **arrays)


def cached_grid_set(path: str | os.PathLike, spec: GridSpec, out_dir: str | os.PathLike, *,
                    max_steps: int | None = None, seed: int = 0,
                    progress_factory: Callable[[int, str], Any] | None = None) -> tuple[GridSet, bool]:
    """The GridSet of ``path`` under ``out_dir``: reused when made from the same
    file, grid and step selection, otherwise (re)built.  Returns (set, reused)."""
    path, out_dir = Path(path), Path(out_dir)
    ds = open_dataset(path)
    try:
        check_scene(spec, ds.scene, path)
        index = select_steps(ds.steps, max_steps, seed)
        if len(index) == 0:
            raise GridDataError(f"{path}: no steps with contact points to learn from")
        meta = _meta(path, spec, index, ds)
    finally:
        ds.close()
    if (out_dir / "meta.json").exists():
        try:
            cached = load_grid_set(out_dir)
        except (OSError, ValueError):
            cached = None
        if cached is not None and cached.meta == meta:
            return cached, True
    bar = progress_factory(len(index), f"grids {path.name}") if progress_factory else None
    try:
        return build_grid_set(path, spec, index, out_dir, progress=bar.update if bar else None), False
    finally:
        if bar is not None:
            bar.close()


def channel_stats(grids: np.ndarray, chunk: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel (mean, std) over all samples and nodes of (N, ny, nx, C), float64.

    Accumulated in chunks (the grids are memory-mapped) with float64 sums
    around a first-chunk shift, which keeps the variance accurate.
    """
    c = grids.shape[-1]
    shift = np.asarray(grids[:chunk], np.float64).reshape(-1, c).mean(axis=0)
    s1, s2, count = np.zeros(c), np.zeros(c), 0
    for start in range(0, len(grids), chunk):
        x = np.asarray(grids[start:start + chunk], np.float64).reshape(-1, c) - shift
        s1 += x.sum(axis=0)
        s2 += (x * x).sum(axis=0)
        count += len(x)
    mean = s1 / count
    var = np.maximum(s2 / count - mean * mean, 0.0)
    return mean + shift, np.sqrt(var)


def pooled_normalization(train: list[GridSet], spec: GridSpec) -> dict[str, tuple[float, float]]:
    """channel -> (mean, std) over the nodes of every training grid of every
    file, inputs and targets (files of other grid sizes count by their nodes).

    A channel that is constant in the training set gets std 1 (it carries no
    information; GridSpec requires std > 0).
    """
    norm = {}
    for names, key in ((spec.inputs, "inputs"), (spec.targets, "targets")):
        stats = []
        for gs in train:  # loop over files
            grids = getattr(gs, key)
            mean, std = channel_stats(grids)
            stats.append((float(np.prod(grids.shape[:3])), mean, std))
        total = sum(n for n, _, _ in stats)
        mean = sum(n * m for n, m, _ in stats) / total
        var = sum(n * (sd * sd + (m - mean) ** 2) for n, m, sd in stats) / total
        for n, m, v in zip(names, mean, var):
            if not np.isfinite(m) or not np.isfinite(v):
                raise GridDataError(f"channel {n!r}: non-finite values in the training grids")
            sd = float(np.sqrt(v))
            norm[n] = (float(m), sd if sd > 1e-12 else 1.0)
    return norm


# --------------------------------------------------------------------------- #
# Loss at the contact points
# --------------------------------------------------------------------------- #


def point_values(grids: np.ndarray, gs: GridSet, spec: GridSpec, start: int = 0) -> np.ndarray:
    """SPH G2P of raw grids (n, ny, nx, C) (steps ``start .. start + n`` of ``gs``) at
    their steps' contact points: (P_n, C) float32, rows as in ``gs.point_targets``."""
    out = np.empty((int(gs.point_offsets[start + len(grids)] - gs.point_offsets[start]), grids.shape[-1]),
                   np.float32)
    base = int(gs.point_offsets[start])
    for k in range(len(grids)):  # loop over steps; G2P needs all of a step's points at once
        rows = gs.points(start + k)
        out[rows.start - base:rows.stop - base] = g2p(grids[k], gs.point_positions[rows], spec, TRANSFER["g2p"],
                                                       outside=TRANSFER["outside"],
                                                       tolerance=TRANSFER["tolerance"])[0]
    return out


def point_errors(values: np.ndarray, truth: np.ndarray, names) -> dict[str, dict[str, float]]:
    """channel -> {"mse" (unit^2), "mae", "rmse" (unit)} of per-point values (P, C) against truth (P, C)."""
    err = np.asarray(values, np.float64) - np.asarray(truth, np.float64)
    mse = (err * err).mean(axis=0) if len(err) else np.full(err.shape[1], np.nan)
    mae = np.abs(err).mean(axis=0) if len(err) else np.full(err.shape[1], np.nan)
    return {n: {"mse": float(m), "mae": float(a), "rmse": float(np.sqrt(m))} for n, m, a in zip(names, mse, mae)}


def point_baselines(gs: GridSet, spec: GridSpec) -> dict[str, dict[str, dict[str, float]]]:
    """Contact-point errors of warm starts that need no model, for scale:

    * ``zero``: predict 0 at every point;
    * ``builtin``: Box2D's own warm start (last step's impulse), only when the
      targets are ``impulse_normal``/``impulse_tangent``;
    * ``grid_oracle``: the true target grid sent back with G2P: what a
      perfect grid prediction would still miss through the transfer.
    """
    names = spec.targets
    out = {"zero": point_errors(np.zeros_like(gs.point_targets), gs.point_targets, names)}
    if tuple(names) == ("impulse_normal", "impulse_tangent"):
        out["builtin"] = point_errors(gs.point_builtin, gs.point_targets, names)
    oracle = np.concatenate([point_values(np.asarray(gs.targets[s:s + 256]), gs, spec, s)
                             for s in range(0, len(gs), 256)])
    out["grid_oracle"] = point_errors(oracle, gs.point_targets, names)
    return out
