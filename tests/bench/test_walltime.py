"""`deepcontact bench walltime`: whole step times per world size, and the break-even."""

from __future__ import annotations

import json
import os

import pytest

import numpy as np

from bench.walltime import overhead_allowed, scene_for, solve_fit
from commands import main
from tests.server.conftest import write_conv_model


def test_family_worlds_keep_the_thesis_density_as_they_grow():
    assert scene_for("thesis", 250).box_size == (15.0, 15.0)
    assert scene_for("100", 250).box_size == (15.0, 15.0) and scene_for("100", 250).radius == (0.3, 0.55)
    assert scene_for("400", 250).box_size == (30.0, 30.0) and scene_for("400", 250).bodies == 400
    with pytest.raises(ValueError, match="number of bodies"):
        scene_for("huge", 250)


def test_a_sweep_costs_the_slope_of_the_solve_times_not_their_ratio():
    # Solves of 0.4 ms plus 3.5 us a sweep: the median ratio would say 5 us and more a sweep.
    sweeps = np.array([50, 120, 300, 700, 1000])
    fixed, per_sweep = solve_fit(0.4 + 0.0035 * sweeps, sweeps)
    assert fixed == pytest.approx(0.4) and per_sweep == pytest.approx(0.0035)
    assert solve_fit(np.array([1.0, 1.1]), np.array([80, 80])) is None  # no spread: no line


def test_the_overhead_a_ratio_allows_is_what_is_left_of_it_after_collide_and_solve():
    # Builtin's step 1.6 ms; the learned 2.7 ms, 1.4 of it overhead: 1.5x allows 2.4 - 1.3 ms.
    assert overhead_allowed(1.5, 1.6, 2.7, 1.4) == pytest.approx(1.1)
    assert overhead_allowed(1.0, 1.6, 2.7, 1.4) == pytest.approx(0.3)


def test_bench_walltime_times_builtin_the_served_and_the_in_process_model_on_every_size(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    out = tmp_path / "out"
    assert main(["bench", "walltime", "--sizes", "thesis,40", "--seeds", "901", "--steps", "90",
                 "--models", str(models), "--model", "tiny", "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "walltime.json").read_text())
    assert set(result["sizes"]) == {"thesis", "family-40"}
    thesis = result["sizes"]["thesis"]
    assert thesis["learned"]["fallback_steps"] == 0  # served, so timed
    assert thesis["learned"]["round_trip_ms"] > 0 and thesis["ms_per_iteration"] > 0
    assert thesis["learned"]["first_round_trip_ms"] > 0
    # Builtin's step is Box2D's own work; the learned one adds the round trip.
    assert thesis["learned"]["step_ms"] > thesis["learned"]["solve_ms"] + thesis["learned"]["collide_ms"]
    assert thesis["break_even_iterations"] == pytest.approx(thesis["learned"]["overhead_ms"] / thesis["ms_per_iteration"])
    # The same model called in process: the served warm starts without the round trip.
    local = thesis["in_process"]
    assert local["mean_iterations"] == thesis["learned"]["mean_iterations"]  # the same trajectory
    assert local["predict_ms"] > 0 and local["inference_ms"] > 0
    assert local["break_even_iterations"] == pytest.approx(local["overhead_ms"] / thesis["ms_per_iteration"])
    budget = thesis["budget"]
    assert budget["overhead_allowed_ms"]["1.5"] > budget["overhead_allowed_ms"]["1.0"]
    assert budget["saved_ms"] == pytest.approx(thesis["saved_iterations"] * thesis["ms_per_iteration"])
    table = (out / "walltime.md").read_text()
    assert "| family-40 | 40 |" in table and "in-process:tiny" in table and "overhead for 1.5x" in table
    assert (out / "walltime.png").stat().st_size > 10_000


def test_bench_walltime_refuses_an_unknown_model(tmp_path, model_dir, capsys):
    assert main(["bench", "walltime", "--sizes", "thesis", "--seeds", "901", "--models", str(model_dir),
                 "--model", "nope", "--out", str(tmp_path), "--quiet"]) == 2
    assert "no model 'nope'" in capsys.readouterr().err


def test_bench_walltime_can_leave_the_in_process_run_out(tmp_path, model_dir):
    assert main(["bench", "walltime", "--sizes", "thesis", "--seeds", "901", "--steps", "30", "--no-in-process",
                 "--models", str(model_dir), "--model", "tiny", "--out", str(tmp_path), "--quiet"]) == 0
    result = json.loads((tmp_path / "walltime.json").read_text())
    assert "in_process" not in result["sizes"]["thesis"]
    assert "in-process" not in (tmp_path / "walltime.md").read_text()


def test_bench_walltime_serves_over_a_unix_socket_when_told_to(tmp_path, model_dir):
    bind = f"unix:{tmp_path / 'warmstart.sock'}"
    assert main(["bench", "walltime", "--sizes", "thesis", "--seeds", "901", "--steps", "30", "--no-in-process",
                 "--models", str(model_dir), "--model", "tiny", "--bind", bind, "--out", str(tmp_path), "--quiet"]) == 0
    result = json.loads((tmp_path / "walltime.json").read_text())
    assert result["bind"] == bind and result["sizes"]["thesis"]["learned"]["round_trip_ms"] > 0


def test_bench_walltime_times_a_users_world_at_the_tolerance_it_is_given(tmp_path, model_dir):
    out = tmp_path / "out"
    assert main(["bench", "walltime", "--world", "examples/stack.py:build", "--tolerance", "1e-6",
                 "--max-iterations", "2000", "--seeds", "901", "--steps", "40", "--models", str(model_dir),
                 "--model", "tiny", "--out", str(out), "--quiet"]) == 0
    result = json.loads((out / "walltime.json").read_text())
    assert result["solver"]["velocity_threshold"] == 1e-6 and result["solver"]["velocity_iterations"] == 2000
    row = result["sizes"]["examples/stack.py:build"]
    assert row["bodies"] == 12 and row["box_size"] is None  # read off the world the function builds
    assert row["learned"]["fallback_steps"] == 0 and row["in_process"]["mean_iterations"] > 0
    # The ratio a user's simulation sees: the whole step's mean, learned over Builtin's.
    table = (out / "walltime.md").read_text()
    ratio = row["learned"]["mean_step_ms"] / row["builtin"]["mean_step_ms"]
    assert f"**{ratio:.2f}** |" in table and "solved to 1e-06 N s, at most 2000 velocity iterations" in table


@pytest.mark.parametrize("flags, message", [
    (["--world", "nowhere.py:build"], "there is no file nowhere.py"),
    (["--world", "examples/stack.py:missing"], "has no function 'missing'"),
    (["--world", "examples/stack.py:build", "--sizes", "thesis"], "not both"),
    (["--tolerance", "0"], "--tolerance and --dt must be > 0"),
    (["--max-iterations", "0"], "--max-iterations >= 1"),
])
def test_bench_walltime_refuses_a_world_it_cannot_build_in_one_line_and_writes_nothing(tmp_path, model_dir, capsys,
                                                                                      flags, message):
    out = tmp_path / "out"
    assert main(["bench", "walltime", *flags, "--seeds", "901", "--models", str(model_dir), "--model", "tiny",
                 "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_the_wall_of_stacks_stands_at_two_points_a_box():
    from bench.stack_wall import BOXES, COLUMNS, build
    from simclient.engine import Engine, SolverConfig

    engine = Engine(build(901), SolverConfig())
    points = [engine.step().contact_points for _ in range(40)]
    assert engine.world.bodyCount == 1 + COLUMNS * BOXES
    # Every box on a face: the ten columns stand (until they fall asleep, column by column, and
    # their points leave the solve).
    assert points[-1] == 2 * COLUMNS * BOXES


def test_the_deep_wall_stands_twenty_boxes_a_column():
    from bench.stack_wall import COLUMNS, deep
    from simclient.engine import Engine, SolverConfig

    engine = Engine(deep(901), SolverConfig())
    points = [engine.step().contact_points for _ in range(40)]
    assert engine.world.bodyCount == 1 + COLUMNS * 20 and points[-1] == 2 * COLUMNS * 20


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="pinning needs two cores")
def test_bench_walltime_pins_the_server_to_the_last_core_and_the_simulation_to_the_rest(tmp_path, model_dir):
    cores = sorted(os.sched_getaffinity(0))
    assert main(["bench", "walltime", "--sizes", "thesis", "--seeds", "901", "--steps", "30", "--no-in-process",
                 "--pin", "--models", str(model_dir), "--model", "tiny", "--out", str(tmp_path), "--quiet"]) == 0
    result = json.loads((tmp_path / "walltime.json").read_text())
    assert result["pinned"] == {"server": cores[-1:], "simulation": cores[:-1]}
    assert f"The server on core {cores[-1]}" in (tmp_path / "walltime.md").read_text()
    assert sorted(os.sched_getaffinity(0)) == cores  # this process gets its cores back


def test_bench_walltime_refuses_to_pin_on_one_core_in_one_line_and_writes_nothing(tmp_path, model_dir, capsys,
                                                                                 monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0})
    out = tmp_path / "out"
    assert main(["bench", "walltime", "--sizes", "thesis", "--seeds", "901", "--pin", "--models", str(model_dir),
                 "--model", "tiny", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--pin needs two cores or more" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
