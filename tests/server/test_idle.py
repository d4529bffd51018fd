"""Streams that go quiet are ended by the server, and the client carries on (server.idle)."""

from __future__ import annotations

import contextlib
import time

import grpc
import pytest

from deepcontact import wire
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.serve import Server
from simclient.client import WarmStartClient

IDLE_S = 0.5


def wait_for(condition, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return False


@contextlib.contextmanager
def serving(model_dir, **options):
    server = Server(models=model_dir, **options).start()
    try:
        yield server
    finally:
        server.stop()


def step(client: WarmStartClient, k: int, bodies, points):
    return client.step(wire.encode_step(k, "zero", bodies, points), timeout=5.0)


def test_a_silent_stream_is_ended_and_its_slot_goes_to_the_next_client(model_dir, thesis_steps):
    world, steps = thesis_steps
    with serving(model_dir, max_concurrent=1, stream_idle_s=IDLE_S) as server, \
            WarmStartClient(server.address, world=world) as quiet, grpc.insecure_channel(server.address) as channel:
        step(quiet, 0, *steps[0])  # opens a stream, then sends nothing more
        other = pb_grpc.WarmStartStub(channel)
        request = wire.encode_step(1, "zero", *steps[0], world=world)
        with pytest.raises(grpc.RpcError) as err:
            other.Predict(request, timeout=5)
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED  # the quiet stream holds the only slot

        assert wait_for(lambda: server.idle.ended == 1)
        assert wait_for(lambda: len(server.idle) == 0)
        reply = other.Predict(request, timeout=5)
        assert reply.step == 1


def test_the_client_reopens_a_stream_the_server_ended_without_failing_a_step(model_dir, thesis_steps):
    world, steps = thesis_steps
    with serving(model_dir, stream_idle_s=IDLE_S) as server, WarmStartClient(server.address, world=world) as client:
        step(client, 0, *steps[0])
        assert wait_for(lambda: server.idle.ended == 1)  # a simulation paused past the limit
        for k, (bodies, points) in enumerate(steps[1:], start=1):
            assert step(client, k, bodies, points).step == k  # no StepFailed: nothing falls back
        assert client.reconnects == 1


def test_a_stream_that_keeps_sending_is_left_open(model_dir, thesis_steps):
    world, steps = thesis_steps
    with serving(model_dir, stream_idle_s=2.0) as server, WarmStartClient(server.address, world=world) as client:
        for k in range(60):  # three seconds of steps, 50 ms apart: longer than the limit, never idle past it
            bodies, points = steps[k % len(steps)]
            step(client, k, bodies, points)
            time.sleep(0.05)
        assert server.idle.ended == 0 and client.reconnects == 0


def test_a_server_without_the_limit_keeps_silent_streams(model_dir, thesis_steps):
    world, steps = thesis_steps
    with serving(model_dir, stream_idle_s=0) as server, WarmStartClient(server.address, world=world) as client:
        step(client, 0, *steps[0])
        time.sleep(4 * IDLE_S)
        assert server.idle is None
        assert step(client, 1, *steps[1]).step == 1 and client.reconnects == 0
