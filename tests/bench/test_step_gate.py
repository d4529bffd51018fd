"""`deepcontact bench step-gate`: a per-step gate between a model's warm start and Box2D's,
fitted on some seeds' steps and priced on others', on the model's own states."""

from __future__ import annotations

import json
import shutil
from pathlib import Path


from deepcontact.cli import main
from deepcontact.modelcard import ModelCard
from deepcontact.step_gate import FEATURES

SHIPPED = Path(__file__).parents[2] / "models"


def test_the_command_prices_the_gate_between_the_model_and_the_perfect_choice(tmp_path):
    out = tmp_path / "gate.json"
    models = tmp_path / "models"
    models.mkdir()
    target = ModelCard.alias_target(SHIPPED / "default.json")
    for name in ("default.json", f"{target}.json", f"{target}.onnx"):
        shutil.copy(SHIPPED / name, models)
    assert main(["bench", "step-gate", "--models", str(models), "--fit-seeds", "800-801", "--seeds", "850",
                 "--steps", "40", "--workers", "1", "--json", str(out), "--save-card", "default-gated"]) == 0
    report = json.loads(out.read_text())
    assert report["features"] == list(FEATURES) and len(report["gate"]["coefficients"]) == len(FEATURES) + 1
    rows = report["rows"]
    assert set(rows) == {"builtin", "default", "default gated", "perfect choice"}
    perfect = rows["perfect choice"]["mean_iterations"]
    # the gate serves one of the two at every step, so it can do no better than the perfect choice
    # and no worse than the worse of the two at every step
    assert perfect <= rows["default gated"]["mean_iterations"]
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
    assert main(["bench", "step-gate", "--fit-seeds", "800-801", "--seeds", "801-802", "--steps", "20"]) == 2
    assert "overlap" in capsys.readouterr().err
