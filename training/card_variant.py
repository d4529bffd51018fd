"""Another card for an exported model: the same ONNX served another way.

    python -m training.card_variant models/residual.json --combine new-points
        # models/residual-new-points.json: the model only where a contact point is new
    python -m training.card_variant models/residual.json --correction-scale 0.5
        # models/residual-x0.5.json: builtin + half the model's correction
    python -m training.card_variant models/residual.json --correction-threshold 0.2
        # models/residual-t0.2.json: builtin + the corrections larger than 0.2 N s (normal)
    python -m training.card_variant models/graph-mse-1-799.json --passes 2
        # models/graph-mse-1-799-p2.json: the network run again from its own warm start

Same ONNX file and GridSpec; another name and `combine`, `correction_scale`, `correction_threshold` or `passes`
(deepcontact.modelcard). The card is written beside the original (temporary
name, then rename).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from deepcontact.modelcard import COMBINE, ModelCard, ModelCardError


def card_variant(path: Path, *, combine: str | None = None, correction_scale: float | None = None,
                 correction_threshold: float | None = None, passes: int | None = None,
                 name: str | None = None) -> Path:
    """Write the variant beside the card at path; returns its path. Default name:
    NAME-new-points (or NAME-COMBINE), NAME-xSCALE and/or NAME-tTHRESHOLD."""
    card = ModelCard.load(path)
    changes = {}
    suffix = ""
    if combine is not None:
        changes["combine"] = combine
        suffix += f"-{combine}"
    if correction_scale is not None:
        if not correction_scale > 0:
            raise ValueError(f"--correction-scale must be > 0, got {correction_scale}")
        changes["correction_scale"] = correction_scale
        suffix += f"-x{correction_scale:g}"
    if correction_threshold is not None:
        if not correction_threshold >= 0:
            raise ValueError(f"--correction-threshold must be >= 0 N s, got {correction_threshold}")
        changes["correction_threshold"] = correction_threshold
        suffix += f"-t{correction_threshold:g}"
    if passes is not None:
        changes["passes"] = passes
        suffix += f"-p{passes}"
    if not changes:
        raise ValueError("nothing to change: give --combine, --correction-scale, --correction-threshold "
                         "and/or --passes")
    name = name or card.name + suffix
    out = path.with_name(f"{name}.json")
    ModelCard.from_dict(dataclasses.replace(card, name=name, **changes).to_dict()).save(out)  # checked as loaded
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.card_variant",
                                     description="another card for an exported model (same ONNX)")
    parser.add_argument("card", type=Path, help="the model's card, e.g. models/residual.json")
    parser.add_argument("--combine", choices=COMBINE, help="how the output becomes the warm start")
    parser.add_argument("--correction-scale", type=float, help="residual models: scale of the correction")
    parser.add_argument("--correction-threshold", type=float,
                        help="residual models: drop corrections whose normal part is at most this, N s")
    parser.add_argument("--passes", type=int,
                        help="graph residual models: run the network this many times, each pass reading its "
                             "inputs at the last pass's warm start in place of Box2D's")
    parser.add_argument("--name", help="the variant's name (default: derived from the changes)")
    args = parser.parse_args(argv)
    try:
        out = card_variant(args.card, combine=args.combine, correction_scale=args.correction_scale,
                           correction_threshold=args.correction_threshold, passes=args.passes,
                           name=args.name)
    except (ModelCardError, ValueError) as exc:
        print(f"card_variant: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
