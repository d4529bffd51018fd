"""lab.classifier_variants: the shipped default served on classifiers of fewer rounds, all servable."""

from __future__ import annotations

from lab.classifier_variants import ROUND_VARIANTS, main
from server.predictors import load_models


def test_each_variant_is_the_shipped_default_on_a_classifier_of_fewer_rounds(tmp_path):
    out = tmp_path / "variants"
    assert main([str(out)]) == 0
    served = {p.name: p for p in load_models(out)}
    default = served["default"]
    shipped_rounds = default.classifier.card.architecture["config"]["rounds"]
    for _, tag in ROUND_VARIANTS:
        variant = served[f"default-{tag}"]
        assert variant.settings == default.settings  # the shipped face, fallback included
        assert variant.fallback.name == default.fallback.name == "zoo"
        assert variant.classifier.card.onnx_file == f"{tag}-modes.onnx"
        assert variant.classifier.card.architecture["config"]["rounds"] < shipped_rounds
        # The same inputs as the shipped classifier: each point's friction read after the standard channels.
        assert variant.classifier.card.gridspec.inputs == default.classifier.card.gridspec.inputs
