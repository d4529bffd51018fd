"""Record on a card what its model was measured to need: its `measured` (deepcontact.modelcard).

    deepcontact bench iterations --seeds 850-899 --warm-starts builtin,server:default --no-guard --out runs/measured
    python -m training.measure models/default.json runs/measured/summary.json

Reads the mean iterations' ratio to Builtin and its bootstrap interval from a `bench iterations`
summary (run without the guard, on choosing seeds of a world inside the card's trained_on) and
writes them, with the summary's command, into the card (alias or full; temporary name, then
rename). The server vouches for a model on a familiar step only where this interval lies
wholly below 1 (docs/worlds.md, "The guard").
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from deepcontact.io import write_json_atomic
from deepcontact.modelcard import ModelCard, ModelCardError


class MeasureError(ValueError):
    """A summary or card that cannot be measured from or written to; the message says which."""


def measured_from(summary: dict, model: str) -> dict:
    """The card's `measured` from a bench iterations summary of `server:MODEL` without the guard."""
    if summary.get("guard"):
        raise MeasureError("the summary was run with the guard; measure with --no-guard")
    if summary.get("seeds") and not all(850 <= s <= 899 for s in summary["seeds"]):
        raise MeasureError("measure on the choosing seeds 850-899 (docs/data.md)")
    try:
        mean = summary["ratios_to_builtin"][f"server:{model}"]["mean"]
    except KeyError:
        raise MeasureError(f"the summary holds no ratio of server:{model} to builtin") from None
    return {"ratio": round(mean["value"], 3), "interval": [round(mean["low"], 3), round(mean["high"], 3)],
            "command": _rerunnable(summary["command"])}


def _rerunnable(command: str) -> str:
    """The summary's command without what only that run had (its folder, its server, quiet)."""
    words, kept = shlex.split(command), []
    skip = False
    for word in words:
        if skip:
            skip = False
        elif word in ("--out", "--server"):
            skip = True
        elif word != "--quiet":
            kept.append(word)
    return shlex.join(kept + ["--out", "OUT"])


def record(card_path: Path, summary_path: Path) -> dict:
    """Write `measured` into the card at card_path; returns it."""
    data = json.loads(Path(card_path).read_text())
    card = ModelCard.load(card_path)  # a card that does not read is refused before anything is written
    measured = measured_from(json.loads(Path(summary_path).read_text()), card.name)
    write_json_atomic(card_path, {**data, "measured": measured})
    ModelCard.load(card_path)
    return measured


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.measure", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("card", type=Path, help="the card to write measured into (e.g. models/default.json)")
    parser.add_argument("summary", type=Path, help="bench iterations' summary.json, run without the guard")
    args = parser.parse_args(argv)
    try:
        measured = record(args.card, args.summary)
    except (MeasureError, ModelCardError, OSError, json.JSONDecodeError) as exc:
        print(f"training.measure: {exc}", file=sys.stderr)
        return 2
    print(f"{args.card}: measured {measured['ratio']}x [{measured['interval'][0]}, {measured['interval'][1]}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
