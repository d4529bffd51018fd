"""The per-step gate (deepcontact.step_gate): its features, its fit and its card form."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.step_gate import FEATURES, StepGate, step_features


def test_the_gate_learns_which_side_of_a_feature_the_model_wins_on():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(400, len(FEATURES)))
    model_won = (x[:, 1] > 0.2).astype(float)
    gate = StepGate.fit(x, model_won, weight=np.ones(len(x)))
    assert np.mean(gate.serves_model(x) == model_won.astype(bool)) > 0.95
    assert np.argmax(np.abs(gate.coefficients[1:])) == 1  # the deciding feature carries the weight


def test_a_step_that_costs_nothing_either_way_does_not_move_the_gate():
    x = np.repeat(np.arange(4.0)[:, None], len(FEATURES), axis=1)
    won = np.array([0.0, 0.0, 1.0, 1.0])
    plain = StepGate.fit(x, won, weight=np.ones(4))
    # a contradicting step worth (almost) nothing leaves the fit where it was
    padded = StepGate.fit(np.vstack([x, x[3:]]), np.append(won, 0.0), weight=np.append(np.ones(4), 1e-9))
    assert np.array_equal(plain.serves_model(x), padded.serves_model(x))


def test_a_gate_goes_through_its_card_form_unchanged_and_refuses_other_features():
    gate = StepGate.fit(np.random.default_rng(1).normal(size=(50, len(FEATURES))), np.tile([0.0, 1.0], 25), np.ones(50))
    assert StepGate.from_dict(gate.to_dict()) == gate
    with pytest.raises(ValueError, match="other features"):
        StepGate.from_dict({**gate.to_dict(), "features": list(FEATURES[:-1])})
    with pytest.raises(ValueError, match="coefficients"):
        StepGate(gate.mean, gate.scale, gate.coefficients[:-1])
    with pytest.raises(ValueError, match="finite"):
        StepGate(gate.mean, (0.0,) + gate.scale[1:], gate.coefficients)


def test_a_gate_fitted_on_more_features_names_them_and_no_card_serves_it():
    names = FEATURES + ("inner state mean[0]",)
    x = np.random.default_rng(2).normal(size=(60, len(names)))
    gate = StepGate.fit(x, (x[:, -1] > 0).astype(float), np.ones(60), names=names)
    assert gate.to_dict()["features"] == list(names) and gate.serves_model(x).shape == (60,)
    with pytest.raises(ValueError, match="other features"):  # a server computes FEATURES only
        StepGate.from_dict(gate.to_dict())


def test_a_step_served_box2ds_own_warm_start_has_no_correction(thesis_steps):
    _world, steps = thesis_steps
    bodies, points = steps[0]
    same = step_features(bodies, points, points["builtin"].astype(np.float64))
    moved = step_features(bodies, points, points["builtin"] + np.array([0.5, 0.0]))
    assert same.shape == moved.shape == (len(FEATURES),) and np.all(np.isfinite(moved))
    at = {name: k for k, name in enumerate(FEATURES)}
    assert same[at["|correction| / |builtin|"]] == 0 and same[at["share of points corrected > 0.1 N s"]] == 0
    assert moved[at["share of points corrected > 0.1 N s"]] == 1 and moved[at["share corrected > 1 N s"]] == 0
    # the step's bodies and points, not the answer, give the rest
    rest = [at["log points"], at["share of new points"], at["log mean body speed (m/s)"], at["mean penetration (m)"]]
    assert np.array_equal(same[rest], moved[rest])


def test_the_features_are_their_plain_definitions(thesis_steps):
    _world, steps = thesis_steps
    bodies, points = steps[2]
    rng = np.random.default_rng(3)
    answer = points["builtin"] + rng.normal(0, 0.3, (len(points), 2))
    b = points["builtin"].astype(np.float64)
    nd, nb = np.linalg.norm(answer - b, axis=1), np.linalg.norm(b, axis=1)
    dyn = bodies[bodies["type"] == 2]
    speed, spin = np.linalg.norm(dyn["velocity"], axis=1), np.abs(dyn["angular_velocity"])
    plain = [np.log(len(points)), np.mean(nb == 0), np.log(np.sqrt(np.mean(nb ** 2)) + 1e-6),
             np.log(np.sqrt(np.mean(nd ** 2)) + 1e-6), np.linalg.norm(nd) / np.sqrt(np.sum(nb ** 2) + 1e-6),
             np.mean(nd > 0.1), np.mean(nd > 1), np.log(nd.max() + 1e-6), np.mean(answer[:, 0] <= 0),
             np.mean(np.sign(answer[:, 1]) * np.sign(b[:, 1]) < 0),
             np.log(speed.mean() + 1e-6), np.log(speed.max() + 1e-6), np.mean(speed > 0.1),
             np.log(spin.mean() + 1e-6), np.mean(np.maximum(-points["separation"], 0))]
    np.testing.assert_allclose(step_features(bodies, points, answer), plain, rtol=1e-5, atol=1e-7)
