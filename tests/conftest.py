"""Shared fixtures: real patched engine, real worlds."""

from __future__ import annotations

import dataclasses

import pytest


@pytest.fixture(scope="session")
def thesis_spec():
    from simclient.scene import SceneSpec

    return SceneSpec.thesis()


def settled(spec, seed: int = 900, steps: int = 150, **solver):
    """A thesis world after `steps` builtin steps: the pile has formed."""
    from simclient.scene import build_world

    if solver:
        spec = dataclasses.replace(spec, solver=dataclasses.replace(spec.solver, **solver))
    engine = build_world(spec, seed)
    for _ in range(steps):
        engine.step()
    return engine
