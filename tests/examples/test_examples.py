"""The worlds of examples/, each built, stepped through a session against the shipped default, and run."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from simclient import WarmStartSession

EXAMPLES = Path(__file__).parents[2] / "examples"
WORLDS = ("pyramid", "stack", "chain", "car")


def example(name: str):
    spec = importlib.util.spec_from_file_location(f"example_{name}", EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def snapshot(world) -> np.ndarray:
    return np.array([tuple(b.position) + (b.angle,) for b in world.bodies])


@pytest.mark.parametrize("name", WORLDS)
def test_each_world_is_a_function_of_its_seed(name):
    build = example(name).build
    assert np.array_equal(snapshot(build(901)), snapshot(build(901)))
    assert not np.array_equal(snapshot(build(901)), snapshot(build(902)))


@pytest.mark.parametrize("name", WORLDS)
def test_each_world_steps_through_a_session_on_the_shipped_default(name, default_server):
    world = example(name).build(901)
    with WarmStartSession(world, default_server.address, model="default", deadline_ms=2000) as session:
        for _ in range(80):
            session.step(0.01, 1000, 1000)
        summary = session.summary()
    assert summary["steps_with_contacts"] > 0 and summary["fallback_steps"] == 0, summary["fallbacks_by_reason"]
    assert summary["guard_probes"] > 0 or summary["guarded_steps"] > 0
    assert np.isfinite(snapshot(world)).all()


def test_the_default_answers_a_stack_of_boxes_by_its_zoo_route(default_server):
    # contact-modes was trained on piles of discs: on boxes the default's route is the zoo
    # classifier's, and where that one's solve misses its labels, Box2D's own start (the graph
    # network was trained on discs too).
    world = example("stack").build(901)
    with WarmStartSession(world, default_server.address, model="default", deadline_ms=2000, guard=False) as session:
        served = [session.step(0.01, 1000, 1000) for _ in range(120)]
    answered = {record.served_by for record in served if record.points}
    assert "zoo" in answered and answered <= {"zoo", "builtin"}, answered


def test_an_example_runs_with_one_command(default_server):
    run = subprocess.run([sys.executable, str(EXAMPLES / "stack.py"), "--server", default_server.address,
                          "--steps", "60"], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "builtin" in run.stdout and "server:default (guard on)" in run.stdout and "/ builtin" in run.stdout


def test_the_readmes_attach_script_runs_against_a_server(default_server):
    run = subprocess.run([sys.executable, str(EXAMPLES / "attach.py"), default_server.address],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "'mean_velocity_iterations'" in run.stdout and "'fallback_steps': 0" in run.stdout
