"""bench.inprocess: a served model called in the simulation's process, without gRPC."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from bench.inprocess import InProcess
from server.serve import Server
from simclient.scene import SceneSpec
from simclient.simulate import connect, run_simulation
from simclient.warmstarts import make_provider
from simclient.worlds import WorldSpec

# The shipped cards: the default carries its admission along the stream, which the in-process
# run must keep as a stream does for the two to take one trajectory.
MODELS = Path(__file__).resolve().parents[2] / "models"
EXAMPLES = MODELS.parent / "examples"


def served_and_in_process(spec, seed: int) -> tuple[dict, dict]:
    """The default's run of (spec, seed) served by a real server on loopback, and called in process."""
    server = Server(models=MODELS).start()
    try:
        client = connect(server.address, "default", connect_timeout=10.0, allow_fallback=False)
        try:
            served = run_simulation(spec, seed, make_provider("server:default"), client=client, deadline_ms=1000)
        finally:
            client.close()
    finally:
        server.stop()
    return served, run_simulation(spec, seed, InProcess.load(MODELS, "default", spec))


def test_on_a_world_with_joints_the_in_process_run_answers_around_them_as_the_server_does():
    # The chain swings onto the heap: its links' points get Box2D's start extrapolated, the
    # heap's the zoo route, on both sides (server.joints on the wire's rows, in process on the
    # engine's own body indices).
    spec = WorldSpec(f"{EXAMPLES / 'chain.py'}:build", steps=90)
    served, in_process = served_and_in_process(spec, 901)
    assert served["summary"]["fallback_steps"] == 0
    for column in ("velocity_iterations", "contact_points"):  # (the solution's errors are NaN where joints hold points)
        assert in_process["per_step"][column] == served["per_step"][column], column


def test_the_default_called_in_process_takes_the_served_trajectory_step_for_step():
    spec = dataclasses.replace(SceneSpec.thesis(), steps=120)  # past the fall: a pile whose points persist
    server = Server(models=MODELS).start()
    try:
        client = connect(server.address, "default", connect_timeout=10.0, allow_fallback=False)
        try:
            served = run_simulation(spec, 901, make_provider("server:default"), client=client, deadline_ms=1000)
        finally:
            client.close()
    finally:
        server.stop()
    local = InProcess.load(MODELS, "default", spec)
    in_process = run_simulation(spec, 901, local)
    assert local.name == "in-process:" + local.predictor.name
    assert served["summary"]["fallback_steps"] == 0
    # The same warm start to the bit: the same errors against the solution and the same iterations.
    for column in ("velocity_iterations", "mse_normal", "mse_tangent", "contact_points"):
        assert in_process["per_step"][column] == served["per_step"][column], column
    assert in_process["summary"]["fallback_steps"] == 0
    assert all(lat is None for lat in in_process["per_step"]["latency_ms"])  # no round trip to time


def test_an_unknown_model_names_the_closest_ones_there():
    store = MODELS.parent / "lab" / "models"  # the research store: too many cards to list them all
    with pytest.raises(FileNotFoundError, match="no model 'defualt' among .*the closest: default"):
        InProcess.load(store, "defualt", SceneSpec.thesis())
