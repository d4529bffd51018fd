"""Recording on a card what its model was measured to need (training.measure)."""

from __future__ import annotations

import json

import pytest

from deepcontact.gridspec import GridSpec
from deepcontact.modelcard import ModelCard
from training.measure import MeasureError, main, measured_from

SUMMARY = {"guard": False, "seeds": list(range(850, 900)),
           "command": "deepcontact bench iterations --seeds 850-899 --warm-starts builtin,server:default "
                      "--no-guard --out /tmp/x --quiet --server unix:/tmp/s.sock",
           "ratios_to_builtin": {"server:default": {"mean": {"value": 0.8166, "low": 0.7764, "high": 0.858}}}}


def test_a_run_without_the_guard_on_choosing_seeds_is_written_into_the_card(tmp_path):
    ModelCard(name="net", kind="graph", onnx_file="net.onnx", gridspec=GridSpec.thesis(),
              fixed_grid=False).save(tmp_path / "net.json")
    (tmp_path / "default.json").write_text(json.dumps({"name": "default", "alias_of": "net"}))
    (tmp_path / "summary.json").write_text(json.dumps(SUMMARY))
    assert main([str(tmp_path / "default.json"), str(tmp_path / "summary.json")]) == 0
    card = ModelCard.load(tmp_path / "default.json")
    assert card.measured == {"ratio": 0.817, "interval": [0.776, 0.858], "command":
                             "deepcontact bench iterations --seeds 850-899 --warm-starts builtin,server:default "
                             "--no-guard --out OUT"}
    assert card.wins_where_trained


@pytest.mark.parametrize("change, message", [({"guard": True}, "with the guard"),
                                             ({"seeds": [901, 902]}, "choosing seeds"),
                                             ({"ratios_to_builtin": {}}, "no ratio")])
def test_a_run_that_cannot_vouch_for_a_model_is_refused(change, message):
    with pytest.raises(MeasureError, match=message):
        measured_from({**SUMMARY, **change}, "default")
