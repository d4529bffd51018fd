"""`deepcontact lab joint-route`: the joints' rows in the route's problem (lab.joint_route),
checked on a small world whose answer is known: a pendulum of two links hung over a box on the
ground, the step solved on its own converged labels with the joints in it."""

from __future__ import annotations

import Box2D
import numpy as np

from deepcontact.faces import OPEN, STICKS, contact_face
from lab.joint_route import Problem, joint_rows
from simclient.engine import Engine, SolverConfig


def _pendulum_on_a_box() -> Engine:
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-5.0, 0.0), (5.0, 0.0)], friction=0.6)
    box = world.CreateDynamicBody(position=(1.0, 0.5))
    box.CreatePolygonFixture(box=(0.5, 0.5), density=1.0, friction=0.6)
    anchor = world.CreateStaticBody(position=(0.0, 1.5))
    upper = world.CreateDynamicBody(position=(0.4, 1.5))
    upper.CreatePolygonFixture(box=(0.4, 0.05), density=1.0, friction=0.6)
    lower = world.CreateDynamicBody(position=(1.2, 1.5))
    lower.CreatePolygonFixture(box=(0.4, 0.05), density=1.0, friction=0.6)
    world.CreateRevoluteJoint(bodyA=anchor, bodyB=upper, anchor=(0.0, 1.5))
    world.CreateRevoluteJoint(bodyA=upper, bodyB=lower, anchor=(0.8, 1.5))
    return Engine(world, SolverConfig())


def test_the_joints_rows_follow_the_engines_joints_and_each_holds_an_anchor():
    engine = _pendulum_on_a_box()
    engine.collide()
    rows = joint_rows(engine, engine.bodies())
    assert len(rows["a"]) == 4  # two revolute joints, two rows each: their anchors' x and y
    assert np.isinf(rows["lo"]).all() and np.isinf(rows["hi"]).all() and not rows["speed"].any()
    pairs = engine.joints()
    assert {tuple(p) for p in pairs} == {(int(a), int(b)) for a, b in zip(rows["a"], rows["b"])}


def test_the_step_solved_on_its_own_labels_with_the_joints_holds_every_joint_and_contact():
    engine = _pendulum_on_a_box()
    for _ in range(40):  # the box settles, the pendulum swings down onto it
        engine.step()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    mu = points["friction"].astype(np.float64)
    oracle = engine.oracle(start=engine.builtin_start()).astype(np.float64)
    face = contact_face(oracle, mu)
    links = np.isin(points["body_a"], (3, 4)) | np.isin(points["body_b"], (3, 4))  # the pendulum's links
    assert (face[links] != OPEN).any()  # lying on the box
    problem = Problem(bodies, points, joint_rows(engine, bodies), (0.0, -9.8), engine.config.dt)
    contact, joint = problem.solve(face, mu)
    velocity = problem.v0 + problem.minv * (problem.jc.T @ contact.ravel() + problem.jj.T @ joint)
    assert np.abs(problem.jj @ velocity).max() < 1e-9  # no joint comes apart
    normal = (problem.jc @ velocity)[0::2]
    assert np.abs(normal[face != OPEN]).max() < 1e-9  # no pressing point closes or opens
    tangent = (problem.jc @ velocity)[1::2]
    assert np.abs(tangent[face == STICKS]).max() < 1e-9
    # Left out, the joints' load goes nowhere and the pendulum's contacts are solved wrong.
    free, _ = problem.solve(face, mu, with_joints=False)
    assert not np.allclose(free, contact, atol=1e-6)
