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
    from lab.face_card import add_arguments as face_card_arguments

    face_card_arguments(parser, "850-855")


def price(seed: int, steps: int, predictor) -> tuple[dict[str, np.ndarray], int, int]:
    """({"builtin", "fresh", "reused": (steps,) sweeps}, steps with contacts, steps whose labels were reused)."""
    from deepcontact.faces import route_compiled
    from lab.face_card import builtin_states

    face = predictor.settings
    out = {"builtin": [], "fresh": [], "reused": []}
    held: dict[int, np.ndarray] = {}  # point key -> the labels the stream holds, (2,) N s
    counted, reused = 0, 0

    def served(state, labels) -> np.ndarray:
        answer = route_compiled(state.bodies, state.points, labels, state.friction, state.world.physics,
                                face["pressing"], face["share"], face["label_friction"], face["rounds"], None, None,
                                face["relax"], face["rho"])
        if answer is None or (face["max_residual"] is not None and answer.residual > face["max_residual"]):
            return state.points["builtin"].astype(np.float64)
        return answer.impulses

    for _, state in builtin_states(seed, steps, predictor):
        out["builtin"].append(state.engine.trial(*state.builtin))
        keys = state.points["key"].tolist()
        counted += 1
        if keys and all(key in held for key in keys):
            kept, reused = np.array([held[key] for key in keys]), reused + 1
        else:
            kept = state.labels
        for name, chosen in (("fresh", state.labels), ("reused", kept)):
            out[name].append(state.trial(served(state, chosen)))
        held = dict(zip(keys, kept))
    return {name: np.array(v, float) for name, v in out.items()}, counted, reused


def run(args: argparse.Namespace) -> int:
    from lab.face_card import priced

    done = priced(args, "deepcontact lab label-reuse", price)
    if done is None:
        return 2
    predictor, runs = done
    counted, reused = sum(r[1] for r in runs), sum(r[2] for r in runs)
    ratio = {name: ratio_interval([r[0][name] for r in runs], [r[0]["builtin"] for r in runs])
             for name in ("fresh", "reused")}
    print(f"the thesis world, seeds {args.seeds}, {args.model}'s route on Box2D's states: {counted} steps with "
          f"contacts, the classifier skipped at {reused}")
    print(f"| labels | / builtin |\n|---|---|\n| the step's own | {ratio['fresh'].text()} |\n"
          f"| held across steps | {ratio['reused'].text()} |")
    print(f"held / own: {ratio_interval([r[0]['reused'] for r in runs], [r[0]['fresh'] for r in runs]).text()}")
    return 0
