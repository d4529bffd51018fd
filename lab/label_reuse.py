"""`deepcontact lab label-reuse`: can a stream keep the classifier's labels across steps?

    deepcontact lab label-reuse --seeds 850-855

The default's classifier is a third of its server's step (about 0.28 ms of 0.9). On a settled
pile the contact points persist from step to step; if their labels did too, a server could keep
each stream's last labels and run the classifier only on steps with a new point. This prices it
on Box2D's own trajectory of the thesis world (the same states for both answers): at every step
with contacts, the route (deepcontact.faces.route_compiled, the default card's settings; Box2D's
start where its solve misses max_residual or the compiled dual declines) on the classifier's
labels of the step, and on the labels the stream would hold (the last labels served, by point
key, where every point of the step persists; the step's own labels where one is new, and those
are kept). Prints each answer's sweeps over Box2D's, the reused over the fresh, and how many
steps skipped the classifier.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bench.stats import ratio_interval


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="850-855", help="thesis-world seeds (default 850-855, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--models", default="models", help="model folder (default models/)")
    parser.add_argument("--model", default="default", help="a face card (default: default)")


def price(seed: int, steps: int, predictor) -> tuple[dict[str, np.ndarray], int, int]:
    """({"builtin", "fresh", "reused": (steps,) sweeps}, steps with contacts, steps whose labels were reused)."""
    from bench.inprocess import declared_world
    from deepcontact.faces import route_compiled
    from simclient.provider import point_friction
    from simclient.scene import SceneSpec, build_world

    spec = SceneSpec.thesis()
    world, face = declared_world(spec, None), predictor.settings
    engine = build_world(spec, seed)
    mu = engine.body_friction()
    out = {"builtin": [], "fresh": [], "reused": []}
    held: dict[int, np.ndarray] = {}  # point key -> the labels the stream holds, (2,) N s
    previous, counted, reused = None, 0, 0

    def served(bodies, points, labels, friction) -> np.ndarray:
        answer = route_compiled(bodies, points, labels, friction, world.physics, face["pressing"], face["share"],
                                face["label_friction"], face["rounds"], None, None, face["relax"],
                                face["rho"])
        if answer is None or (face["max_residual"] is not None and answer.residual > face["max_residual"]):
            return points["builtin"].astype(np.float64)
        return answer.impulses

    for k in range(steps):
        if engine.collide() == 0:
            engine.solve()
            continue
        bodies, points = engine.bodies(), engine.contacts()
        friction = point_friction(mu, points).astype(np.float32)
        builtin = engine.builtin_start()
        out["builtin"].append(engine.trial(*builtin))
        labels = predictor.classifier.predict(bodies, points, world, k, previous, friction=friction).impulses
        keys = points["key"].tolist()
        counted += 1
        if keys and all(key in held for key in keys):
            kept, reused = np.array([held[key] for key in keys]), reused + 1
        else:
            kept = labels
        for name, chosen in (("fresh", labels), ("reused", kept)):
            z = np.asarray(served(bodies, points, chosen, friction), np.float32)
            out[name].append(engine.trial(np.ascontiguousarray(z[:, 0]), np.ascontiguousarray(z[:, 1])))
        held = dict(zip(keys, kept))
        engine.set_warm_start(*builtin)
        engine.solve()
        previous = points
    return {name: np.array(v, float) for name, v in out.items()}, counted, reused


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from server.predictors import load_model
    from simclient import seeds as seed_ranges

    try:
        seeds = seed_ranges.parse_seeds(args.seeds)
        if args.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {args.steps}")
    except ValueError as exc:
        print(f"deepcontact lab label-reuse: {exc}", file=sys.stderr)
        return 2
    card = Path(args.models) / f"{args.model}.json"
    if not card.exists():
        print(f"deepcontact lab label-reuse: no card {card}", file=sys.stderr)
        return 2
    predictor = load_model(card)
    if getattr(predictor, "settings", None) is None:
        print(f"deepcontact lab label-reuse: {args.model} is not a face card", file=sys.stderr)
        return 2
    from tqdm import tqdm

    runs = [price(s, args.steps, predictor) for s in tqdm(seeds, unit="sim", file=sys.stderr)]
    counted, reused = sum(r[1] for r in runs), sum(r[2] for r in runs)
    ratio = {name: ratio_interval([r[0][name] for r in runs], [r[0]["builtin"] for r in runs])
             for name in ("fresh", "reused")}
    print(f"the thesis world, seeds {args.seeds}, {args.model}'s route on Box2D's states: {counted} steps with "
          f"contacts, the classifier skipped at {reused}")
    print(f"| labels | / builtin |\n|---|---|\n| the step's own | {ratio['fresh'].text()} |\n"
          f"| held across steps | {ratio['reused'].text()} |")
    print(f"held / own: {ratio_interval([r[0]['reused'] for r in runs], [r[0]['fresh'] for r in runs]).text()}")
    return 0
