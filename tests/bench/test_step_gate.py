"""`deepcontact bench step-gate`: a per-step gate between a model's warm start and Box2D's,
fitted on some seeds' steps and priced on others', on the model's own states."""

from __future__ import annotations

import json

import numpy as np

from bench.step_gate import FEATURES, fit_gate, gate_serves_model
from deepcontact.cli import main


def test_the_gate_learns_which_side_of_a_feature_the_model_wins_on():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, 3))
    model_wins = (x[:, 1] > 0.2).astype(float)
    gate = fit_gate(x, model_wins, weight=np.ones(len(x)))
    served = gate_serves_model(x, gate)
    assert np.mean(served == model_wins.astype(bool)) > 0.95
    assert np.argmax(np.abs(gate[2][1:])) == 1  # the deciding feature carries the weight


def test_a_step_that_costs_nothing_either_way_does_not_move_the_gate():
    x = np.array([[0.0], [1.0], [2.0], [3.0]])
    wins = np.array([0.0, 0.0, 1.0, 1.0])
    plain = fit_gate(x, wins, weight=np.ones(4))
    # a contradicting step worth (almost) nothing leaves the fit where it was
    padded = fit_gate(np.vstack([x, [[3.0]]]), np.append(wins, 0.0), weight=np.append(np.ones(4), 1e-9))
    assert np.array_equal(gate_serves_model(x, plain), gate_serves_model(x, padded))


def test_the_command_prices_the_gate_between_the_model_and_the_perfect_choice(tmp_path):
    out = tmp_path / "gate.json"
    assert main(["bench", "step-gate", "--fit-seeds", "800-801", "--seeds", "850", "--steps", "40",
                 "--workers", "1", "--json", str(out)]) == 0
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


def test_fitting_and_pricing_on_the_same_seeds_is_refused(capsys):
    assert main(["bench", "step-gate", "--fit-seeds", "800-801", "--seeds", "801-802", "--steps", "20"]) == 2
    assert "overlap" in capsys.readouterr().err
