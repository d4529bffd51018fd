"""Checking a models folder as a whole: every card (`*.json`) and ONNX file, and
every bad one named at once.

`server.predictors.load_models` reads the folder through this module:

    problems = FolderProblems(folder)
    cards = read_cards(folder, problems)            # the cards that parse, by path
    check_onnx_files(folder, cards, problems)       # each *.onnx parses; some card names it
    ... load each card; problems.add(path, why) for each that cannot be served ...
    problems.raise_if_any() or problems.log_skipped()

An operator who fixes the first bad file of a folder should not learn of the
next one only at the next start: the error names every file and what is wrong
with it, on one line. A card is bad when its own file is, and also when what it
depends on is: the ONNX file it names, the card it is an alias of, the fallback
card of its face.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from deepcontact.modelcard import ModelCard, ModelCardError

log = logging.getLogger("deepcontact.server")
#: The problem of an ONNX file no card names; listed together as "no model card names A.onnx, B.onnx".
UNNAMED = "no model card names it"


class FolderProblems:
    """What is wrong in one models folder: one problem per file, in the order found."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.by_file: dict[str, str] = {}

    def add(self, path: Path | str, problem: str) -> None:
        """Record `problem` for the file at `path` (its first problem only: one reason per file)."""
        self.by_file.setdefault(Path(path).name, _one_line(problem, Path(path)))

    def __contains__(self, path: Path | str) -> bool:
        return Path(path).name in self.by_file

    def message(self) -> str:
        """One line naming every bad file and what is wrong with it."""
        n = len(self.by_file)
        parts = [f"{name}: {problem}" for name, problem in self.by_file.items() if problem != UNNAMED]
        unnamed = [name for name, problem in self.by_file.items() if problem == UNNAMED]
        if unnamed:
            parts.append(f"no model card names {', '.join(unnamed)}")
        listed = "; ".join(parts)
        return (f"{self.folder}: {n} bad model file{'s' if n > 1 else ''} ({listed}); "
                "--skip-bad-models serves the others")

    def raise_if_any(self) -> None:
        """ModelCardError with message() when any file is bad."""
        if self.by_file:
            raise ModelCardError(self.message())

    def log_skipped(self) -> None:
        """One warning line per bad file, for a server that serves the others."""
        for name, problem in self.by_file.items():
            log.warning(f"skipping bad model file {name}: {problem}",
                        extra={"file": str(self.folder / name), "problem": problem})


def read_cards(folder: Path, problems: FolderProblems) -> dict[Path, ModelCard]:
    """Every card in folder that reads as a card (an alias resolved), by path, sorted; the
    others go to `problems`. An alias whose target is bad says so rather than repeat
    the target's problem."""
    cards: dict[Path, ModelCard] = {}
    failed: dict[Path, Exception] = {}
    for path in sorted(Path(folder).glob("*.json")):
        try:
            cards[path] = ModelCard.load(path)
        except Exception as exc:  # any reason a card cannot be read makes it a bad file, not a crash
            failed[path] = exc
    for path, exc in failed.items():
        target = _alias_target(path)
        if target is not None and target != path and target in failed:
            problems.add(path, f"an alias of {target.name}, which is bad")
        else:
            problems.add(path, describe(exc))
    return cards


def check_onnx_files(folder: Path, cards: dict[Path, ModelCard], problems: FolderProblems) -> None:
    """Each `*.onnx` in folder must parse as an ONNX model and be named by a card; the
    others go to `problems`. A file that only a bad card names is not reported as
    unnamed: that card is."""
    named = {card.onnx_file for card in cards.values()} | _named_by_bad_cards(folder, cards)
    for path in sorted(Path(folder).glob("*.onnx")):
        problem = onnx_problem(path)
        if problem is None and path.name not in named:
            problem = UNNAMED
        if problem is not None:
            problems.add(path, problem)


def onnx_problem(path: Path) -> str | None:
    """What is wrong with an ONNX file as a file (it cannot be read, does not parse as a
    model, or fails ONNX's checker), or None. Cheap (about half a millisecond a file:
    no ONNX Runtime session), so a folder's files are all checked before any is loaded."""
    import onnx

    try:
        model = onnx.load(str(path), load_external_data=False)
    except OSError as exc:
        return f"cannot read it ({exc.strerror or exc})"
    except Exception as exc:  # protobuf's DecodeError and the like
        return f"not an ONNX model ({describe(exc)})"
    try:
        onnx.checker.check_model(model)
    except Exception as exc:  # onnx.checker.ValidationError
        return f"not a valid ONNX model ({describe(exc)})"
    return None


def dependency_problem(path: Path, card: ModelCard, problems: FolderProblems) -> str | None:
    """Why a card that reads cannot be served for a bad file it depends on (the ONNX file
    it names, its face's fallback card), or None."""
    if plain_name(card.onnx_file) and card.onnx_file in problems:
        return f"names {card.onnx_file}, which is bad"
    fallback = card.face["fallback"] if card.face is not None else None
    if fallback is not None and plain_name(f"{fallback}.json") and f"{fallback}.json" in problems:
        return f"its face falls back to {fallback!r}, which is bad"
    return None


def plain_name(name: str) -> bool:
    """Whether `name` is a file name inside the folder, not a path that leaves it."""
    return name not in ("", ".", "..") and Path(name).name == name


def describe(exc: BaseException) -> str:
    """An exception as a short reason: a ModelCardError or ValueError by its message (it
    was written for users), anything else with its type's name in front."""
    if isinstance(exc, ModelCardError) or type(exc) is ValueError:
        return str(exc)
    return f"{type(exc).__name__}: {exc}"


def _one_line(problem: str, path: Path) -> str:
    """The problem on one line, without a leading "PATH: " (the file is named beside it)."""
    text = " ".join(str(problem).split())
    for prefix in (f"{path}: ", f"{path.name}: "):
        if text.startswith(prefix):
            text = text[len(prefix):]
    return text


def _alias_target(path: Path) -> Path | None:
    """The card an alias card at path names, beside it; None for a full card or one unread."""
    try:
        target = ModelCard.alias_target(path)
    except Exception:
        return None
    return path.with_name(f"{target}.json") if isinstance(target, str) and plain_name(f"{target}.json") else None


def _named_by_bad_cards(folder: Path, cards: dict[Path, ModelCard]) -> set[str]:
    """The onnx_file of each card that did not read as a card but is JSON with one."""
    named = set()
    for path in Path(folder).glob("*.json"):
        if path in cards:
            continue
        try:
            data = json.loads(path.read_text())
        except Exception:
            continue
        if isinstance(data, dict) and isinstance(data.get("onnx_file"), str):
            named.add(data["onnx_file"])
    return named
