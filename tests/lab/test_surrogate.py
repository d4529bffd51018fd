"""`deepcontact lab surrogate`: the loss's per-step score beside the iterations a model saves,
on the steps of a recorded file, simulated again with the engine's trial solves.

The commands that load TensorFlow (train-graph, the surrogate's scoring) run as their own
processes: TensorFlow's threads in the test process break the tests that fork after them."""

from __future__ import annotations

import json
import subprocess
import sys

import h5py
import numpy as np
import pytest

from commands import main


def deepcontact(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "commands", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A recorded validation file and a tiny contact-graph model trained on two other seeds."""
    d = tmp_path_factory.mktemp("surrogate")
    for name, seeds in (("train", "1-2"), ("val", "3")):
        assert main(["generate", "--steps", "20", "--seeds", seeds, "--out", str(d / f"{name}.h5"), "--quiet"]) == 0
    models = d / "models"
    trained = deepcontact("train-graph", "--train", str(d / "train.h5"), "--val", str(d / "val.h5"), "--out",
                          str(models / "g.onnx"), "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds",
                          "1", "--loss", "mse", "--cache", str(d / "cache"), "--quiet")
    assert trained.returncode == 0, trained.stderr
    return d


def test_every_recorded_step_gets_its_score_and_its_saving(recorded, tmp_path):
    out = tmp_path / "surrogate.json"
    scored = deepcontact("lab", "surrogate", "--models", str(recorded / "models"), "--model", "g",
                         "--data", str(recorded / "val.h5"), "--sweeps", "0,4", "--json", str(out))
    assert scored.returncode == 0, scored.stderr
    report = json.loads(out.read_text())
    with h5py.File(recorded / "val.h5", "r") as f:
        with_contacts = int((f["steps"]["point_count"] > 0).sum())
    assert report["steps"] == with_contacts == sum(r["steps"] for r in report["deciles"])
    assert -1.0 <= report["spearman"] <= 1.0 and report["mean_builtin"] > 0
    assert all(r["low"] <= r["mean_score"] <= r["high"] for r in report["deciles"])
    assert report["order"] == "jacobi" and report["omega"] == 0.5


def test_the_score_can_follow_the_solvers_own_order(recorded, tmp_path):
    out = tmp_path / "surrogate-gs.json"
    scored = deepcontact("lab", "surrogate", "--models", str(recorded / "models"), "--model", "g",
                         "--data", str(recorded / "val.h5"), "--sweeps", "0,4", "--order", "gauss-seidel",
                         "--json", str(out))
    assert scored.returncode == 0, scored.stderr
    report = json.loads(out.read_text())
    assert report["order"] == "gauss-seidel" and report["omega"] == 1.0  # undamped, as Box2D
    assert report["steps"] == sum(r["steps"] for r in report["deciles"]) > 0


def test_a_file_that_the_engine_does_not_repeat_is_refused(recorded, tmp_path, capsys):
    altered = tmp_path / "altered.h5"
    altered.write_bytes((recorded / "val.h5").read_bytes())
    with h5py.File(altered, "r+") as f:
        steps = f["steps"][...]
        steps["velocity_iterations"][np.flatnonzero(steps["point_count"] > 0)[0]] += 1
        f["steps"][...] = steps
    assert main(["lab", "surrogate", "--models", str(recorded / "models"), "--model", "g",
                 "--data", str(altered), "--sweeps", "0,4"]) == 2
    assert "do not repeat the file's recorded iterations" in capsys.readouterr().err


def test_a_grid_model_has_no_such_loss(recorded, capsys):
    from tests.server.conftest import write_conv_model

    write_conv_model(recorded / "models", "grid")
    assert main(["lab", "surrogate", "--models", str(recorded / "models"), "--model", "grid",
                 "--data", str(recorded / "val.h5")]) == 2
    assert "contact-graph" in capsys.readouterr().err
