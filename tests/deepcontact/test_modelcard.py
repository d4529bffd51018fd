"""Model cards and alias cards (deepcontact.modelcard)."""

import json

import pytest

from deepcontact.gridspec import GridSpec
from deepcontact.modelcard import LIST_ALL_UP_TO, ModelCard, ModelCardError, unknown_model
from deepcontact.step_gate import FEATURES, StepGate


def _card(folder, name="residual-new-points"):
    card = ModelCard(name=name, kind="pressure", onnx_file="residual.onnx", gridspec=GridSpec.thesis(),
                     fixed_grid=False, combine="new-points")
    card.save(folder / f"{name}.json")
    return card


def test_an_alias_serves_the_card_it_names_under_its_own_name(tmp_path):
    target = _card(tmp_path)
    (tmp_path / "default.json").write_text(json.dumps(
        {"name": "default", "alias_of": "residual-new-points", "why": "best measured, docs/results.md"}))
    card = ModelCard.load(tmp_path / "default.json")
    assert card.name == "default"
    assert card.onnx_file == "residual.onnx" and card.combine == "new-points"
    assert card.gridspec == target.gridspec
    assert ModelCard.alias_target(tmp_path / "default.json") == "residual-new-points"
    assert ModelCard.alias_target(tmp_path / "residual-new-points.json") is None


def test_a_broken_alias_says_what_is_wrong(tmp_path):
    _card(tmp_path)
    (tmp_path / "default.json").write_text(json.dumps({"name": "default", "alias_of": "missing"}))
    with pytest.raises(ModelCardError, match="missing.json: no model card"):
        ModelCard.load(tmp_path / "default.json")
    (tmp_path / "second.json").write_text(json.dumps({"name": "second", "alias_of": "default"}))
    with pytest.raises(ModelCardError, match="itself an alias"):
        ModelCard.load(tmp_path / "second.json")
    (tmp_path / "odd.json").write_text(json.dumps({"name": "odd", "alias_of": "residual-new-points", "kind": "x"}))
    with pytest.raises(ModelCardError, match="alias card holds"):
        ModelCard.load(tmp_path / "odd.json")


def test_a_broken_card_in_a_folder_is_named_in_the_error(tmp_path):
    _card(tmp_path)
    (tmp_path / "broken.json").write_text(json.dumps({"name": "broken"}))
    with pytest.raises(ModelCardError, match=r"broken\.json: model card lacks \['fixed_grid', 'gridspec'"):
        ModelCard.load(tmp_path / "broken.json")
    assert ModelCard.load(tmp_path / "residual-new-points.json").name == "residual-new-points"


def _gate() -> dict:
    f = len(FEATURES)
    return StepGate((0.0,) * f, (1.0,) * f, (1.0,) + (0.0,) * f).to_dict()


def test_an_alias_may_serve_its_graph_model_gated_and_only_a_residual_graph_model(tmp_path):
    graph = ModelCard(name="graph", kind="graph", onnx_file="graph.onnx", gridspec=GridSpec.thesis(),
                      fixed_grid=False, combine="residual")
    graph.save(tmp_path / "graph.json")
    (tmp_path / "gated.json").write_text(json.dumps({"name": "gated", "alias_of": "graph", "step_gate": _gate()}))
    gated = ModelCard.load(tmp_path / "gated.json")
    assert gated.name == "gated" and gated.onnx_file == "graph.onnx" and gated.step_gate == _gate()
    assert ModelCard.load(tmp_path / "graph.json").step_gate is None  # the target itself is served plain
    _card(tmp_path)  # a grid model: its impulses are not a correction to gate
    (tmp_path / "grid-gated.json").write_text(json.dumps(
        {"name": "grid-gated", "alias_of": "residual-new-points", "step_gate": _gate()}))
    with pytest.raises(ModelCardError, match="only a graph model"):
        ModelCard.load(tmp_path / "grid-gated.json")
    (tmp_path / "bad.json").write_text(json.dumps({"name": "bad", "alias_of": "graph",
                                                   "step_gate": {**_gate(), "mean": [0.0]}}))
    with pytest.raises(ModelCardError, match="step_gate: a step gate holds"):
        ModelCard.load(tmp_path / "bad.json")


def test_an_alias_may_serve_a_graph_classifier_solved_on_its_labels_with_defaults_filled(tmp_path):
    graph = ModelCard(name="classifier", kind="graph", onnx_file="classifier.onnx", gridspec=GridSpec.thesis(),
                      fixed_grid=False, combine="residual")
    graph.save(tmp_path / "classifier.json")
    (tmp_path / "face.json").write_text(json.dumps({"name": "face", "alias_of": "classifier",
                                                    "face": {"pressing": 0.75, "rounds": 50}}))
    face = ModelCard.load(tmp_path / "face.json")
    assert face.face == {"pressing": 0.75, "share": 1.0, "rounds": 50, "label_friction": None, "max_residual": None,
                         "fallback": None, "damping": 0.0, "max_points": None, "solver": "gelsy", "retry_pressing": [],
                         "close": None, "relax": 1.0, "rho": 100.0, "against_builtin": False, "rescale": False,
                         "carry": False, "check_sweeps": None, "extrapolate_jointed": False, "check_stop": False,
                         "slide_in_bodies": True, "min_rounds": None, "revolute_joints": False, "by_island": False,
                         "restitution": True, "held_labels": False, "check_work": None, "held_from_builtin": False,
                         "repairs": 0, "repair_rounds": None}
    assert ModelCard.load(tmp_path / "classifier.json").face is None  # the classifier itself is served plain
    for bad, match in (({"pressing": -1}, "pressing >= 0"), ({"rounds": 0}, "rounds a whole number"),
                       ({"rounds": 2.5}, "rounds a whole number"), ({"labels": 1}, "keys among"),
                       ({"label_friction": 0}, "max_residual and close null or > 0"), ({"max_residual": -1}, "null or > 0"),
                       ({"close": 0}, "close null or > 0"), ({"retry_pressing": [0.9]}, "only with max_residual"),
                       ({"damping": -1e-10}, "damping >= 0"), ({"solver": "svd"}, "solver one of"),
                       ({"max_points": 0}, "max_points null or a whole number"),
                       ({"max_points": 150.5}, "max_points null or a whole number"),
                       ({"relax": 2.0}, "relax between 0 and 2"), ({"relax": 0}, "relax between 0 and 2"), ({"rho": 0}, "rho > 0"),
                       ({"against_builtin": 1}, "against_builtin, rescale, carry, extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"rescale": "yes"}, "against_builtin, rescale, carry, extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"carry": 1}, "rescale, carry, extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"extrapolate_jointed": "on"}, "carry, extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"slide_in_bodies": 0}, "extrapolate_jointed, slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"revolute_joints": "yes"}, "slide_in_bodies, revolute_joints, restitution and held_labels true or false"),
                       ({"restitution": 1}, "revolute_joints, restitution and held_labels true or false"),
                       ({"held_labels": "on"}, "restitution and held_labels true or false"),
                       ({"held_from_builtin": True}, "held_from_builtin true or false and only with held_labels"),
                       ({"held_from_builtin": 1, "held_labels": True}, "held_from_builtin true or false"),
                       ({"repairs": 2}, "repairs a whole number 0-8 and above 0 only with by_island"),
                       ({"repairs": 9, "by_island": True, "check_stop": True, "check_sweeps": 200},
                        "repairs a whole number 0-8"),
                       ({"repairs": True, "by_island": True, "check_stop": True, "check_sweeps": 200},
                        "repairs a whole number 0-8"),
                       ({"repair_rounds": 10}, "repair_rounds null or a whole number 1 to rounds and only with repairs"),
                       ({"repair_rounds": 60, "rounds": 50, "repairs": 3, "by_island": True, "check_stop": True,
                         "check_sweeps": 200}, "repair_rounds null or a whole number 1 to rounds"),
                       ({"repair_rounds": 0, "repairs": 3, "by_island": True, "check_stop": True,
                         "check_sweeps": 200}, "repair_rounds null or a whole number 1 to rounds"),
                       ({"check_sweeps": 0}, "check_sweeps null or a whole number 1-1000"),
                       ({"check_sweeps": 12.5}, "check_sweeps null or a whole number 1-1000"),
                       ({"check_stop": True}, "check_stop true or false and only with check_sweeps"),
                       ({"check_work": 40000}, "check_work null or a whole number >= 1 and only with check_sweeps"),
                       ({"check_work": 0.5, "check_sweeps": 200}, "check_work null or a whole number >= 1"),
                       ({"check_stop": 1, "check_sweeps": 12}, "check_stop true or false"),
                       ({"by_island": True, "check_sweeps": 12}, "by_island true or false and only with check_stop"),
                       ({"by_island": 1, "check_sweeps": 12, "check_stop": True}, "by_island true or false"),
                       ({"min_rounds": 0}, "min_rounds null or a whole number 1 to rounds"),
                       ({"min_rounds": 60, "rounds": 50}, "min_rounds null or a whole number 1 to rounds"),
                       ({"min_rounds": 2.5}, "min_rounds null or a whole number 1 to rounds"),
                       ({"fallback": 3, "max_residual": 0.3}, "fallback null or a card's name"), ("yes", "keys among")):
        (tmp_path / "bad.json").write_text(json.dumps({"name": "bad", "alias_of": "classifier", "face": bad}))
        with pytest.raises(ModelCardError, match=match):
            ModelCard.load(tmp_path / "bad.json")
    _card(tmp_path)  # a grid model: not read as labels
    (tmp_path / "grid-face.json").write_text(json.dumps(
        {"name": "grid-face", "alias_of": "residual-new-points", "face": {}}))
    with pytest.raises(ModelCardError, match="only a graph model"):
        ModelCard.load(tmp_path / "grid-face.json")


def test_an_unknown_model_is_told_with_every_name_when_there_are_few():
    assert unknown_model("nope", {"pressure", "default"}) == "no model 'nope'; there are default, pressure"
    assert unknown_model("nope", []) == "no model 'nope'; there is none"


def test_an_unknown_model_among_many_is_told_with_the_closest_names_only():
    known = [f"graph-variant-{i}" for i in range(LIST_ALL_UP_TO + 100)] + ["default", "pressure"]
    message = unknown_model("defualt", known)
    assert message.startswith(f"no model 'defualt' among {len(known)} (the closest: default")
    assert "graph-variant-50" not in message  # not the whole list
    assert "none is close" in unknown_model("zzzzzzzz", known)


def test_a_card_says_what_its_model_was_trained_on_and_measured_to_need(tmp_path):
    """trained_on is what training saw; measured, on an alias too, what the model is worth there.
    Only a measured gain (the whole interval below 1) makes the server vouch for a world."""
    import dataclasses

    from deepcontact.envelope import Envelope

    seen = Envelope(radius=(0.3, 0.55), friction=(0.2, 0.8))
    dataclasses.replace(_card(tmp_path), trained_on=seen.to_dict()).save(tmp_path / "residual-new-points.json")
    measured = {"ratio": 0.8, "interval": [0.75, 0.86], "command": "deepcontact bench iterations --seeds 850-899"}
    (tmp_path / "default.json").write_text(json.dumps(
        {"name": "default", "alias_of": "residual-new-points", "measured": measured}))
    card = ModelCard.load(tmp_path / "default.json")
    assert card.envelope == seen and card.measured == measured and card.wins_where_trained
    target = ModelCard.load(tmp_path / "residual-new-points.json")
    assert target.envelope == seen and target.measured is None and not target.wins_where_trained
    tie = {**measured, "interval": [0.9, 1.02], "ratio": 0.96}
    (tmp_path / "tie.json").write_text(json.dumps({"name": "tie", "alias_of": "residual-new-points", "measured": tie}))
    assert not ModelCard.load(tmp_path / "tie.json").wins_where_trained


def test_a_malformed_envelope_or_measurement_is_refused_in_one_line(tmp_path):
    card = _card(tmp_path).to_dict()
    for key, value, message in (("trained_on", {"radius": [0.6, 0.3]}, "trained_on"),
                                ("trained_on", {"flavour": "x"}, "trained_on"),
                                ("measured", {"ratio": 0.8}, "measured"),
                                ("measured", {"ratio": 1.2, "interval": [0.7, 0.9], "command": ""}, "measured")):
        with pytest.raises(ModelCardError, match=message):
            ModelCard.from_dict({**card, key: value})
