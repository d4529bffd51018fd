"""Ship a trained model: its card and ONNX file copied into the served folder under a name
that says what it is, with a one-line description.

    python -m training.ship lab/models/graph-face-fr-r12-e15-mirror.json --as contact-modes \\
        --description "labels each contact point open, sticking or sliding" --into models
        # models/contact-modes.onnx and models/contact-modes.json

The research store (lab/models/) keeps every model under the name of its recipe; `models/`
holds only what is served. The shipped card is the research card renamed, its recipe kept
(`commands`) and the research name recorded (`training.shipped_from`), so a shipped model's
provenance is one `grep` away. Both files are written to a temporary name and renamed.
"""

from __future__ import annotations

import argparse
import dataclasses
import shutil
import sys
from pathlib import Path

from deepcontact.modelcard import ModelCard, ModelCardError


def ship(card_path: Path, name: str, description: str, into: Path) -> Path:
    """Copy the model of the (full, not alias) card at card_path into `into` as NAME.onnx and
    NAME.json; returns the new card's path. ModelCardError for an alias or a missing file."""
    card_path = Path(card_path)
    if ModelCard.alias_target(card_path):
        raise ModelCardError(f"{card_path} is an alias card: ship the card it names")
    card = ModelCard.load(card_path)
    onnx = card.onnx_path(card_path)
    if not onnx.is_file():
        raise ModelCardError(f"{card_path}: names {card.onnx_file}, which is not in {card_path.parent}")
    if "\n" in description or not description.strip():
        raise ValueError("--description: one line of text saying what the model is")
    into.mkdir(parents=True, exist_ok=True)
    target = into / f"{name}.onnx"
    tmp = into / f".{name}.onnx.part"
    shutil.copyfile(onnx, tmp)
    tmp.replace(target)
    shipped = dataclasses.replace(card, name=name, onnx_file=target.name, description=description.strip(),
                                  training={**card.training, "shipped_from": card.name})
    return shipped.save(into / f"{name}.json")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("card", type=Path, help="the trained model's card (in the research store)")
    parser.add_argument("--as", dest="name", required=True, help="the shipped name, e.g. contact-modes")
    parser.add_argument("--description", required=True, help="what the model is, in one line")
    parser.add_argument("--into", type=Path, default=Path("models"), help="the served folder (default models/)")
    args = parser.parse_args(argv)
    try:
        path = ship(args.card, args.name, args.description, args.into)
    except (ModelCardError, ValueError, OSError) as exc:
        print(f"training.ship: {exc}", file=sys.stderr)
        return 2
    print(f"shipped {args.card} as {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
