"""Shared fixtures: real patched engine, real worlds, a real model folder, a real local Ray."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import settings

# A command that meets what it did not expect prints one line (deepcontact.cli); in the
# tests it raises instead, so the test fails with the traceback.
os.environ.setdefault("DEEPCONTACT_DEBUG", "1")
# Ray reads these when it is first imported, so they are set before any test runs: the
# session's local Rays (the one below and those the commands start) and the commands
# connecting to them share one token (Ray's token authentication) kept in the
# environment rather than in ~/.ray, and report no usage statistics.
os.environ.setdefault("RAY_AUTH_MODE", "token")
os.environ.setdefault("RAY_AUTH_TOKEN", secrets.token_hex(32))
os.environ["RAY_USAGE_STATS_ENABLED"] = "0"

# Property tests draw new examples on every local run, to keep exploring; CI (.ci/run sets
# DEEPCONTACT_CI) draws the same ones every time, so that whether main lands does not depend
# on luck. A failure found locally is fixed and pinned as a plain test.
settings.register_profile("ci", derandomize=True)
if os.environ.get("DEEPCONTACT_CI"):
    settings.load_profile("ci")


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


def reflected(bodies: np.ndarray, contacts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(bodies (B,) BODY_DTYPE, contacts (P,) CONTACT_DTYPE) of the world reflected about
    x = 0 (x -> -x; exact in float32): positions, velocities, points and normals mirrored,
    angles, angular velocities and tangent impulses negated."""
    bodies, contacts = bodies.copy(), contacts.copy()
    for records, vectors in ((bodies, ("position", "velocity")), (contacts, ("point", "normal"))):
        for field in vectors:
            records[field][:, 0] *= -1
    bodies["angle"] *= -1
    bodies["angular_velocity"] *= -1
    for field in ("builtin", "warm_start", "impulse"):  # the tangent (n_y, -n_x) turns into minus itself
        contacts[field][:, 1] *= -1
    return bodies, contacts


@pytest.fixture(scope="session")
def thesis_steps():
    """(world message, [(bodies, points)]) of a few settled thesis steps, with final impulses."""
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


def shipped_model_files(names) -> list:
    """The files of the shipped models `names` in models/: their cards, what each is an alias
    of, a face card's fallback, and the ONNX files they name."""
    import json
    from pathlib import Path

    shipped = Path(__file__).parents[1] / "models"
    files, todo = set(), list(names)
    while todo:
        card = shipped / f"{todo.pop()}.json"
        files.add(card)
        d = json.loads(card.read_text())
        todo += [d["alias_of"]] if d.get("alias_of") else []
        todo += [d["face"]["fallback"]] if (d.get("face") or {}).get("fallback") else []
        if d.get("onnx_file"):
            files.add(shipped / d["onnx_file"])
    return sorted(files)


@pytest.fixture(scope="session")
def default_server(tmp_path_factory):
    """A real `deepcontact serve` process (Unix socket) on the shipped default and what it serves through."""
    import shutil

    from server.process import ServerProcess

    folder = tmp_path_factory.mktemp("shipped")
    for path in shipped_model_files(["default"]):
        shutil.copy(path, folder)
    with ServerProcess(folder, local_socket=True) as srv:
        yield srv
