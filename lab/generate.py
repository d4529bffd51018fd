"""`deepcontact lab generate`: what recording costs over simulating, and what writing costs.

Runs the same simulations twice in this one process, interleaved seed by
seed: once plain (`Engine.step`), once recorded (collide, export bodies,
solve, export contact points). Reports the median per-simulation times and
their ratio. Each recorded simulation is then appended to one HDF5 file per
compression (training.dataset.COMPRESSIONS), timed apart: `generate` writes
from one process, so 1 / (write time) is the most simulations per second it
can take in, however many workers simulate (docs/scale.md).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import tempfile
import time
from pathlib import Path

from deepcontact.io import write_json_atomic
from simclient import seeds as seed_ranges
from simclient.scene import SceneSpec, spec_to_dict
from training.dataset import COMPRESSIONS, Writer
from training.generate import record_simulation


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="900-909", help="thesis-world seeds (default 900-909)")
    parser.add_argument("--compressions", default=",".join(COMPRESSIONS),
                        help=f"time the write with each of these (default {','.join(COMPRESSIONS)})")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def run(args: argparse.Namespace) -> int:
    spec = SceneSpec.thesis()
    seeds = seed_ranges.parse_seeds(args.seeds)
    compressions = [c.strip() for c in args.compressions.split(",") if c.strip()]
    unknown = sorted(set(compressions) - set(COMPRESSIONS))
    if unknown or not compressions:
        print(f"deepcontact lab generate: unknown compression {', '.join(unknown) or '(none given)'} "
              f"(one of {', '.join(COMPRESSIONS)})", file=sys.stderr)
        return 2
    plain, recorded = [], []
    written = {c: [] for c in compressions}
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        writers = {c: stack.enter_context(Writer(Path(tmp) / f"bench-{c}.h5", scene=spec_to_dict(spec), seeds=seeds,
                                                 command="bench", compression=c)) for c in compressions}
        for seed in seeds:
            t0 = time.perf_counter()
            record_simulation(spec, seed, record=False)
            t1 = time.perf_counter()
            arrays = record_simulation(spec, seed)
            t2 = time.perf_counter()
            for c, writer in writers.items():
                t3 = time.perf_counter()
                writer.append(arrays["steps"], arrays["bodies"], arrays["points"], arrays["trace"])
                written[c].append(time.perf_counter() - t3)
            plain.append(t1 - t0)
            # recorded to HDF5 as generate does by default: the first compression's write counts
            recorded.append(t2 - t1 + written[compressions[0]][-1])
        stack.close()  # the files land under their names: their sizes
        sizes = {c: (Path(tmp) / f"bench-{c}.h5").stat().st_size for c in compressions}
    result = {
        "seeds": seeds,
        "plain_s_median": statistics.median(plain),
        "recorded_s_median": statistics.median(recorded),
        "ratio_of_medians": statistics.median(recorded) / statistics.median(plain),
        "median_of_ratios": statistics.median(r / p for r, p in zip(recorded, plain)),
        "write": {c: {"ms_median": 1e3 * statistics.median(written[c]), "mb_per_simulation": sizes[c] / len(seeds) / 1e6,
                      "max_simulations_per_s": 1 / statistics.median(written[c])} for c in compressions},
    }
    print(f"thesis world, {len(seeds)} simulations of {spec.steps} steps: plain {result['plain_s_median']:.3f} s, "
          f"recorded to HDF5 ({compressions[0]}) {result['recorded_s_median']:.3f} s per simulation (medians); "
          f"ratio of medians {result['ratio_of_medians']:.3f}, median ratio {result['median_of_ratios']:.3f}")
    print("writing one simulation to HDF5 (generate's one writing process; median):")
    for c, w in result["write"].items():
        print(f"  {c:5s} {w['ms_median']:6.1f} ms, {w['mb_per_simulation']:.2f} MB: "
              f"at most {w['max_simulations_per_s']:.0f} simulations/s into one file")
    if args.json:
        write_json_atomic(args.json, result)
    return 0
