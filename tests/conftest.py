"""Shared fixtures: real patched engine, real worlds, a real local Ray."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys

import pytest

# Ray reads these when it is first imported, so they are set before any test runs: the
# session's local Rays (the one below and those the commands start) and the commands
# connecting to them share one token (Ray's token authentication) kept in the
# environment rather than in ~/.ray, and report no usage statistics.
os.environ.setdefault("RAY_AUTH_MODE", "token")
os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"


@pytest.fixture(scope="session")
def thesis_spec():
    from simclient.scene import SceneSpec

    return SceneSpec.thesis()


def settled(spec, seed: int = 900, steps: int = 150, **solver):
    """A thesis world after `steps` builtin steps: the pile has formed."""
    from simclient.scene import settled_world

    return settled_world(spec, seed, steps, **solver)


_RAY_HEAD = """
import logging, sys
import ray
info = ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
                logging_level=logging.ERROR)
print(info.address_info["gcs_address"], flush=True)
sys.stdin.read()  # until the test session closes our stdin
ray.shutdown()
"""


@pytest.fixture(scope="session")
def ray_cluster():
    """The address of a real local Ray with 2 CPUs, started once for the session
    in a child process (so the commands under test connect to it as to any
    existing cluster) and stopped with it."""
    head = subprocess.Popen([sys.executable, "-c", _RAY_HEAD], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True)
    address = head.stdout.readline().strip()
    if not address:
        head.wait(timeout=30)
        pytest.fail(f"the local Ray did not start (exit {head.returncode})")
    yield address
    head.stdin.close()
    try:
        head.wait(timeout=60)
    except subprocess.TimeoutExpired:
        head.kill()
        head.wait()
