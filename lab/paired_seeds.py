"""Two sets of one-seed `bench iterations` runs, paired by seed: one warm start's ratio to another's.

    for s in $(seq 901 920); do
        deepcontact bench iterations --world examples/pyramid.py:build --seeds $s --no-guard \
            --warm-starts server:default --out runs/after/$s --quiet        # a fresh server each seed
    done                                                                   # (and the same at another commit)
    python -m lab.paired_seeds runs/after runs/before --warm-start server:default
    python -m lab.paired_seeds runs/c50 runs/shipped --warm-start server:default-c50 --against server:default

`bench iterations` starts one server for all its seeds, so the server's estimate of the route's
cost by step size, learned on the first seeds, serves the later ones: what a user's first
simulation against a fresh server meets is seen only with one seed a run. Each run's
summary.json holds its seed's mean iterations a step with contacts; this pairs the runs of the
two folders (each holding one folder a run) by seed and prints the ratio of the sums of those
means, A over B, with a 95 % bootstrap interval over the seeds both hold.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

RESAMPLES = 4000


def seed_means(folder: Path, warm_start: str) -> dict[int, float]:
    """{seed: mean iterations a step with contacts} of `warm_start` over the runs under folder
    (each a `bench iterations --out` folder with its summary.json)."""
    means = {}
    for summary in sorted(folder.glob("*/summary.json")):
        run = json.loads(summary.read_text())
        for seed, mean in zip(run["seeds"], run["per_seed_mean_iterations"].get(warm_start, [])):
            means[int(seed)] = float(mean)
    return means


def paired_ratio(a: dict[int, float], b: dict[int, float], seed: int = 0) -> tuple[float, float, float, int]:
    """(sum of a's means / sum of b's, the 95 % bootstrap interval's low and high, seeds) over the
    seeds both hold."""
    seeds = sorted(set(a) & set(b))
    if len(seeds) < 2:
        raise ValueError(f"{len(seeds)} seeds in both: a paired interval needs two or more")
    x, y = np.array([a[s] for s in seeds]), np.array([b[s] for s in seeds])
    idx = np.random.default_rng(seed).integers(0, len(seeds), (RESAMPLES, len(seeds)))
    low, high = np.quantile(x[idx].sum(axis=1) / y[idx].sum(axis=1), [0.025, 0.975])
    return float(x.sum() / y.sum()), float(low), float(high), len(seeds)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.paired_seeds", description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="a folder of one-seed `bench iterations --out` folders")
    parser.add_argument("b", type=Path, help="the folder to pair it with, by seed")
    parser.add_argument("--warm-start", default="server:default", help="the warm start read (default server:default)")
    parser.add_argument("--against", default=None, metavar="WARM_START",
                        help="the warm start read in b's runs (default: --warm-start)")
    args = parser.parse_args(argv)
    try:
        a, b = seed_means(args.a, args.warm_start), seed_means(args.b, args.against or args.warm_start)
        value, low, high, n = paired_ratio(a, b)
    except (ValueError, OSError, KeyError, json.JSONDecodeError) as exc:
        print(f"python -m lab.paired_seeds: {exc}", file=sys.stderr)
        return 2
    against = args.against or args.warm_start
    print(f"{args.warm_start} in {args.a} / {against} in {args.b}, over {n} seeds: {value:.3f} [{low:.3f}, {high:.3f}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
