"""Shared fixtures: real patched engine, real worlds."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def thesis_spec():
    from simclient.scene import SceneSpec

    return SceneSpec.thesis()


def settled(spec, seed: int = 900, steps: int = 150, **solver):
    """A thesis world after `steps` builtin steps: the pile has formed."""
    from simclient.scene import settled_world

    return settled_world(spec, seed, steps, **solver)
