"""`deepcontact bench generate`: what recording costs over simulating.

Runs the same simulations twice in this one process, interleaved seed by
seed: once plain (`Engine.step`), once recorded (collide, export bodies,
solve, export contact points) and appended to an HDF5 file. Reports the
median per-simulation times and their ratio.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from deepcontact.io import write_json_atomic
from simclient import seeds as seed_ranges
from simclient.scene import SceneSpec, spec_to_dict
from training.dataset import Writer
from training.generate import record_simulation


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="900-909", help="thesis-world seeds (default 900-909)")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def run(args: argparse.Namespace) -> int:
    spec = SceneSpec.thesis()
    seeds = seed_ranges.parse_seeds(args.seeds)
    plain, recorded = [], []
    with tempfile.TemporaryDirectory() as tmp, \
            Writer(Path(tmp) / "bench.h5", scene=spec_to_dict(spec), seeds=seeds, command="bench") as writer:
        for seed in seeds:
            t0 = time.perf_counter()
            record_simulation(spec, seed, record=False)
            t1 = time.perf_counter()
            arrays = record_simulation(spec, seed)
            writer.append(arrays["steps"], arrays["bodies"], arrays["points"], arrays["trace"])
            t2 = time.perf_counter()
            plain.append(t1 - t0)
            recorded.append(t2 - t1)
    result = {
        "seeds": seeds,
        "plain_s_median": statistics.median(plain),
        "recorded_s_median": statistics.median(recorded),
        "ratio_of_medians": statistics.median(recorded) / statistics.median(plain),
        "median_of_ratios": statistics.median(r / p for r, p in zip(recorded, plain)),
    }
    print(f"thesis world, {len(seeds)} simulations of {spec.steps} steps: plain {result['plain_s_median']:.3f} s, "
          f"recorded to HDF5 {result['recorded_s_median']:.3f} s per simulation (medians); "
          f"ratio of medians {result['ratio_of_medians']:.3f}, median ratio {result['median_of_ratios']:.3f}")
    if args.json:
        write_json_atomic(args.json, result)
    return 0
