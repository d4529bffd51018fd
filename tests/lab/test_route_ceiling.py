"""`deepcontact lab route-ceiling`: the route on the oracle's own labels, priced on Box2D's states
(lab.route_ceiling), on the vertical stack of examples/: a stack at rest is solved on its labels
exactly, so the route's ceiling there lies far below Box2D's start."""

from __future__ import annotations

import numpy as np

from lab.route_ceiling import ANSWERS, price, table
from simclient.worlds import WorldSpec


def test_a_stack_at_rest_on_its_own_labels_needs_a_few_sweeps_where_box2ds_start_needs_many():
    runs = [price(WorldSpec("examples/stack.py:build", steps=60), 901, rounds=200)]
    its = runs[0]
    assert set(its) == set(ANSWERS) and len(its["builtin"]) > 20
    assert its["oracle"].mean() < 0.2 * its["builtin"].mean()
    assert its["labels:oracle"].mean() < 0.5 * its["builtin"].mean()
    printed = table(runs, cap=1000)
    assert printed.splitlines()[2].startswith("| builtin |") and "labels:oracle-long" in printed


def test_bad_rounds_are_one_line_and_nothing_runs(capsys):
    import argparse

    from lab.route_ceiling import add_arguments, run

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(["--world", "examples/stack.py:build", "--rounds", "0"])) == 2
    assert capsys.readouterr().err.strip() == "deepcontact lab route-ceiling: --rounds must be >= 1, got 0"
