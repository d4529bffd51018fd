"""`deepcontact lab graph-size`: a contact-graph model's inference against the step's size.

    deepcontact lab graph-size --model default,graph-projected-max-1-799-long-e2 \
        --sizes 140x100,400x400,400x1600 --json bench/results/graph-size/sizes.json

A contact-graph network exported since 2026-11-26 sums each round's messages per body with
scatter-adds, so its cost should grow with the points; one exported before, with dense one-hot
incidence matrices (points x bodies; docs/models.md, "Contact-graph models"), with points times
bodies, once per round of message passing. This times the ONNX session
alone, as the server runs it (`GraphPredictor.run_session`, one thread), on synthetic steps of
P contact points between B dynamic bodies: random normalized inputs and random ends, since the
arithmetic does not depend on the values. Printed: per model and size, the median over
--repeats runs, in ms. A card with `passes: K` (deepcontact.modelcard) is timed as K runs of
its session, as the server runs them; the channels it computes between passes are not timed.
Set OMP_NUM_THREADS=1 for numbers comparable to the other benchmarks'.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument, add_seed_argument
from deepcontact.io import write_json_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", default="default,graph-projected-max-1-799-long-e2",
                        help="comma-separated contact-graph models (card names; default %(default)s)")
    add_models_argument(parser)
    parser.add_argument("--sizes", default="140x100,400x400,400x1600",
                        help="comma-separated POINTSxBODIES (default %(default)s: the thesis world's median "
                             "step, and 400 points among 400 and 1,600 bodies)")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per model and size (default %(default)s)")
    add_seed_argument(parser, "seed of the synthetic inputs (default 0)", default=0)
    parser.add_argument("--json", metavar="FILE", help="write the rows here as JSON")


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """'140x100,400x1600' -> [(140, 100), (400, 1600)] (points, bodies), each at least 1."""
    sizes = []
    for item in text.split(","):
        try:
            points, bodies = (int(v) for v in item.strip().lower().split("x"))
        except ValueError:
            raise ValueError(f"size {item.strip()!r} is not POINTSxBODIES, e.g. 400x1600") from None
        if points < 1 or bodies < 1:
            raise ValueError(f"size {item.strip()!r}: points and bodies must be at least 1")
        sizes.append((points, bodies))
    return sizes


def synthetic_step(points: int, bodies: int, channels: int, rng: np.random.Generator, physics: bool = False):
    """Inputs of one step: points (P, channels) float32 normalized, ends (P, 2) int32 rows of
    dynamic, dynamic (B, 1) float32 (all bodies dynamic); with `physics`, for a network with
    probes, also geometry (P, 8) (unit normals and tangents, lever arms up to 0.5 m), masses
    (P, 2) kg and inverse (B, 2)."""
    step = (rng.standard_normal((points, channels)).astype(np.float32),
            rng.integers(0, bodies, (points, 2)).astype(np.int32),
            np.ones((bodies, 1), np.float32))
    if not physics:
        return step
    angle = rng.uniform(0.0, 2 * np.pi, points)
    n = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    geometry = np.concatenate([n, n[:, ::-1] * [1, -1], rng.uniform(-0.5, 0.5, (points, 4))], axis=1)
    return step + (geometry.astype(np.float32), rng.uniform(0.1, 1.0, (points, 2)).astype(np.float32),
                   rng.uniform(0.5, 2.0, (bodies, 2)).astype(np.float32))


def run(args: argparse.Namespace) -> int:
    from deepcontact.modelcard import ModelCard
    from server.predictors import GraphPredictor, load_model

    try:
        sizes = parse_sizes(args.sizes)
    except ValueError as e:
        raise SystemExit(f"lab graph-size: {e}") from None
    if args.repeats < 1:
        raise SystemExit("lab graph-size: --repeats must be at least 1")
    folder = Path(args.models)
    rows = []
    for name in (n.strip() for n in args.model.split(",") if n.strip()):
        path = folder / f"{name}.json"
        if not path.is_file():
            raise SystemExit(f"lab graph-size: no card {path}")
        target = ModelCard.alias_target(path)
        predictor = load_model(folder / f"{target}.json" if target else path)
        if not isinstance(predictor, GraphPredictor):
            raise SystemExit(f"lab graph-size: {name} is a {predictor.kind} model, not a contact-graph one")
        rounds = predictor.card.architecture.get("config", {}).get("rounds")
        passes = predictor.card.passes
        rng = np.random.default_rng(args.seed)
        for points, bodies in sizes:
            feed = synthetic_step(points, bodies, len(predictor.inputs), rng, predictor.physics)
            predictor.run_session(*feed)  # the first run at a shape plans its memory
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                for _ in range(passes):
                    predictor.run_session(*feed)
                times.append(time.perf_counter() - t0)
            rows.append({"model": name, "served": predictor.name, "rounds": rounds, "passes": passes,
                         "points": points, "bodies": bodies, "median_ms": 1e3 * float(np.median(times))})
    print("| model | rounds | passes | points | bodies | inference median ms |\n|---|---|---|---|---|---|")
    for r in rows:
        shown = r["model"] if r["model"] == r["served"] else f"{r['model']} ({r['served']})"
        print(f"| {shown} | {'–' if r['rounds'] is None else r['rounds']} | {r['passes']} | {r['points']} | "
              f"{r['bodies']} | {r['median_ms']:.2f} |")
    if args.json:
        write_json_atomic(args.json, {"repeats": args.repeats, "seed": args.seed, "rows": rows})
        print(f"wrote {args.json}")
    return 0
