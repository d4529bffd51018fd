"""The `deepcontact` command table (commands/): the product's commands, the lab as one lazy group."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from commands import COMMANDS, build_parser, main
from deepcontact.cli import Command, Group

ROOT = Path(__file__).resolve().parents[2]
PRODUCT = ["demo", "serve", "health", "simulate", "generate", "train", "train-graph", "export", "evaluate",
           "transfer-table"]
BENCH = ["engine", "iterations", "load", "scale", "server", "soak", "transfer", "walltime"]
INSTRUMENTS = ["admission", "admission-carry", "corrections", "face-solve", "faces", "generate", "graph-size", "inference",
               "joint-copy", "joint-route", "joint-start", "jointed-points", "joints-price", "label-reuse", "order", "route-ceiling", "route-stages", "spread", "step-gate", "surrogate", "simulate", "iterations"]


def _listed(lines) -> list[str]:
    """The subcommands an argparse help lists: the first word of each line indented by four spaces."""
    return [line.split()[0] for line in lines if line.startswith("    ") and not line.startswith("     ")]


def _run(*code_or_args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *code_or_args], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_help_lists_the_products_commands_and_the_lab_group_and_imports_no_command_module():
    code = ("import sys; from commands import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m.split('.')[0] for m in sys.modules if m.split('.')[0] in "
            "('lab', 'bench', 'simclient', 'server', 'training', 'numpy')))")
    done = _run("-c", code)
    assert done.returncode == 0, done.stderr
    *help_lines, imported = done.stdout.splitlines()
    assert imported == "[]"  # neither the lab nor any command's module: --help stays fast
    listed = _listed(help_lines)
    assert set(PRODUCT) | {"bench", "lab"} <= set(listed)
    bench = next(line for line in help_lines if line.strip().startswith("bench"))
    for instrument in ("admission", "face-solve", "surrogate", "step-gate"):
        assert instrument not in " ".join(help_lines)
    assert "engine" in bench


def test_bench_lists_the_products_benchmarks_only(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "--help"])
    listed = set(_listed(capsys.readouterr().out.splitlines()))
    assert listed == set(BENCH)


def test_lab_help_lists_every_instrument_with_a_line_of_help(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["lab", "--help"])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    listed = _listed(lines)
    assert sorted(listed) == sorted(INSTRUMENTS)
    from lab.commands import COMMANDS as LAB

    assert all(isinstance(c, Command) and c.help and "\n" not in c.help for c in LAB)


def test_the_table_names_the_product_and_reaches_the_lab_only_through_its_group():
    groups = [c for c in COMMANDS if isinstance(c, Group)]
    assert [g.words for g in groups] == [("lab",)] and groups[0].module == "lab.commands"
    assert not any(c.module.startswith("lab") for c in COMMANDS if isinstance(c, Command))
    assert all(importlib_spec(c.module) for c in COMMANDS)


def importlib_spec(module: str):
    import importlib.util

    return importlib.util.find_spec(module)


def test_python_dash_m_commands_runs_the_same_command_and_an_unknown_one_is_refused():
    done = _run("-m", "commands", "--version")
    assert done.returncode == 0 and done.stdout.startswith("deepcontact ")
    done = _run("-m", "commands", "lab", "nonsense")
    assert done.returncode == 2 and "invalid choice" in done.stderr


def test_an_unexpected_error_is_one_line_naming_the_command(tmp_path, monkeypatch, capsys):
    monkeypatch.delenv("DEEPCONTACT_DEBUG", raising=False)
    import simclient.simulate

    def broken(args):
        raise RuntimeError("a bug")

    monkeypatch.setattr(simclient.simulate, "run", broken)
    assert main(["lab", "simulate", "--seed", "1", "--warm-start", "builtin", "--out", str(tmp_path / "x.json")]) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["deepcontact lab simulate: unexpected error: RuntimeError: a bug "
                                        "(DEEPCONTACT_DEBUG=1 shows the traceback)"]


def test_a_group_table_is_loaded_only_when_the_group_is_parsed(capsys):
    from deepcontact.cli import build_parser as table_parser

    parser = table_parser([Command(("one",), "deepcontact.health", "a command"),
                           Group(("later",), "tests.commands.nonexistent_table", "a group whose table is missing")],
                          prog="t", description="a test table")
    assert parser.parse_args(["one", "--server", "127.0.0.1:1"])._words == ("one",)  # the group's table not needed
    with pytest.raises(SystemExit) as stop:  # parsed: its table is looked for, and is not there
        parser.parse_args(["later", "x"])
    assert stop.value.code == 2
    assert "t later: error: not installed here" in capsys.readouterr().err


def test_the_built_parser_is_the_one_main_uses():
    args = build_parser().parse_args(["bench", "engine"])
    assert args._module == "bench.engine" and args._words == ("bench", "engine")
