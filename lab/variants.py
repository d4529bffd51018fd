"""Model folders of variants beside the shipped models, for pricing them on the same states: the
shared part of lab.zoo_variants and lab.admission_variants.

    write_folder(out, fill)   # models/ copied to OUT.part, fill(folder) adds the cards, renamed to OUT
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]


def card(folder: Path, name: str, **fields) -> None:
    """Write the card NAME.json into folder: {"name": name, **fields}."""
    (folder / f"{name}.json").write_text(json.dumps({"name": name, **fields}, indent=1) + "\n")


def write_folder(out: Path, fill: Callable[[Path], None]) -> None:
    """models/ with fill(folder)'s cards beside it at `out`: written to a temporary folder and
    renamed; an existing folder is replaced."""
    tmp = out.with_name(out.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(ROOT / "models", tmp)
    fill(tmp)
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)


def main(argv: list[str] | None, prog: str, doc: str, build: Callable[[Path], None]) -> int:
    """A variants module's command line: `python -m PROG OUT` builds the folder at OUT."""
    parser = argparse.ArgumentParser(prog=prog, description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="the folder to write (replaced if it exists)")
    args = parser.parse_args(argv)
    build(args.out)
    print(f"wrote {args.out}: {', '.join(sorted(p.stem for p in args.out.glob('*.json')))}")
    return 0
