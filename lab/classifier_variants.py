"""A model folder with the shipped default served on cheaper classifiers, for pricing them on the
same states and timing them on the same server (issue 101's Pareto table: cost against iterations;
docs/research/2026-12-07-fewer-rounds.md):

    python -m lab.classifier_variants runs/classifier-variants
    deepcontact lab iterations --seeds 850-899 --deadline-ms 1000 --models runs/classifier-variants \
        --warm-starts builtin,price:server:default+server:default-r8-long+...
    deepcontact bench server --models runs/classifier-variants --model default-r8-long --rounds 3

Beside models/ it writes, for each network of ROUND_VARIANTS (the research store, lab/models), a
card `NAME-modes` over it and `default-NAME`: the shipped default's face, fallback and measured
scale exactly as models/default.json has them, its classifier that network in place of
contact-modes (twelve rounds of width 32):

    default-r8-long  the eight-round classifier the shipped one was grown from
                     (graph-face-fr-r8-long: the same data and inputs, 11 epochs)
    default-r8       the shipped classifier's first eight rounds, trained on (graph-face-fr-r12-e15-r8)
    default-r6       its first six, trained on (graph-face-fr-r12-e15-r6)
    default-r4       its first four, trained on (graph-face-fr-r12-e15-r4)

A network missing from the store is left out, with a line on standard error. Written to a
temporary folder and renamed; an existing folder is replaced.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

from lab.variants import ROOT, card, write_folder
from lab.variants import main as variants_main

STORE = ROOT / "lab" / "models"
#: (store name, tag): each a classifier with contact-modes' inputs and outputs and fewer rounds.
ROUND_VARIANTS = (("graph-face-fr-r8-long", "r8-long"), ("graph-face-fr-r12-e15-r8", "r8"),
                  ("graph-face-fr-r12-e15-r6", "r6"), ("graph-face-fr-r12-e15-r4", "r4"))


def _fill(tmp: Path) -> None:
    shipped = json.loads((tmp / "default.json").read_text())
    for store_name, tag in ROUND_VARIANTS:
        if not (STORE / f"{store_name}.json").exists():
            print(f"python -m lab.classifier_variants: {store_name} is not in lab/models; default-{tag} left out",
                  file=sys.stderr)
            continue
        network = json.loads((STORE / f"{store_name}.json").read_text())
        name = f"{tag}-modes"
        network.update(name=name, onnx_file=f"{name}.onnx", measured=None)
        shutil.copy(STORE / f"{store_name}.onnx", tmp / f"{name}.onnx")
        (tmp / f"{name}.json").write_text(json.dumps(network, indent=1) + "\n")
        card(tmp, f"default-{tag}", alias_of=name, face=shipped["face"], measured=shipped.get("measured"))


def build(out: Path) -> None:
    """Write the folder the module docstring describes at `out`."""
    write_folder(out, _fill)


def main(argv: list[str] | None = None) -> int:
    return variants_main(argv, "python -m lab.classifier_variants", __doc__, build)


if __name__ == "__main__":
    sys.exit(main())
