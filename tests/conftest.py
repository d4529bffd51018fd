"""Shared fixtures: real patched engine, real worlds, a real model folder."""

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


@pytest.fixture(scope="session")
def model_dir(tmp_path_factory):
    """A model folder for real servers: `tiny` (any grid) and `tiny-fixed` (61x61 only)."""
    from tests.server.conftest import write_conv_model

    folder = tmp_path_factory.mktemp("models")
    write_conv_model(folder, "tiny")
    write_conv_model(folder, "tiny-fixed", fixed_grid=True)
    return folder


@pytest.fixture(scope="session")
def thesis_steps():
    """(world message, [(bodies, points)]) of a few settled thesis steps, with final impulses."""
    import numpy as np

    from deepcontact import wire
    from simclient.scene import SceneSpec, settled_world

    spec = SceneSpec.thesis()
    engine = settled_world(spec, 901, 150)
    steps = []
    for _ in range(5):
        engine.collide()
        bodies = engine.bodies()
        engine.solve()
        steps.append((bodies, engine.contacts()))
    return wire.encode_world(*spec.domain, spec.walls(), spec.physics), steps
