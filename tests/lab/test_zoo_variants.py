"""lab.zoo_variants: the shipped models with the zoo's variants beside them, all servable."""

from __future__ import annotations

from lab.zoo_variants import main
from server.predictors import load_models


def test_the_variants_folder_serves_the_shipped_models_and_each_variant(tmp_path):
    out = tmp_path / "variants"
    (out).mkdir()
    (out / "stale.json").write_text("{}")  # a folder already there is replaced
    assert main([str(out)]) == 0
    served = {p.name: p for p in load_models(out)}
    assert {"default", "zoo", "default-bf", "default-graph", "zoo-first", "zoo-bf", "zoo-always",
            "default-first", "zoo500", "default-zoo500"} <= set(served)
    assert not (out / "stale.json").exists() and not out.with_name("variants.part").exists()
    # The default falls back to the zoo route; the variant falls back to the graph network directly.
    assert served["default"].fallback.name == "zoo"
    assert served["default-graph"].fallback.name == "contact-graph"
    assert served["default-bf"].fallback is None
    assert served["zoo-always"].settings["max_residual"] is None
    assert served["zoo-r0.6"].settings["max_residual"] == 0.6
    assert served["default-r0.6"].settings["max_residual"] == 0.6
    assert served["default-r0.6"].fallback.name == "zoo-before"  # the zoo route as the variants' research had it
    # The zoo route's gate, rounds and check, each variant the shipped zoo route with only those changed,
    # and the default falling back to it.
    zoo = served["zoo-before"].settings  # the zoo route each variant changes (lab.zoo_variants.ZOO_FACE)
    assert served["zoo-ungated-r200"].settings == {**zoo, "max_residual": None, "rounds": 200}
    assert served["zoo-ungated-r200-unchecked"].settings == \
        {**zoo, "max_residual": None, "rounds": 200, "against_builtin": False, "check_sweeps": None}
    assert served["zoo-check200"].settings == {**zoo, "check_sweeps": 200}
    assert served["zoo-res10-r200-check200"].settings == {**zoo, "max_residual": 1.0, "rounds": 200, "check_sweeps": 200}
    longer = served["default-zoo-ungated-r200-check200"]
    assert longer.fallback.name == "zoo-ungated-r200-check200"
    assert longer.settings == {**served["default"].settings, "fallback": "zoo-ungated-r200-check200"}
    assert served["default-stop"].settings == {**served["default"].settings, "check_stop": True, "fallback": "zoo-before"}
    assert served["zoo-ungated-r100-check200-stop"].settings == \
        {**zoo, "max_residual": None, "rounds": 100, "check_sweeps": 200, "check_stop": True}


def test_the_zoo_classifier_trained_on_is_served_behind_the_routes_exactly_as_shipped(tmp_path):
    out = tmp_path / "variants"
    assert main([str(out)]) == 0
    served = {p.name: p for p in load_models(out)}
    zoo, candidate = served["zoo"], served["zoo-s7e6"]
    assert candidate.settings == zoo.settings  # the shipped zoo route's face, another network under it
    assert candidate.classifier.card.onnx_file == "s7e6-modes.onnx"
    assert zoo.classifier.card.onnx_file == "contact-modes-zoo.onnx"
    default = served["default-s7e6"]
    assert default.settings == {**served["default"].settings, "fallback": "zoo-s7e6"}
    assert default.fallback is candidate or default.fallback.name == "zoo-s7e6"
    assert served["zoo-s7e6-s9e6"].settings == zoo.settings  # its next six epochs, the same way
    assert served["zoo-s7e6-s9e6"].classifier.card.onnx_file == "s7e6-s9e6-modes.onnx"
    assert served["default-s7e6-s9e6"].settings == {**served["default"].settings, "fallback": "zoo-s7e6-s9e6"}
    # The shipped zoo route island by island and checking the step whole, each behind the default.
    assert served["zoo-island"].settings == {**zoo.settings, "by_island": True}
    assert served["zoo-whole"].settings == {**zoo.settings, "by_island": False, "repairs": 0}  # repairs need islands
    for tag in ("island", "whole"):
        assert served[f"default-{tag}"].settings == {**served["default"].settings, "fallback": f"zoo-{tag}"}
    # The default's own route checked by the sweeps to the stopping rule, its fallback as shipped.
    assert served["default-own-stop200"].settings == {**served["default"].settings, "check_stop": True,
                                                       "check_sweeps": 200}


def test_the_zoo_route_with_each_number_of_repairs_is_served_behind_the_default(tmp_path):
    out = tmp_path / "variants"
    assert main([str(out)]) == 0
    served = {p.name: p for p in load_models(out)}
    zoo = served["zoo"].settings
    assert zoo["repairs"] == 3  # shipped
    for k in (0, 1, 2, 3, 5, 8):
        assert served[f"zoo-repair{k}"].settings == {**zoo, "repairs": k, **({} if k else {"repair_rounds": None})}
        assert served[f"default-repair{k}"].settings == {**served["default"].settings, "fallback": f"zoo-repair{k}"}
    # Three repairs, each admitted in fewer rounds than the route's answer.
    for r in (10, 30, 100):
        assert served[f"zoo-repair3-rounds{r}"].settings == {**zoo, "repairs": 3, "repair_rounds": r}
        assert served[f"default-repair3-rounds{r}"].settings["fallback"] == f"zoo-repair3-rounds{r}"
    # The default's own route checked island by island, without and with repairs.
    own = {**served["default"].settings, "check_stop": True, "check_sweeps": 200, "by_island": True}
    assert served["default-own-repair0"].settings == {**own, "repairs": 0}
    assert served["default-own-repair3"].settings == {**own, "repairs": 3}
