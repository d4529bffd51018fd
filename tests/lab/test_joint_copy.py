"""lab.joint_copy: the server's copy of a chain's step, with its joints and without, against the engine."""

from __future__ import annotations

import argparse
from pathlib import Path

from lab.joint_copy import add_arguments, run

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _args(*argv):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_the_chains_copy_with_its_joints_agrees_with_the_engine_more_often(capsys):
    assert run(_args("--world", f"{EXAMPLES / 'chain.py'}:build", "--seeds", "850", "--steps", "80")) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| with") or line.startswith("| without")]
    share = [int(r.split("|")[2].split(" of ")[0]) for r in rows]
    assert len(share) == 2 and share[0] >= share[1]


def test_a_world_with_other_joints_is_one_line_of_error(capsys):
    assert run(_args("--world", f"{EXAMPLES / 'car.py'}:build", "--seeds", "850", "--steps", "40")) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("deepcontact lab joint-copy:") and "\n" not in err
