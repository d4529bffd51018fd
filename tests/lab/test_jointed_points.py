"""`deepcontact lab jointed-points` (lab.jointed_points): the points at jointed bodies against
the rest, and the bodies' velocities after Box2D's warm start of their joints."""

from __future__ import annotations

import argparse
from pathlib import Path

import Box2D
import numpy as np

from lab.jointed_points import ANSWERS, LABEL_ROWS, add_arguments, after_joint_warm_start, run
from simclient.engine import Engine, SolverConfig

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _hanging_link() -> Engine:
    """A link hung by its top end from a static anchor: at rest it is held by its joint alone."""
    world = Box2D.b2World(gravity=(0.0, -9.8))
    anchor = world.CreateStaticBody(position=(0.0, 2.0))
    link = world.CreateDynamicBody(position=(0.0, 1.5))
    link.CreatePolygonFixture(box=(0.05, 0.5), density=1.0)
    world.CreateRevoluteJoint(bodyA=anchor, bodyB=link, anchor=(0.0, 2.0))
    return Engine(world, SolverConfig())


def test_a_hanging_link_at_rest_is_held_against_a_steps_gravity_by_its_joints_warm_start():
    engine = _hanging_link()
    for _ in range(120):
        engine.collide()
        engine.solve()
    bodies = engine.bodies()
    link = int(np.flatnonzero(bodies["type"] == 2)[0])
    assert abs(bodies["velocity"][link, 1]) < 1e-3  # at rest
    held = after_joint_warm_start(engine, bodies)
    # The joint's last impulse, m g dt upward, is what the step's gravity takes away again.
    assert np.isclose(held["velocity"][link, 1], 9.8 * engine.config.dt, rtol=1e-2)
    assert abs(held["velocity"][link, 0]) < 1e-4 and abs(held["angular_velocity"][link]) < 1e-3
    assert np.array_equal(held["position"], bodies["position"])  # only the velocities move
    assert bodies["velocity"][link, 1] == engine.bodies()["velocity"][link, 1]  # the engine's records untouched


def test_the_chain_is_priced_on_box2ds_states_for_every_answer(capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["--world", f"{EXAMPLES / 'chain.py'}:build", "--seeds", "850", "--steps", "40"])
    assert run(args) == 0
    out = capsys.readouterr().out
    assert "% of the points touch a jointed body" in out
    sweeps, labels = out.split("\n\n")
    rows = {line.split("|")[1].strip(): float(line.split("|")[2]) for line in sweeps.splitlines()
            if line.startswith("| ") and not line.startswith("| answer")}
    assert set(rows) == set(ANSWERS)
    assert rows["oracle"] < rows["builtin"]  # the converged answer needs fewer sweeps than Box2D's start
    # The second table: each reading of the labels, right at the jointed and at the free points.
    right = {line.split("|")[1].strip(): line.split("|")[2:4] for line in labels.splitlines()
             if line.startswith("| ") and not line.startswith("| labels")}
    assert set(right) == set(LABEL_ROWS)
    for cells in right.values():
        assert all(0.0 <= float(cell.split("%")[0]) <= 100.0 for cell in cells)


def test_a_world_that_does_not_load_is_one_line_of_error(capsys):
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    assert run(parser.parse_args(["--world", "no/such.py:build"])) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("deepcontact lab jointed-points:") and "\n" not in err
