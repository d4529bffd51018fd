"""Arguments several commands share, defined once.

    add_models_argument(parser)                                   # --models DIR, default models/
    add_seed_argument(parser, default=900, help="thesis-world seed (default 900)")
"""

from __future__ import annotations

import argparse
from pathlib import Path

DEFAULT_MODELS = Path("models")


def add_models_argument(parser: argparse.ArgumentParser, help: str | None = None,
                        default: Path = DEFAULT_MODELS) -> None:
    """--models DIR (a Path): the model folder; help says what it is for (default: "model folder")."""
    parser.add_argument("--models", type=Path, default=Path(default), metavar="DIR",
                        help=f"{help or 'model folder'} (default {default}/)")


def add_seed_argument(parser: argparse.ArgumentParser, help: str, default: int | None = None,
                      required: bool = False) -> None:
    """--seed N (an int); help says whose seed it is and its default."""
    parser.add_argument("--seed", type=int, default=default, required=required, help=help)
