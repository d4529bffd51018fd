"""A second card for an exported model: its output used only where a contact point is new.

    python -m training.new_points_card models/residual.json   # writes models/residual-new-points.json

Same ONNX file, same GridSpec; name NAME-new-points, combine "new-points"
(deepcontact.modelcard): the model's warm start where Box2D has none (a point
new this step), Box2D's builtin where the point persists.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from deepcontact.modelcard import ModelCard, ModelCardError


def new_points_card(path: Path) -> Path:
    """Write NAME-new-points.json beside the card at path; returns its path."""
    card = ModelCard.load(path)
    out = path.with_name(f"{card.name}-new-points.json")
    dataclasses.replace(card, name=f"{card.name}-new-points", combine="new-points").save(out)
    return out


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or args[0] in ("-h", "--help"):
        print(__doc__.strip().splitlines()[2].strip(), file=sys.stderr)
        return 0 if args and args[0] in ("-h", "--help") else 2
    try:
        print(f"wrote {new_points_card(Path(args[0]))}")
    except ModelCardError as exc:
        print(f"new_points_card: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
