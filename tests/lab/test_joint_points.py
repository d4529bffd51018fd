"""lab.joint_points: each rigid revolute joint recorded as two contact points at its anchor."""

from __future__ import annotations

import Box2D
import numpy as np

from deepcontact.faces import STICKS, contact_face
from deepcontact.records import CONTACT_DTYPE
from lab.joint_points import KEY_BASE, SERVED_FACE, chains, joint_point_pairs
from simclient.engine import Engine, SolverConfig
from simclient.worlds import WorldSpec
from training.generate import record_simulation


def _two_links(limited: bool = False) -> Engine:
    """Two links hung end to end from a static anchor, the second joint limited or not."""
    world = Box2D.b2World(gravity=(0.0, -9.8))
    anchor = world.CreateStaticBody(position=(0.0, 3.0))
    upper = world.CreateDynamicBody(position=(0.0, 2.5))
    upper.CreatePolygonFixture(box=(0.05, 0.5), density=1.0)
    lower = world.CreateDynamicBody(position=(0.0, 1.5))
    lower.CreatePolygonFixture(box=(0.05, 0.5), density=1.0)
    world.CreateRevoluteJoint(bodyA=anchor, bodyB=upper, anchor=(0.0, 3.0))
    world.CreateRevoluteJoint(bodyA=upper, bodyB=lower, anchor=(0.0, 2.0), enableLimit=limited,
                              lowerAngle=-0.5, upperAngle=0.5)
    return Engine(world, SolverConfig())


def test_a_hanging_joint_becomes_two_opposed_points_that_carry_its_last_impulse():
    engine = _two_links()
    for _ in range(120):
        engine.collide()
        engine.solve()
    pairs = joint_point_pairs(engine, CONTACT_DTYPE)
    assert len(pairs) == 4 and len(set(pairs["key"].tolist())) == 4 and (pairs["key"] >= KEY_BASE).all()
    top = pairs[:2]  # the anchor's joint: the world's first
    assert np.allclose(top["point"], [[0.0, 3.0], [0.0, 3.0]], atol=1e-3)
    assert np.array_equal(top["normal"], [[1.0, 0.0], [-1.0, 0.0]])
    # It holds both links up: an upward impulse of their weight times dt, which lies along neither
    # normal and splits over the two tangents (the first's (0, -1), the second's (0, 1)).
    weight = 2 * 0.1 * 1.0 * 9.8 * engine.config.dt  # two links of 0.1 m x 1 m at density 1, N s
    assert np.allclose(top["builtin"][:, 0], 0.0, atol=1e-3 * weight)
    assert np.allclose(top["builtin"][:, 1], [-weight / 2, weight / 2], rtol=1e-2)
    # Served pressing and sticking: the face their final impulse is read as.
    assert (contact_face(pairs["impulse"].astype(np.float64), pairs["friction"].astype(np.float64)) == STICKS).all()
    assert np.array_equal(pairs["impulse"][0], SERVED_FACE)


def test_a_limited_joint_is_left_out_or_refused():
    engine = _two_links(limited=True)
    engine.collide()
    assert len(joint_point_pairs(engine, CONTACT_DTYPE)) == 2  # the free one alone
    assert joint_point_pairs(engine, CONTACT_DTYPE, only_rigid=False) is None


def test_a_recorded_chains_world_carries_its_joints_points_after_its_contacts():
    spec = WorldSpec("lab.joint_points:chains", steps=30)
    plain = record_simulation(spec, 3)
    both = record_simulation(spec, 3, extra_points=lambda engine: joint_point_pairs(engine, CONTACT_DTYPE))
    world, _ = chains(3)
    joints = sum(1 for _ in world.joints)
    assert joints >= 10
    assert np.array_equal(both["steps"]["velocity_iterations"], plain["steps"]["velocity_iterations"])  # unseen by the solver
    first = both["steps"][0]
    points = both["points"][first["point_offset"]:first["point_offset"] + first["point_count"]]
    own = plain["steps"][0]["point_count"]
    assert first["point_count"] == own + 2 * joints
    assert (points["key"][own:] >= KEY_BASE).all() and (points["key"][:own] < KEY_BASE).all()
