"""`deepcontact generate`: record simulations into an HDF5 training file.

    deepcontact generate --scene thesis --seeds 1-100 --out data/train.h5
    deepcontact generate --world simclient.zoo:pyramid --seeds 1-100 --out data/zoo-pyramid-1-100.h5

One task per simulation, on worker processes (all cores by default) or on
Ray (`--ray [ADDRESS]`, deepcontact.dispatch). Each task returns its
simulation as arrays (pool workers hand them over as a temporary .npz, Ray
through its object store; no pickle files); the parent alone writes the
HDF5 file, appending in seed order, so the file's contents do not depend on
the number of processes or where they ran. Per step it records the bodies
at collide time, the contact points after the solve (with the builtin warm
start and the final impulse) and the solver's statistics.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from deepcontact import dispatch
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from simclient import seeds as seed_ranges
from simclient import worlds
from simclient.scene import SceneSpec
from training.dataset import COMPRESSIONS, STEP_DTYPE, Writer


def record_simulation(spec, seed: int, record: bool = True, oracle: bool = False,
                      extra_points=None) -> dict[str, np.ndarray]:
    """Run one simulation of a scene (SceneSpec) or a user's world (simclient.worlds.WorldSpec,
    e.g. a zoo class) with Box2D's builtin warm start.

    Returns (when record) physics (3,) (dt s, gravity m/s^2), steps (S,) STEP_DTYPE with offsets
    into this simulation's bodies (S*B,) BODY_DTYPE, points (P,) CONTACT_DTYPE and
    trace (T,) float32 N s; with oracle also oracle (P, 2) float32 N s, each
    step solved from zero to convergence before it is solved as usual (the
    world does not change; a point outside every awake island, which never
    happens with sleeping off, keeps its final impulse). A point of a sleeping
    body (a user's world may let bodies sleep) is not solved: Box2D keeps its
    impulse, so its warm start and final impulse are recorded as that impulse
    (Box2D's own warm start), not as NaN. With record=False it
    only runs the steps (the baseline of `deepcontact lab generate`). extra_points: None, or a
    function of the engine, called after each collide, whose (Q,) CONTACT_DTYPE records (their
    final impulse already set) are recorded after the step's own points (lab.joint_points: each
    rigid joint as two points the solver does not see).
    """
    engine = worlds.build(spec, seed)
    if not record:
        for _ in range(spec.steps):
            engine.step()
        return {}
    steps = np.zeros(spec.steps, dtype=STEP_DTYPE)
    bodies, points, traces, exact = [], [], [], []
    n_bodies = n_points = n_trace = 0
    for k in range(spec.steps):
        engine.collide()
        b = engine.bodies()
        extra = extra_points(engine) if extra_points is not None else None
        solved = engine.oracle() if oracle else None
        stats = engine.solve()
        p = engine.contacts()
        asleep = ~np.isfinite(p["impulse"]).all(axis=1)
        if asleep.any():
            p["impulse"][asleep] = p["warm_start"][asleep] = p["builtin"][asleep]
        if oracle:
            exact.append(np.where(np.isfinite(solved), solved, p["impulse"]).astype(np.float32))
            if extra is not None:
                exact.append(extra["impulse"].astype(np.float32))
        if extra is not None:
            p = np.concatenate([p, extra])
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
    out = {
        "steps": steps,
        "bodies": np.concatenate(bodies) if bodies else np.zeros(0, BODY_DTYPE),
        "points": np.concatenate(points) if points else np.zeros(0, CONTACT_DTYPE),
        "trace": np.concatenate(traces).astype(np.float32) if traces else np.zeros(0, np.float32),
    }
    if oracle:
        out["oracle"] = np.concatenate(exact) if exact else np.zeros((0, 2), np.float32)
    # A user's world may draw its time step and gravity from the seed: the file keeps each seed's.
    out["physics"] = np.array([engine.config.dt, *engine.world.gravity], np.float64)
    return out


def simulate_seed(spec_dict: dict, seed: int, oracle: bool = False) -> dict[str, np.ndarray]:
    """One task: record_simulation of (scene or world as worlds.spec_to_dict, seed)."""
    return record_simulation(worlds.spec_from_dict(spec_dict), seed, oracle=oracle)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    worlds.add_world_arguments(parser)
    parser.add_argument("--seeds", required=True, help="seeds to simulate, e.g. 1-100 or 1-10,20 (training range 1-899)")
    parser.add_argument("--out", required=True, type=Path, help="HDF5 file to write (e.g. data/train.h5)")
    dispatch.add_arguments(parser, workers_default="all cores")
    parser.add_argument("--oracle", action="store_true",
                        help="also record each step solved from zero to convergence (Copy's warm start), for oracle "
                             "targets (oracle_* channels); about twice the time")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.add_argument("--allow-bench-seeds", action="store_true",
                        help="allow benchmark (900-999), reserved (>= 10000) and unassigned seeds in this file")
    parser.add_argument("--compression", choices=tuple(COMPRESSIONS), default="gzip",
                        help="how the file is compressed (default gzip, the smallest). This one process writes "
                             "every simulation, so on many cores its compression is the ceiling: lzf writes about "
                             "twice as fast for about 16 %% more disk, none about 16 times as fast for 2.4 times "
                             "the disk (deepcontact lab generate; docs/scale.md)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    try:
        spec = worlds.spec_from_args(args)
        seeds = seed_ranges.parse_seeds(args.seeds)
        dispatch.check_arguments(args)
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

    command = "deepcontact " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    workers = args.workers if args.ray else (args.workers or os.cpu_count() or 1)
    tasks = [dispatch.Task(f"seed {s}", (worlds.spec_to_dict(spec), s, args.oracle)) for s in seeds]
    t0 = time.perf_counter()
    points = steps = 0
    try:
        with Writer(args.out, scene=worlds.spec_to_dict(spec), seeds=seeds, command=command, oracle=args.oracle,
                    compression=args.compression) as writer, \
                dispatch.Dispatcher(workers=workers, ray=args.ray) as dispatcher:
            # Results come in seed order: the file does not depend on which task finished first.
            for arrays in dispatcher.map(simulate_seed, tasks, progress=None if args.quiet else "generate"):
                writer.append(arrays["steps"], arrays["bodies"], arrays["points"], arrays["trace"], arrays.get("oracle"),
                              physics=arrays["physics"])
                steps += len(arrays["steps"])
                points += len(arrays["points"])
            where = dispatcher.description
    except dispatch.DispatchError as exc:
        print(f"deepcontact generate: {exc}; nothing written to {args.out}", file=sys.stderr)
        return 1
    dt = time.perf_counter() - t0
    print(f"wrote {args.out}: {len(seeds)} simulations, {steps} steps, {points} contact points "
          f"in {dt:.1f} s ({where})")
    return 0


def _short(seeds: list[int]) -> str:
    return ", ".join(map(str, seeds[:5])) + (f" ... ({len(seeds)} seeds)" if len(seeds) > 5 else "")
