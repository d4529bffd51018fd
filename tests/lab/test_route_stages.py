"""lab.route_stages: a served model's stages on a user's world, summarized by step size."""

from __future__ import annotations

import numpy as np

from commands import main
from lab.route_stages import answered_by, solve_ways, stage_medians


def test_route_stages_prints_each_stage_of_the_default_on_a_users_world(capsys):
    assert main(["lab", "route-stages", "--world", "examples/stack.py:build", "--steps", "12", "--large", "10"]) == 0
    out = capsys.readouterr().out
    assert "`examples/stack.py:build` seed 850, default in process" in out
    for stage in ("features", "inference", "solve", "admit", "total"):
        assert f"| {stage} |" in out
    # A resting stack of boxes: no point slides, so its solves run in the bodies' space.
    assert "| bodies |" in out and "| dual |" in out


def test_route_stages_refuses_a_world_it_cannot_load_in_one_line(capsys):
    assert main(["lab", "route-stages", "--world", "no_such_file.py:build"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    # A deadline inside the server's own margin leaves the route nothing: refused the same way.
    assert main(["lab", "route-stages", "--world", "examples/stack.py:build", "--deadline-ms", "2"]) == 2
    assert "--deadline-ms must exceed" in capsys.readouterr().err


def test_under_a_deadline_route_stages_counts_what_answered_each_step(capsys):
    assert main(["lab", "route-stages", "--world", "examples/stack.py:build", "--steps", "12", "--large", "10",
                 "--deadline-ms", "1000"]) == 0
    out = capsys.readouterr().out
    assert "each step due 997 ms after its call (a 1000 ms request's)" in out
    assert "| answered by | steps | of at least 10 points |" in out


def test_what_answered_is_counted_over_every_step_and_the_large_ones():
    sizes = np.array([100, 600, 700, 800])
    counted = answered_by(sizes, [None, "builtin", "zoo", "builtin"], large=500)
    assert counted == {"builtin": (2, 2), "the model": (1, 0), "zoo": (1, 1)}
    assert list(counted)[0] == "builtin"  # the most steps first


def test_the_large_steps_are_summarized_apart_and_total_is_the_stages_sum():
    sizes = np.array([100, 600, 700])
    stages = [{"solve": 0.001, "admit": 0.001}, {"solve": 0.010, "admit": 0.002}, {"solve": 0.020, "admit": 0.002}]
    medians = stage_medians(sizes, stages, large=500)
    assert medians["solve"] == (10.0, 15.0)
    assert medians["total"] == (12.0, 17.0)
    assert np.isnan(stage_medians(sizes, stages, large=1000)["solve"][1])


def test_the_solves_are_counted_by_the_way_they_ran():
    solves = [(100, 0.001, True), (600, 0.002, True), (700, 0.010, False)]
    ways = solve_ways(solves, large=500)
    assert ways["bodies"] == (2, 1, 1.5, 2.0)
    assert ways["dual"][:3] == (1, 1, 10.0)
    assert np.isnan(solve_ways(solves[:1], large=500)["dual"][2])
