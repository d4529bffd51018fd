"""`deepcontact generate`: record simulations into an HDF5 training file.

    deepcontact generate --scene thesis --seeds 1-100 --out data/train.h5

One process per simulation (all cores by default). Each worker writes its
simulation to a temporary .npz (no pickle), the parent appends them to the
HDF5 file in seed order, so the file's contents do not depend on the number
of processes. Per step it records the bodies at collide time, the contact
points after the solve (with the builtin warm start and the final impulse)
and the solver's statistics.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from simclient import seeds as seed_ranges
from simclient.engine import BODY_DTYPE, CONTACT_DTYPE
from simclient.scene import SceneSpec, add_scene_arguments, build_world, spec_from_args, spec_from_dict, spec_to_dict
from training.dataset import STEP_DTYPE, Writer


def record_simulation(spec: SceneSpec, seed: int, record: bool = True) -> dict[str, np.ndarray]:
    """Run one simulation with Box2D's builtin warm start.

    Returns (when record) steps (S,) STEP_DTYPE with offsets into this
    simulation's bodies (S*B,) BODY_DTYPE, points (P,) CONTACT_DTYPE and
    trace (T,) float32 N s. With record=False it only runs the steps (the
    baseline of `deepcontact bench generate`).
    """
    engine = build_world(spec, seed)
    if not record:
        for _ in range(spec.steps):
            engine.step()
        return {}
    steps = np.zeros(spec.steps, dtype=STEP_DTYPE)
    bodies, points, traces = [], [], []
    n_bodies = n_points = n_trace = 0
    for k in range(spec.steps):
        engine.collide()
        b = engine.bodies()
        stats = engine.solve()
        p = engine.contacts()
        row = steps[k]
        row["seed"], row["step"] = seed, k
        row["body_offset"], row["body_count"] = n_bodies, len(b)
        row["point_offset"], row["point_count"] = n_points, len(p)
        row["trace_offset"] = n_trace
        row["velocity_iterations"] = stats.velocity_iterations
        row["velocity_iterations_sum"] = stats.velocity_iterations_sum
        row["position_iterations"] = stats.position_iterations
        row["islands"] = stats.islands
        row["solve_ms"] = stats.solve_ms
        bodies.append(b)
        points.append(p)
        traces.append(stats.residual_trace)
        n_bodies += len(b)
        n_points += len(p)
        n_trace += len(stats.residual_trace)
    return {
        "steps": steps,
        "bodies": np.concatenate(bodies) if bodies else np.zeros(0, BODY_DTYPE),
        "points": np.concatenate(points) if points else np.zeros(0, CONTACT_DTYPE),
        "trace": np.concatenate(traces).astype(np.float32) if traces else np.zeros(0, np.float32),
    }


def _worker(spec_dict: dict, seed: int, tmpdir: str) -> str:
    arrays = record_simulation(spec_from_dict(spec_dict), seed)
    path = Path(tmpdir) / f"seed-{seed}.npz"
    np.savez(path, **arrays)
    return str(path)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser)
    parser.add_argument("--seeds", required=True, help="seeds to simulate, e.g. 1-100 or 1-10,20 (training range 1-899)")
    parser.add_argument("--out", required=True, type=Path, help="HDF5 file to write (e.g. data/train.h5)")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="processes, one simulation each at a time (default: all cores)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.add_argument("--allow-bench-seeds", action="store_true",
                        help="allow benchmark (900-999), reserved (>= 10000) and unassigned seeds in this file")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    try:
        spec = spec_from_args(args)
        seeds = seed_ranges.parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"deepcontact generate: {exc}", file=sys.stderr)
        return 2
    bad = seed_ranges.outside_training(seeds)
    if bad and not args.allow_bench_seeds:
        kinds = sorted({seed_ranges.describe(s) for s in bad})
        print(f"deepcontact generate: seeds {_short(bad)} are {' and '.join(kinds)} seeds, not training seeds "
              f"(1-899); pass --allow-bench-seeds if this file is not for training", file=sys.stderr)
        return 2
    if args.out.exists() and not args.overwrite:
        print(f"deepcontact generate: {args.out} exists; pass --overwrite to replace it", file=sys.stderr)
        return 2
    if args.workers < 1:
        print("deepcontact generate: --workers must be >= 1", file=sys.stderr)
        return 2

    command = "deepcontact " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    t0 = time.perf_counter()
    points = steps = 0
    with tempfile.TemporaryDirectory(prefix="deepcontact-gen-") as tmpdir, \
            Writer(args.out, scene=spec_to_dict(spec), seeds=seeds, command=command) as writer, \
            _progress(len(seeds), args.quiet) as bar, \
            cf.ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = [pool.submit(_worker, spec_to_dict(spec), s, tmpdir) for s in seeds]
        # Append in seed order: the file does not depend on which worker finished first.
        for fut in futures:
            path = fut.result()
            with np.load(path, allow_pickle=False) as z:
                writer.append(z["steps"], z["bodies"], z["points"], z["trace"])
                steps += len(z["steps"])
                points += len(z["points"])
            os.unlink(path)
            bar.update(1)
    dt = time.perf_counter() - t0
    print(f"wrote {args.out}: {len(seeds)} simulations, {steps} steps, {points} contact points "
          f"in {dt:.1f} s ({args.workers} workers)")
    return 0


def _short(seeds: list[int]) -> str:
    return ", ".join(map(str, seeds[:5])) + (f" ... ({len(seeds)} seeds)" if len(seeds) > 5 else "")


class _progress:
    """A tqdm bar on a terminal (or always unless quiet); a no-op when quiet."""

    def __init__(self, total: int, quiet: bool):
        self.bar = None
        if not quiet:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="sim", desc="generate", file=sys.stderr)

    def __enter__(self):
        return self

    def update(self, n: int) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()
