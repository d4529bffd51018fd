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

# The shipped cards: the default carries its admission along the stream, which the in-process
# run must keep as a stream does for the two to take one trajectory.
MODELS = Path(__file__).resolve().parents[2] / "models"


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
