"""lab.joint_start: a chain's closed loops, served with and without the joints' start."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from lab.joint_start import RUNS, add_arguments, run, simulate

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def test_each_run_of_the_chain_is_a_closed_loop_of_its_own(capsys):
    from simclient.worlds import WorldSpec

    spec = WorldSpec(f"{EXAMPLES / 'chain.py'}:build", steps=60)
    spec.validate()
    runs = {name: simulate(spec, 850, "models", "default", name) for name in RUNS}
    assert all(len(r) > 0 for r in runs.values())
    assert np.array_equal(runs["builtin"], simulate(spec, 850, "models", "default", "builtin"))  # deterministic
    # The joints started elsewhere move the solve: the closed loop parts from the one served without.
    assert not np.array_equal(runs["served+joints"], runs["served"])
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(["--world", f"{EXAMPLES / 'chain.py'}:build", "--seeds", "850-851",
                                  "--steps", "30"])) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][1:]
    assert [line.split("|")[1].strip() for line in table] == list(RUNS)


def test_a_world_that_does_not_load_is_one_line_of_error(capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(["--world", "no/such.py:build"])) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("deepcontact lab joint-start:") and "\n" not in err


def test_ragdolls_priced_on_box2ds_own_states_every_run_on_the_same_steps(capsys):
    from lab.joint_start import priced
    from simclient.worlds import WorldSpec

    spec = WorldSpec("simclient.zoo:ragdolls", steps=80)
    spec.validate()
    runs = priced(spec, 850, "models", "default")
    assert set(runs) == {"builtin", "served", "served+revolute", "builtin+limits*", "served+revolute+limits*"}
    assert len({len(r) for r in runs.values()}) == 1 and len(runs["builtin"]) > 0  # the very same steps
    # The joints' limits and motors in the server's copy: its start differs from the contacts' alone.
    assert not np.array_equal(runs["served+revolute"], runs["served"])
    # The limits started at the impulse Box2D's own solve ends at: a start of their own.
    assert not np.array_equal(runs["builtin+limits*"], runs["builtin"])
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(["--world", "simclient.zoo:ragdolls", "--seeds", "850-851", "--steps", "40",
                                  "--on-builtin"])) == 0
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")][1:]
    assert [line.split("|")[1].strip() for line in table] == ["builtin", "served", "served+revolute", "builtin+limits*",
                                                               "served+revolute+limits*"]
