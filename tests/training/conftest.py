"""Shared fixtures for the training tests."""

from __future__ import annotations

import pytest

from commands import main


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Tiny recorded files: training seeds 1-2 and validation seed 3, 20 steps each, without
    and with (`-oracle`) the oracle's impulses."""
    d = tmp_path_factory.mktemp("data")
    for name, seeds in (("train", "1-2"), ("val", "3")):
        assert main(["generate", "--steps", "20", "--seeds", seeds, "--out", str(d / f"{name}.h5"), "--quiet"]) == 0
        assert main(["generate", "--steps", "20", "--seeds", seeds, "--oracle", "--out", str(d / f"{name}-oracle.h5"),
                     "--quiet"]) == 0
    return d


#: train-graph arguments for a network small enough to train in seconds
SMALL = ["--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse", "--quiet"]


@pytest.fixture(scope="module")
def small_graph(data, tmp_path_factory):
    """(folder, cache): a small graph model `small` trained on the recorded corrections,
    its weights in cache as small.weights.npz."""
    folder = tmp_path_factory.mktemp("graph")
    cache = folder / "cache"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
                 "--out", str(folder / "small.onnx"), "--cache", str(cache), *SMALL]) == 0
    return folder, cache
