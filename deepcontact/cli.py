"""The machinery of a command table: a parser built from one, loaded lazily, and a one-line end.

    TABLE = [Command(("simulate",), "simclient.simulate", "one simulation with one warm start"),
             Command(("bench", "iterations"), "bench.iterations", "every warm start on the same worlds"),
             Group(("lab",), "lab.commands", "research instruments")]
    parser = build_parser(TABLE, prog="deepcontact", description="...", groups={("bench",): "benchmarks"})
    sys.exit(main(parser, argv))

A Command's module does the work and exposes `add_arguments(parser)` and `run(args) -> int`;
it is imported only when its subcommand is parsed, so `--help` stays fast (no TensorFlow). A
Group's module holds a table of its own (`COMMANDS`, and `GROUPS` for its inner groups' help),
imported only when the group is parsed: a table on this floor names no module above it, the
entry package that passes one in does (commands/). A command ends with its summary or a
one-line error, never a traceback (DEEPCONTACT_DEBUG=1 shows it).
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import NamedTuple


class Command(NamedTuple):
    """A subcommand: the words that name it, the module that runs it, its one-line help."""

    words: tuple[str, ...]
    module: str  # exposes add_arguments(parser) and run(args) -> int
    help: str


class Group(NamedTuple):
    """A group of subcommands whose table is another module's, loaded when the group is parsed."""

    words: tuple[str, ...]
    module: str  # holds COMMANDS (a table) and optionally GROUPS ({words: help} of its inner groups)
    help: str


def build_parser(table, *, prog: str, description: str, version: str | None = None,
                 groups: dict[tuple[str, ...], str] | None = None) -> argparse.ArgumentParser:
    """A parser for every entry of `table` (Command and Group). groups: the help of the groups
    the commands' words make (e.g. ("bench",)); each group's help ends with its commands' names."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    if version is not None:
        parser.add_argument("--version", action="version", version=version)
    add_table(parser, table, groups=groups)
    return parser


def add_table(parser: argparse.ArgumentParser, table, *, groups: dict[tuple[str, ...], str] | None = None,
              words: tuple[str, ...] = ()) -> None:
    """The entries of `table` as subcommands of `parser`, which stands for the command `words`."""
    groups = groups or {}
    depth = len(words)
    levels: dict[tuple[str, ...], argparse._SubParsersAction] = {
        (): parser.add_subparsers(dest=f"command_{depth}" if depth else "command", metavar="COMMAND", required=True)}
    for entry in table:
        for k in range(1, len(entry.words)):
            prefix = entry.words[:k]
            if prefix not in levels:
                names = sorted({e.words[k] for e in table if e.words[:k] == prefix})
                text = f"{groups.get(prefix, '')} ({', '.join(names)})".strip()
                sub = levels[prefix[:-1]].add_parser(prefix[-1], help=text, description=text)
                levels[prefix] = sub.add_subparsers(dest=f"command_{depth + k}", metavar="COMMAND", required=True)
        sub = levels[entry.words[:-1]].add_parser(entry.words[-1], help=entry.help, description=entry.help)
        if isinstance(entry, Group):
            _lazy(sub, lambda sub=sub, entry=entry: _add_group(sub, entry, words + entry.words))
        else:
            sub.set_defaults(_module=entry.module, _words=words + entry.words)
            _lazy(sub, lambda sub=sub, entry=entry: importlib.import_module(entry.module).add_arguments(sub))


def _add_group(parser: argparse.ArgumentParser, group: Group, words: tuple[str, ...]) -> None:
    try:
        module = importlib.import_module(group.module)
    except ModuleNotFoundError as exc:
        if exc.name is None or not group.module.startswith(exc.name):
            raise  # the table is there and imports something missing: a bug, said as one
        parser.error(f"not installed here ({exc})")  # e.g. an image of the product alone
    add_table(parser, module.COMMANDS, groups=getattr(module, "GROUPS", None), words=words)


def _lazy(sub: argparse.ArgumentParser, load) -> None:
    """Run load() (add the subcommand's arguments, or a group's table) the first time `sub` parses."""
    original = sub.parse_known_args

    def parse_known_args(args=None, namespace=None):
        if not getattr(sub, "_deepcontact_loaded", False):
            load()
            sub._deepcontact_loaded = True
        return original(args, namespace)

    sub.parse_known_args = parse_known_args


#: The packages of pyproject.toml's extras, by the name a missing one is imported as: a command
#: whose part needs one says which extra installs it, in one line.
EXTRAS = {"tensorflow": "train", "tf2onnx": "train", "keras": "train", "h5py": "train", "matplotlib": "bench",
          "hdrh": "bench", "ray": "ray"}


def main(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> int:
    """Parse `argv` and run the chosen command: its exit status, 130 on ^C, and 1 with one line
    on stderr for an exception it did not expect (DEEPCONTACT_DEBUG=1: the traceback instead)."""
    words: tuple[str, ...] = ()
    try:
        args = parser.parse_args(argv)  # loads the chosen command's module (its arguments)
        words = args._words
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        missing = _missing_part(exc)
        if missing and not os.environ.get("DEEPCONTACT_DEBUG"):
            words = words or _command_words(sys.argv[1:] if argv is None else argv)  # parsing itself failed
            print(f"{' '.join((parser.prog, *words))}{missing}", file=sys.stderr)
            return 2
        # Commands answer what they expect with their own one-line errors; this is
        # for what they did not expect (a bug). DEEPCONTACT_DEBUG=1 shows where.
        if os.environ.get("DEEPCONTACT_DEBUG"):
            raise
        print(f"{' '.join((parser.prog, *words))}: unexpected error: {type(exc).__name__}: {exc} "
              "(DEEPCONTACT_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 1


def _missing_part(exc: Exception) -> str | None:
    """The end of a one-line error for a package this install lacks (" needs ...: pip install
    'deepcontact[EXTRA]'", or the patched Box2D's build hint), None for any other exception."""
    if isinstance(exc, ModuleNotFoundError) and (exc.name or "").split(".")[0] in EXTRAS:
        return (f" needs {exc.name}, which this install lacks: "
                f"pip install 'deepcontact[{EXTRAS[exc.name.split('.')[0]]}]'")
    if isinstance(exc, ImportError) and "make box2d" in str(exc):  # simclient.engine's own hint
        return f": {exc}"
    return None


def _command_words(argv: list[str]) -> tuple[str, ...]:
    """The command's words at the head of argv (before the first flag, at most two, no paths)."""
    words = []
    for arg in argv[:2]:
        if arg.startswith("-") or "/" in arg or "." in arg:
            break
        words.append(arg)
    return tuple(words)
