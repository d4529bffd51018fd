"""Shared fixtures: real patched engine, real worlds."""

from __future__ import annotations

import os

import pytest

# A command that meets what it did not expect prints one line (deepcontact.cli); in the
# tests it raises instead, so the test fails with the traceback.
os.environ.setdefault("DEEPCONTACT_DEBUG", "1")


@pytest.fixture(scope="session")
def thesis_spec():
    from simclient.scene import SceneSpec

    return SceneSpec.thesis()


def settled(spec, seed: int = 900, steps: int = 150, **solver):
    """A thesis world after `steps` builtin steps: the pile has formed."""
    from simclient.scene import settled_world

    return settled_world(spec, seed, steps, **solver)
