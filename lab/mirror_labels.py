"""Where the default's classifier and its mirror image disagree about a label, and how far the
classifier's own answer lies from the thresholds there:

    python -m lab.mirror_labels --seeds 850-855

Issue 101 asked whether the mirror image could run only where it changes a label. It could be
skipped at a step only if the classifier's answer alone told which steps those are: every
point's answer far enough from the route's thresholds (pressing at `pressing` N s along the
normal, sliding at `share` of the friction limit) that the mean with the mirror image cannot
cross them. On Builtin's trajectory of each seed's thesis world this prints the steps and points
whose labels the mirror image changes, how far from a threshold the classifier alone answered
at those points (N s, quantiles), and the share of steps whose every point lies farther than
each margin. Reads models/contact-modes (the shipped classifier) and the default's face.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from bench.inprocess import InProcess
from bench.server import record_steps
from deepcontact.faces import contact_face
from deepcontact.modelcard import ModelCard
from server.mirror_image import MirroredGraphPredictor
from simclient.scene import SceneSpec
from simclient.seeds import parse_seeds

ROOT = Path(__file__).resolve().parents[1]
MARGINS = (0.05, 0.1, 0.2, 0.3)  # N s


def margins(answer: np.ndarray, mu: np.ndarray, pressing: float, share: float) -> np.ndarray:
    """(P,) N s: how far each point's answer ((P, 2) N s, normal and tangent) lies from the
    nearest threshold that reads it (its normal from `pressing`; where it presses, its tangent's
    size from share x mu x its normal)."""
    normal = np.abs(answer[:, 0] - pressing)
    tangent = np.abs(np.abs(answer[:, 1]) - share * mu * answer[:, 0])
    return np.where(answer[:, 0] > pressing, np.minimum(normal, tangent), normal)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.mirror_labels", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="850-855", help="thesis-world seeds (default %(default)s: choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per seed (default %(default)s)")
    args = parser.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(f"python -m lab.mirror_labels: {exc}", file=sys.stderr)
        return 2
    models = ROOT / "models"
    face = json.loads((models / "default.json").read_text())["face"]
    pressing, share = face["pressing"], face.get("share", 1.0)
    served = InProcess.load(models, "contact-modes", SceneSpec.thesis())
    plain, world = served.predictor, served.world
    card = ModelCard.load(models / "contact-modes.json")
    mirrored = MirroredGraphPredictor(dataclasses.replace(card, mirror=True), card.onnx_path(models / "contact-modes.json"))
    steps = points = changed_points = changed_steps = 0
    at_changed, step_margin = [], []
    for seed in tqdm(seeds, desc="seeds", unit="seed"):
        for bodies, contacts, mu in record_steps(seed, args.steps):
            if len(contacts) == 0:
                continue
            alone = plain.predict(bodies, contacts, world, 0, friction=mu).impulses
            mean = mirrored.predict(bodies, contacts, world, 0, friction=mu).impulses
            changed = contact_face(alone, mu, pressing, share) != contact_face(mean, mu, pressing, share)
            margin = margins(alone, mu, pressing, share)
            steps, points = steps + 1, points + len(contacts)
            changed_points += int(changed.sum())
            changed_steps += bool(changed.any())
            at_changed.append(margin[changed])
            step_margin.append(margin.min())
    if steps == 0:
        print(f"python -m lab.mirror_labels: no steps with contacts in {args.steps} steps of seeds {args.seeds}; "
              "give more --steps", file=sys.stderr)
        return 2
    at_changed, step_margin = np.concatenate(at_changed), np.array(step_margin)
    print(f"thesis seeds {args.seeds}: {steps} steps with contacts, {points} points")
    print(f"the mirror image changes a label at {changed_steps} steps ({100 * changed_steps / steps:.1f} %), "
          f"{changed_points} points ({100 * changed_points / points:.2f} %)")
    if len(at_changed):
        q = np.percentile(at_changed, [50, 90, 99, 100])
        print("there, the classifier alone answered from a threshold (N s): median {:.3f}, p90 {:.3f}, "
              "p99 {:.3f}, max {:.3f}".format(*q))
    for m in MARGINS:
        print(f"steps whose every point lies farther than {m} N s: {100 * (step_margin > m).mean():.1f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
