"""What the lab's benches of the face route share: their command line (`--seeds`, `--steps`,
`--models`, `--model`), checked, with the one-line error a bad one gets, and the pricing of a
face card's route over Box2D's own states of the thesis world's seeds (lab.label_reuse,
lab.admission_carry)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np


def add_arguments(parser: argparse.ArgumentParser, seeds: str) -> None:
    """The shared flags; seeds: the default seed range (choosing seeds)."""
    parser.add_argument("--seeds", default=seeds, help=f"thesis-world seeds (default {seeds}, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--models", default="models", help="model folder (default models/)")
    parser.add_argument("--model", default="default", help="a face card (default: default)")


def priced(args: argparse.Namespace, command: str, price):
    """(the face card's FaceRoutePredictor, [price(seed, args.steps, predictor) for each seed]),
    with a progress bar; or None after printing why not to stderr as `command: ...`."""
    from server.predictors import load_model
    from simclient import seeds as seed_ranges

    try:
        seeds = seed_ranges.parse_seeds(args.seeds)
        if args.steps < 1:
            raise ValueError(f"--steps must be >= 1, got {args.steps}")
    except ValueError as exc:
        print(f"{command}: {exc}", file=sys.stderr)
        return None
    card = Path(args.models) / f"{args.model}.json"
    if not card.exists():
        print(f"{command}: no card {card}", file=sys.stderr)
        return None
    predictor = load_model(card)
    if getattr(predictor, "settings", None) is None:
        print(f"{command}: {args.model} is not a face card", file=sys.stderr)
        return None
    from tqdm import tqdm

    return predictor, [price(s, args.steps, predictor) for s in tqdm(seeds, unit="sim", file=sys.stderr)]


class BuiltinState(NamedTuple):
    """One step of Box2D's own trajectory of the thesis world, collided, not yet solved: its
    engine (trial-solve starts on it), records, each point's friction (P,), Box2D's start
    ((P,) normal, (P,) tangent, N s), and the classifier's labels (P, 2) N s."""

    engine: object
    world: object
    bodies: np.ndarray
    points: np.ndarray
    friction: np.ndarray
    builtin: tuple
    labels: np.ndarray

    def trial(self, impulses: np.ndarray) -> int:
        """The sweeps the step needs from impulses (P, 2) N s."""
        z = np.asarray(impulses, np.float32)
        return self.engine.trial(np.ascontiguousarray(z[:, 0]), np.ascontiguousarray(z[:, 1]))


def builtin_states(seed: int, steps: int, predictor):
    """The thesis world of the seed stepped from Box2D's own warm start: a BuiltinState for each
    step with contacts, the face card's classifier (predictor.classifier) asked for its labels; the
    step is solved from Box2D's start after the caller is done with it."""
    from bench.inprocess import declared_world
    from simclient.provider import point_friction
    from simclient.scene import SceneSpec, build_world

    spec = SceneSpec.thesis()
    world = declared_world(spec, None)
    engine = build_world(spec, seed)
    mu = engine.body_friction()
    previous = None
    for k in range(steps):
        if engine.collide() == 0:
            engine.solve()
            continue
        bodies, points = engine.bodies(), engine.contacts()
        friction = point_friction(mu, points).astype(np.float32)
        builtin = engine.builtin_start()
        labels = predictor.classifier.predict(bodies, points, world, k, previous, friction=friction).impulses
        yield k, BuiltinState(engine, world, bodies, points, friction, builtin, labels)
        engine.set_warm_start(*builtin)
        engine.solve()
        previous = points
