"""A model folder with the zoo's variants beside the shipped models, for pricing them on the same
states (docs/research/2026-12-06-a-zoo-of-worlds.md):

    python -m lab.zoo_variants runs/zoo-variants
    deepcontact lab iterations --world simclient.zoo:stack --seeds 850-854 --no-guard \
        --models runs/zoo-variants --warm-starts builtin,price:server:default+server:zoo+server:zoo-first

Beside models/ (whose `default` and `zoo` are the shipped ones) it writes, each a card over a
network of the research store (lab/models):

    default-bf      the default with Box2D's start in place of its fallback (no `fallback`)
    default-graph   the default falling back to contact-graph directly, as until 2026-12-06
    zoo-first       the zoo route on the first run of the zoo's recipe (zoo-first-modes)
    zoo-bf          the zoo route with Box2D's start in place of its fallback
    zoo-always      the zoo route on every step: no max_residual, max_points 5,000
    default-first   the default falling back to zoo-first

Written to a temporary folder and renamed; an existing folder is replaced.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STORE = ROOT / "lab" / "models"
FIRST = "graph-labels-scaled-zoo-first-r12-e4"


def _card(folder: Path, name: str, **fields) -> None:
    (folder / f"{name}.json").write_text(json.dumps({"name": name, **fields}, indent=1) + "\n")


def build(out: Path) -> None:
    """Write the folder the module docstring describes at `out`."""
    tmp = out.with_name(out.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(ROOT / "models", tmp)
    face = json.loads((tmp / "default.json").read_text())["face"]
    zoo_face = json.loads((tmp / "zoo.json").read_text())["face"]
    card = json.loads((STORE / f"{FIRST}.json").read_text())
    card.update(name="zoo-first-modes", onnx_file="zoo-first-modes.onnx", measured=None)
    shutil.copy(STORE / f"{FIRST}.onnx", tmp / "zoo-first-modes.onnx")
    (tmp / "zoo-first-modes.json").write_text(json.dumps(card, indent=1) + "\n")
    no_fallback = {k: v for k, v in face.items() if k != "fallback"}
    _card(tmp, "default-bf", alias_of="contact-modes", face=no_fallback)
    _card(tmp, "default-graph", alias_of="contact-modes", face={**face, "fallback": "contact-graph"})
    _card(tmp, "zoo-first", alias_of="zoo-first-modes", face=zoo_face)
    _card(tmp, "zoo-bf", alias_of="contact-modes-zoo", face={k: v for k, v in zoo_face.items() if k != "fallback"})
    _card(tmp, "zoo-always", alias_of="contact-modes-zoo",
          face={**{k: v for k, v in zoo_face.items() if k != "fallback"}, "max_points": 5000, "max_residual": None})
    _card(tmp, "default-first", alias_of="contact-modes", face={**face, "fallback": "zoo-first"})
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.zoo_variants", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="the folder to write (replaced if it exists)")
    args = parser.parse_args(argv)
    build(args.out)
    print(f"wrote {args.out}: {', '.join(sorted(p.stem for p in args.out.glob('*.json')))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
