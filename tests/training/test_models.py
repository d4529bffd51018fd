"""The Keras models of thesis §7: Pressure (any grid) and Peak (fixed grid), built from configs."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from training.models import (
    PeakConfig,
    PressureConfig,
    build_model,
    config_from_dict,
    config_to_dict,
    count_parameters,
    default_config,
)

SMALL_PEAK = {"grid_shape": [16, 16], "conv_filters": [4, 4, 8, 8], "merge_filters": 2, "dense_units": [32]}


def test_pressure_accepts_any_grid_size():
    model = build_model(default_config("pressure"))
    rng = np.random.default_rng(0)
    for shape in [(2, 61, 61, 6), (1, 20, 33, 6)]:
        out = model(rng.standard_normal(shape).astype(np.float32), training=False)
        assert out.shape == shape[:3] + (2,)
    assert model.input_shape == (None, None, None, 6)


def test_unet_accepts_any_grid_size_and_keeps_full_resolution_through_its_skips():
    model = build_model(default_config("unet", in_channels=9, widths=[8, 16, 32]))
    rng = np.random.default_rng(0)
    for shape in [(2, 61, 61, 9), (1, 41, 101, 9), (1, 7, 5, 9)]:
        out = model(rng.standard_normal(shape).astype(np.float32), training=False)
        assert out.shape == shape[:3] + (2,)
    names = [layer.name for layer in model.layers]
    assert {"skip0", "skip1", "up0", "up1"} <= set(names) and "pool2" in names


def test_default_pressure_is_small_and_follows_the_thesis():
    model = build_model(PressureConfig())
    params = count_parameters(model)
    assert 3_000 <= params["trainable"] <= 50_000
    kinds = {type(layer).__name__ for layer in model.layers}
    assert {"Conv2D", "BatchNormalization", "AveragePooling2D", "Add"} <= kinds
    assert "Dropout" not in kinds  # §7.2: no dropout in Pressure
    convs = [layer for layer in model.layers if type(layer).__name__ == "Conv2D"]
    assert all(float(c.kernel_regularizer.l2) == pytest.approx(0.01) for c in convs)
    assert [c.kernel_size for c in convs][0] == (4, 4) and convs[-1].kernel_size == (1, 1)
    assert convs[-1].name == "impulses" and convs[-1].use_bias  # linear output, no batch norm after it
    # normal(0, 0.1) initialization
    w = np.concatenate([c.kernel.numpy().ravel() for c in convs])
    assert abs(w.std() - 0.1) < 0.01 and abs(w.mean()) < 0.01


def test_peak_builds_at_reduced_width_with_a_fixed_grid():
    config = default_config("peak", **SMALL_PEAK)
    model = build_model(config)
    assert config.fixed_grid and model.input_shape == (None, 16, 16, 6)
    out = model(np.zeros((3, 16, 16, 6), np.float32), training=False)
    assert out.shape == (3, 16, 16, 2)
    names = [layer.name for layer in model.layers]
    assert sum(type(layer).__name__ == "Dropout" for layer in model.layers) == 2  # before each dense layer
    assert "flatten" in names and [n for n in names if n.startswith("merge") and n.endswith("_up")] == [
        "merge2_up", "merge3_up", "merge4_up"]  # the pooled scales are resized back
    with pytest.raises(ValueError):
        model(np.zeros((1, 20, 20, 6), np.float32))


def test_the_default_peak_has_the_thesis_tens_of_millions_of_weights_in_its_config():
    # Not built here (70 MB of weights); the count follows from the config.
    c = PeakConfig()
    ny, nx = c.grid_shape
    dense = ny * nx * c.merge_filters * c.dense_units[0] + c.dense_units[0] * c.dense_units[1] \
        + c.dense_units[1] * ny * nx * c.out_channels
    assert dense > 10_000_000


def test_configs_round_trip_through_json_and_reject_unknown_fields():
    for config in (PressureConfig(branch_filters=(8, 16)), default_config("peak", **SMALL_PEAK)):
        again = config_from_dict(json.loads(json.dumps(config_to_dict(config))))
        assert again == config
    with pytest.raises(ValueError, match="unknown keys"):
        config_from_dict({"kind": "pressure", "filters": 3})
    with pytest.raises(ValueError, match="positive integers"):
        default_config("pressure", branch_filters=[0])
    with pytest.raises(ValueError, match="unknown model kind"):
        default_config("resnet")


def test_configs_and_evaluation_import_without_tensorflow():
    code = ("import sys, training.models, training.grids, training.evaluate, training.export; "
            "assert 'tensorflow' not in sys.modules, 'tensorflow imported'")
    subprocess.run([sys.executable, "-c", code], check=True)
