"""Shared fixtures for the training tests."""

from __future__ import annotations

import pytest

from deepcontact.cli import main


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
