"""`deepcontact lab step-gate`: a per-step gate between a model's warm start and Box2D's,
fitted on some seeds' steps and priced on others', on the model's own states."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np


from commands import main
from deepcontact.modelcard import ModelCard
from lab.step_gate import RACE_SWEEPS, HiddenTap, raced
from deepcontact.step_gate import FEATURES

SHIPPED = Path(__file__).parents[2] / "models"




def _graph_model() -> str:
    """The shipped graph model that answers impulses: the end of the default's chain of face
    routes (a face card is not what a gate serves), else the default's target."""
    name = "default"
    while (face := ModelCard.load(SHIPPED / f"{name}.json").face) is not None and face.get("fallback"):
        name = face["fallback"]
    return ModelCard.alias_target(SHIPPED / f"{name}.json") or name


GRAPH = _graph_model()


def _shipped_default(tmp_path: Path) -> Path:
    """A models folder holding the shipped graph model's card and ONNX and an alias of it, default."""
    models = tmp_path / "models"
    models.mkdir()
    for name in (f"{GRAPH}.json", f"{GRAPH}.onnx"):
        shutil.copy(SHIPPED / name, models)
    (models / "default.json").write_text(json.dumps({"name": "default", "alias_of": GRAPH}))
    return models


def test_the_command_prices_the_gate_between_the_model_and_the_perfect_choice(tmp_path):
    out, models = tmp_path / "gate.json", _shipped_default(tmp_path)
    target = GRAPH
    assert main(["lab", "step-gate", "--models", str(models), "--fit-seeds", "800-801", "--seeds", "850",
                 "--steps", "40", "--workers", "1", "--json", str(out), "--save-card", "default-gated"]) == 0
    report = json.loads(out.read_text())
    assert report["features"] == list(FEATURES) and len(report["gate"]["coefficients"]) == len(FEATURES) + 1
    rows = report["rows"]
    assert set(rows) == {"builtin", "default", "default gated", "perfect choice",
                         *(f"raced {k} sweeps" for k in RACE_SWEEPS)}
    perfect = rows["perfect choice"]["mean_iterations"]
    # the gate serves one of the two at every step, so it can do no better than the perfect choice
    # and no worse than the worse of the two at every step; a race also pays for the loser's sweeps
    assert perfect <= rows["default gated"]["mean_iterations"]
    assert all(perfect <= rows[f"raced {k} sweeps"]["mean_iterations"] for k in RACE_SWEEPS)
    assert perfect <= min(rows["builtin"]["mean_iterations"], rows["default"]["mean_iterations"])
    assert rows["builtin"]["value"] == 1.0
    assert 0.0 <= report["model_served_share"] <= 1.0 and report["priced_steps"] > 0
    assert report["gated_to_model"]["value"] > 0
    assert len(report["feature_correlations"]) == len(FEATURES)
    assert all(-1 <= c <= 1 for c in report["feature_correlations"])
    # the saved card serves the default's target with the fitted gate
    card = ModelCard.load(models / "default-gated.json")
    assert card.name == "default-gated" and card.onnx_file == f"{target}.onnx"
    assert card.step_gate == report["gate"]


def test_fitting_and_pricing_on_the_same_seeds_is_refused(capsys):
    assert main(["lab", "step-gate", "--fit-seeds", "800-801", "--seeds", "801-802", "--steps", "20"]) == 2
    assert "overlap" in capsys.readouterr().err


def test_a_gate_fitted_on_two_worlds_counts_each_worlds_steps_and_names_them_in_its_card(tmp_path):
    out, models = tmp_path / "gate.json", _shipped_default(tmp_path)
    family = "--radius 0.3 0.55 --friction 0.2 0.8 --steps 40"
    assert main(["lab", "step-gate", "--models", str(models), "--fit-seeds", "800", "--seeds", "850",
                 "--steps", "40", "--workers", "1", "--fit-also", family, "--json", str(out),
                 "--save-card", "pooled"]) == 0
    report = json.loads(out.read_text())
    assert report["fit_also"] == [family]
    per_world = report["fit_steps_per_world"]
    assert [w["world"] for w in per_world] == ["thesis-custom", family] and all(w["steps"] > 0 for w in per_world)
    assert sum(w["steps"] for w in per_world) == report["fit_steps"]
    assert family in json.loads((models / "pooled.json").read_text())["why"]


def test_a_fit_world_that_is_not_scene_flags_is_refused_before_anything_runs(capsys):
    assert main(["lab", "step-gate", "--fit-also", "--radius 0.3", "--steps", "20"]) == 2
    assert "--radius" in capsys.readouterr().err
    assert main(["lab", "step-gate", "--fit-also", "--bogus 3", "--steps", "20"]) == 2
    assert "unrecognized" in capsys.readouterr().err


def test_a_gate_on_the_networks_inner_state_is_priced_beside_the_plain_one(tmp_path):
    out, models = tmp_path / "gate.json", _shipped_default(tmp_path)
    tensor = "add_49:0"  # the shipped graph network's last point states, a row a point
    assert main(["lab", "step-gate", "--models", str(models), "--fit-seeds", "800-801", "--seeds", "850",
                 "--steps", "40", "--workers", "1", "--hidden", tensor, "--json", str(out)]) == 0
    report = json.loads(out.read_text())
    rows = report["rows"]
    inner, in_sample = "default gated on its inner state too", "default gated on its inner state too, fitted on these steps (in sample)"
    assert {"default gated", inner, in_sample} <= set(rows)
    assert all(rows["perfect choice"]["mean_iterations"] <= rows[name]["mean_iterations"] for name in (inner, in_sample))
    names = report["hidden_gate"]["features"]
    assert names[:len(FEATURES)] == list(FEATURES) and names[len(FEATURES)] == f"{tensor} mean[0]"
    assert len(names) > len(FEATURES) and report["hidden"] == [tensor]
    assert report["hidden_gate_to_gate"]["value"] > 0


def test_the_tap_hands_the_network_its_answer_and_keeps_the_pooled_state():
    from server.predictors import load_model

    predictor = load_model(SHIPPED / f"{GRAPH}.json")
    rng = np.random.default_rng(0)
    feed = (rng.normal(size=(5, len(predictor.inputs))).astype(np.float32),
            np.array([[0, 1], [1, 2], [2, 0], [0, 3], [3, 1]], np.int32), np.ones((4, 1), np.float32))
    plain = predictor.run_session(*feed)
    tap = HiddenTap(predictor, SHIPPED / f"{GRAPH}.onnx",
                    ["add_49:0"])
    assert predictor.infer == tap.infer and np.array_equal(predictor.infer(*feed), plain)
    width = tap.widths[0]
    assert tap.last.shape == (2 * width,) and len(tap.names()) == 2 * width
    assert np.all(tap.last[width:] >= tap.last[:width])  # each column's max over the rows is at least its mean


def test_a_tensor_the_model_does_not_hold_and_a_card_for_a_screens_gate_are_refused(tmp_path, capsys):
    models = _shipped_default(tmp_path)
    assert main(["lab", "step-gate", "--models", str(models), "--steps", "20", "--hidden", "no/such:0"]) == 2
    err = capsys.readouterr().err
    assert "no/such:0" in err and "add_49:0" in err  # it names some tensors that are there
    assert main(["lab", "step-gate", "--models", str(models), "--steps", "20", "--hidden", "add_49:0",
                 "--save-card", "x"]) == 2
    assert "--save-card with --hidden" in capsys.readouterr().err


def test_a_race_goes_on_from_the_smaller_residual_and_pays_the_losers_sweeps():
    iterations = np.array([[100, 80], [100, 80], [5, 2]], float)  # builtin's, the model's
    residuals = np.zeros((3, 2, len(RACE_SWEEPS)))
    residuals[0, :, 0] = [2.0, 1.0]  # the model's first sweep changes less: it goes on
    residuals[1, :, 0] = [1.0, 2.0]  # Box2D's does: it goes on, though the model would have won
    residuals[2, :, 0] = [0.5, 0.1]
    assert raced(iterations, residuals, 1).tolist() == [81, 101, 3]
    # within 8 sweeps the model's start converges (at 2): the race ends there, both ran 2 sweeps
    assert raced(iterations, residuals, 8)[2] == 2 + 2
