"""Simulations against a real server process that is restarted or slow."""

from __future__ import annotations

import dataclasses
import socket
import threading
import time

import numpy as np
import pytest

from deepcontact import wire
from server.predictors import RandomPredictor
from server.process import ServerProcess
from simclient.client import StepFailed, WarmStartClient
from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
from simclient.warmstarts import make_provider

DEADLINE_MS = 100.0
# A held step misses its deadline whatever the host's speed; the stream answers in order, so the
# next step waits for it, and the 50 ms between the hold and the deadline leave that one in time.
FAULT_DELAY_MS, FAULT_EVERY = 150, 3
# The restart test asserts which steps fell back, not how fast a step is: a deadline far past a
# tiny model's round trip keeps a busy host's hiccup from reading as a crash's fallback. A dead
# server fails a step at once (UNAVAILABLE, BACKING_OFF), so the long wait costs the test nothing.
RESTART_DEADLINE_MS = 1000.0


@pytest.fixture(scope="module")
def slow_server(model_dir):
    with ServerProcess(model_dir, "--fault-delay-ms", str(FAULT_DELAY_MS), "--fault-every", str(FAULT_EVERY)) as srv:
        yield srv


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_restarted_server_gets_its_learned_warm_starts_back(model_dir):
    bind = f"127.0.0.1:{_free_port()}"
    servers = [ServerProcess(model_dir, bind=bind).start()]
    spec = dataclasses.replace(SceneSpec.thesis(), steps=400)
    kill_at, down_s = 40, 1.0
    back_at: list[float] = []  # when the new server answered its health check

    def restart():
        time.sleep(down_s)
        servers.append(ServerProcess(model_dir, bind=bind).start())
        back_at.append(time.monotonic())

    restarter = threading.Thread(target=restart)

    def progress(k):
        if k == kill_at:
            servers[0].kill()  # SIGKILL, as a crash
            restarter.start()
        if k > kill_at:
            time.sleep(0.002)  # a simulation paced at a few hundred steps a second
        if k == spec.steps - 151:
            # The last 150 steps start a generous while (5x the backoff cap) after the new server is up.
            restarter.join(60)
            time.sleep(max(0.0, back_at[0] + 1.0 - time.monotonic()))

    try:
        with WarmStartClient(bind, backoff_s=(0.02, 0.2)) as client:
            result = run_simulation(spec, 903, make_provider("server:tiny"), client=client,
                                    deadline_ms=RESTART_DEADLINE_MS, progress=progress)
        restarter.join(60)
    finally:
        for srv in servers:
            srv.stop()
    per_step, summary = result["per_step"], result["summary"]
    fallback = np.array(per_step["fallback"])
    contacts = np.array(per_step["contact_points"]) > 0
    reasons = {k: per_step["fallback_reason"][k] for k in np.flatnonzero(fallback)}
    assert contacts[kill_at + 1] and not fallback[:kill_at + 1].any(), reasons
    assert fallback[kill_at + 1:].any()  # the crash cost fallbacks ...
    assert not fallback[-150:].any() and contacts[-150:].all(), reasons  # ... and the learned warm start came back
    assert summary["reconnects"] >= 1 and summary["reconnects"] == sum(per_step["reconnect"])
    assert sum(summary["fallbacks_by_reason"].values()) == summary["fallback_steps"] == fallback.sum()
    assert set(summary["fallbacks_by_reason"]) <= {"UNAVAILABLE", "BACKING_OFF", "DEADLINE_EXCEEDED",
                                                   "STREAM_ENDED", "CANCELLED"}
    # Backing off, reconnecting or not, no step waited much past its deadline.
    latency = np.array([x for x in per_step["latency_ms"] if x is not None])
    assert latency.max() < RESTART_DEADLINE_MS + 100


def test_steps_past_the_deadline_fall_back_and_are_counted(slow_server):
    spec = dataclasses.replace(SceneSpec.thesis(), steps=60)
    with WarmStartClient(slow_server.address) as client:
        result = run_simulation(spec, 904, make_provider("server:random"), client=client, deadline_ms=DEADLINE_MS)
    per_step, summary = result["per_step"], result["summary"]
    slow = [k for k, n in enumerate(per_step["contact_points"]) if n > 0 and k % FAULT_EVERY == 0]
    assert slow and all(per_step["fallback"][k] for k in slow)
    assert all(per_step["fallback_reason"][k] == "DEADLINE_EXCEEDED" for k in slow)
    served = [k for k, n in enumerate(per_step["contact_points"]) if n > 0 and not per_step["fallback"][k]]
    assert served and all(k % FAULT_EVERY for k in served)
    assert summary["fallbacks_by_reason"].get("DEADLINE_EXCEEDED", 0) == summary["fallback_steps"] >= len(slow)
    assert all(per_step["latency_ms"][k] < DEADLINE_MS + 100 for k in slow)


def test_a_late_reply_is_never_applied_to_a_later_step(slow_server, thesis_steps):
    world, steps = thesis_steps
    bodies, points = steps[0]
    expected = {k: RandomPredictor(seed=0).predict(None, points, None, k).impulses for k in (4, 5)}
    with WarmStartClient(slow_server.address, world=world) as client:
        with pytest.raises(StepFailed) as failed:
            client.step(wire.encode_step(3, "random", bodies, points), timeout=DEADLINE_MS / 1e3)  # held 150 ms
        assert failed.value.reason == "DEADLINE_EXCEEDED"
        for k in (4, 5):
            reply = client.step(wire.encode_step(k, "random", bodies, points), timeout=5.0)
            assert reply.step == k
            np.testing.assert_array_equal(np.stack(wire.decode_impulses(reply), 1), expected[k])
            time.sleep(FAULT_DELAY_MS / 1e3)  # step 3's reply would be due now
