"""`deepcontact export` (ONNX + model card) and `deepcontact evaluate` (ONNX Runtime, serving-side)."""

from __future__ import annotations

import argparse
import json
import shutil

import numpy as np
import onnx
import onnxruntime as ort
import pytest

from deepcontact.modelcard import ModelCard
from training import evaluate as evaluate_command
from training import export as export_command
from training import train as train_command

TINY_PRESSURE = json.dumps({"stem_filters": 4, "scales": 3, "branch_filters": [4], "head_filters": [4], "l2": 0.0001})
TINY_PEAK = json.dumps({"conv_filters": [2, 2, 4, 4], "merge_filters": 1, "dense_units": [8]})


def command(module, *argv) -> int:
    """`deepcontact <module's command> ARGV...` (built from the module, as the CLI does)."""
    parser = argparse.ArgumentParser()
    module.add_arguments(parser)
    return module.run(parser.parse_args([str(a) for a in argv]))


@pytest.fixture(scope="module")
def pressure_run(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "pressure"
    assert command(train_command, "--train", data / "train.h5", "--val", data / "val.h5", "--out", out,
                   "--config", TINY_PRESSURE, "--epochs", 2, "--batch-size", 8, "--quiet") == 0
    return out


def tf_model(run_dir):
    from training.models import build_model, config_from_dict

    model = build_model(config_from_dict(json.loads((run_dir / "run.json").read_text())["model"]))
    model.load_weights(run_dir / "best.weights.h5")
    return model


def test_export_writes_onnx_and_card_that_agree_with_tensorflow(pressure_run, tmp_path):
    onnx_path = tmp_path / "models" / "tiny.onnx"
    assert command(export_command, pressure_run, "--out", onnx_path) == 0
    card = ModelCard.load(onnx_path.with_suffix(".json"))
    assert card.onnx_file == "tiny.onnx" and card.kind == "pressure" and not card.fixed_grid
    assert set(card.gridspec.normalization) == {*card.gridspec.inputs, *card.gridspec.targets}
    assert card.parity_max_abs_error <= 1e-4
    assert card.training["train"][0]["seeds"] == "1-2" and card.training["val"][0]["seeds"] == "3"
    assert set(card.validation["contact"]) == {"impulse_normal", "impulse_tangent"}
    assert any(c.startswith("deepcontact train") for c in card.commands)
    assert card.commands[-1].startswith("deepcontact export")
    assert not list(onnx_path.parent.glob(".*part"))  # temporary files renamed away

    graph = onnx.load(onnx_path).graph
    dims = [[d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
            for v in (graph.input[0], graph.output[0])]
    assert dims == [["batch", "ny", "nx", 6], ["batch", "ny", "nx", 2]]

    # ONNX Runtime against TensorFlow on random input, at two grid sizes other than the card's.
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    model = tf_model(pressure_run)
    rng = np.random.default_rng(1)
    for shape in [(3, 61, 61, 6), (2, 24, 40, 6)]:
        x = rng.standard_normal(shape).astype(np.float32)
        got = session.run(["impulses"], {"grids": x})[0]
        assert got.shape == shape[:3] + (2,)
        assert np.abs(got - model(x, training=False).numpy()).max() <= 1e-4


def test_evaluate_with_onnx_runtime_matches_the_training_side_validation(pressure_run, data, tmp_path, capsys):
    onnx_path = tmp_path / "tiny.onnx"
    assert command(export_command, pressure_run, "--out", onnx_path) == 0
    result_path = tmp_path / "eval.json"
    assert command(evaluate_command, "--model", onnx_path, "--data", data / "val.h5", "--json", result_path) == 0
    result = json.loads(result_path.read_text())["models"][0]
    card = ModelCard.load(onnx_path.with_suffix(".json"))
    # Serving-side preprocessing (card + ONNX Runtime) scores the same steps as training did.
    assert result["data"]["steps"] == card.validation["steps"]
    assert result["grid_mse"] == pytest.approx(card.validation["grid_mse"], rel=1e-4)
    for name in ("impulse_normal", "impulse_tangent"):
        expected = card.validation["contact"][name]["mse"]
        assert result["contact"][name]["mse"] == pytest.approx(expected, rel=1e-4, abs=1e-9)
    assert set(result["baselines"]) == {"zero", "builtin", "grid_oracle"}
    assert "grid MSE" in capsys.readouterr().out


def test_peak_trains_at_reduced_width_and_exports_with_a_fixed_grid(data, tmp_path):
    run_dir = tmp_path / "peak"
    assert command(train_command, "--model", "peak", "--train", data / "train.h5", "--val", data / "val.h5",
                   "--out", run_dir, "--config", TINY_PEAK, "--epochs", 1, "--batch-size", 8, "--quiet") == 0
    onnx_path = tmp_path / "peak.onnx"
    assert command(export_command, run_dir, "--out", onnx_path) == 0
    card = ModelCard.load(onnx_path.with_suffix(".json"))
    assert card.kind == "peak" and card.fixed_grid and card.parity_max_abs_error <= 1e-4
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    assert session.get_inputs()[0].shape == ["batch", 61, 61, 6]
    x = np.random.default_rng(2).standard_normal((2, 61, 61, 6)).astype(np.float32)
    assert np.abs(session.run(None, {"grids": x})[0] - tf_model(run_dir)(x, training=False).numpy()).max() <= 1e-4


def test_export_refuses_a_run_without_a_finished_checkpoint(pressure_run, tmp_path, capsys):
    out = tmp_path / "m.onnx"
    (tmp_path / "empty").mkdir()
    assert command(export_command, tmp_path / "empty", "--out", out) == 2
    assert "no finished checkpoint" in capsys.readouterr().err
    # A run interrupted after epoch 1 of 3: state.json says it has not finished.
    unfinished = tmp_path / "unfinished"
    shutil.copytree(pressure_run, unfinished, ignore=shutil.ignore_patterns("cache"))
    state = json.loads((unfinished / "state.json").read_text())
    state.update(finished=False, stop_reason=None, epochs_done=1, history=state["history"][:1])
    (unfinished / "state.json").write_text(json.dumps(state))
    assert command(export_command, unfinished, "--out", out) == 2
    err = capsys.readouterr().err
    assert "has not finished (1 of 2 epochs done)" in err and "--resume" in err
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert command(export_command, tmp_path / "missing", "--out", out) == 2
    assert "no such run directory" in capsys.readouterr().err


def test_evaluate_refuses_a_model_without_its_card_or_data(pressure_run, data, tmp_path, capsys):
    onnx_path = tmp_path / "tiny.onnx"
    assert command(export_command, pressure_run, "--out", onnx_path) == 0
    assert command(evaluate_command, "--model", onnx_path, "--data", tmp_path / "none.h5") == 2
    assert "no such data file" in capsys.readouterr().err
    onnx_path.with_suffix(".json").unlink()
    assert command(evaluate_command, "--model", onnx_path, "--data", data / "val.h5") == 2
    assert "no model card" in capsys.readouterr().err


def test_errors_by_phase_scores_each_window_of_steps_and_skips_empty_ones():
    names = ("impulse_normal", "impulse_tangent")
    truth = np.zeros((4, 2))
    warm = {"zero": np.zeros((4, 2)), "model": np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 2.0]])}
    step = evaluate_command.PHASE_STEPS
    point_step = np.array([0, step - 1, 2 * step, 2 * step + 3])  # nothing in the second window
    phases = evaluate_command.errors_by_phase(warm, truth, point_step, names)
    assert list(phases) == [f"0-{step - 1}", f"{2 * step}-{3 * step - 1}"]
    early, late = phases[f"0-{step - 1}"], phases[f"{2 * step}-{3 * step - 1}"]
    assert early["points"] == late["points"] == 2
    assert early["model"]["impulse_normal"]["mse"] == 1.0 and late["model"]["impulse_normal"]["mse"] == 0.0
    assert late["model"]["impulse_tangent"]["mse"] == 2.0 and late["zero"]["impulse_tangent"]["mse"] == 0.0
