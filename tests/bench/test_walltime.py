"""`deepcontact bench walltime`: whole step times per world size, and the break-even."""

from __future__ import annotations

import json

import pytest

from bench.walltime import scene_for
from commands import main
from tests.server.conftest import write_conv_model


def test_family_worlds_keep_the_thesis_density_as_they_grow():
    assert scene_for("thesis", 250).box_size == (15.0, 15.0)
    assert scene_for("100", 250).box_size == (15.0, 15.0) and scene_for("100", 250).radius == (0.3, 0.55)
    assert scene_for("400", 250).box_size == (30.0, 30.0) and scene_for("400", 250).bodies == 400
    with pytest.raises(ValueError, match="number of bodies"):
        scene_for("huge", 250)


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
    table = (out / "walltime.md").read_text()
    assert "| family-40 | 40 |" in table and "in-process:tiny" in table
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
