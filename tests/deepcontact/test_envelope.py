"""What a model was trained on, and whether a step lies inside it (deepcontact.envelope)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import Box2D
from deepcontact.envelope import Envelope
from deepcontact.kinematics import Physics
from simclient.engine import Engine
from simclient.scene import SceneSpec, settled_world, spec_to_dict

THESIS = SceneSpec.thesis()
FAMILY = dataclasses.replace(THESIS, radius=(0.3, 0.55), friction=(0.2, 0.8))
TRAINED = Envelope.from_scenes([spec_to_dict(THESIS), spec_to_dict(FAMILY)])


def step_of(engine):
    engine.collide()
    points = engine.contacts()
    return engine.bodies(), points, points["friction"]


def test_the_envelope_of_the_default_s_training_worlds():
    assert TRAINED == Envelope(shapes=("disc",), radius=(0.3, 0.55), density=(1.0, 1.0), friction=(0.2, 0.8),
                               gravity=(9.8, 9.8), dt=(0.01, 0.01), joints=False, kinematic=False)
    assert Envelope.from_dict(TRAINED.to_dict()) == TRAINED


def test_a_thesis_pile_is_familiar():
    bodies, points, friction = step_of(settled_world(THESIS, 901, 60))
    assert TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), None) is None


def test_a_family_world_with_other_radii_and_friction_is_familiar():
    bodies, points, friction = step_of(settled_world(dataclasses.replace(FAMILY, bodies=200, box_size=(25, 15)), 850, 60))
    assert TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), None) is None


def test_boxes_among_the_discs_are_named():
    bodies, points, friction = step_of(settled_world(dataclasses.replace(THESIS, polygons=0.3), 901, 60))
    reason = TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), None)
    assert reason is not None and "not discs" in reason


def test_another_time_step_gravity_friction_or_size_is_named():
    bodies, points, friction = step_of(settled_world(THESIS, 901, 60))
    assert "dt 0.0167" in TRAINED.unfamiliar(bodies, points, friction, Physics(1 / 60, (0, -9.8)), None)
    assert "gravity 20" in TRAINED.unfamiliar(bodies, points, friction, Physics(0.01, (0, -20.0)), None)
    assert "friction 0.05" in TRAINED.unfamiliar(bodies, points, np.full(len(points), 0.05), Physics.thesis(), None)
    small = TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), None)
    assert small is None
    # Inside the slack (a tenth of the range's top) is still familiar: 0.56 m having seen 0.55 m.
    assert TRAINED.unfamiliar(bodies, points, np.full(len(points), 0.85), Physics.thesis(), None) is None


def test_joints_and_kinematic_bodies_are_named():
    world = Box2D.b2World(gravity=(0, -9.8))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-10, 0), (10, 0)], friction=0.5)
    a = world.CreateDynamicBody(position=(0, 0.5))
    a.CreateCircleFixture(radius=0.5, density=1, friction=0.5)
    b = world.CreateDynamicBody(position=(1.0, 0.5))
    b.CreateCircleFixture(radius=0.5, density=1, friction=0.5)
    world.CreateRevoluteJoint(bodyA=a, bodyB=b, anchor=(0.5, 0.5))
    platform = world.CreateKinematicBody(position=(3, 0.5), linearVelocity=(1, 0))
    platform.CreateCircleFixture(radius=0.5, friction=0.5)
    world.CreateDynamicBody(position=(3, 1.45)).CreateCircleFixture(radius=0.5, density=1, friction=0.5)
    engine = Engine(world)
    bodies, points, friction = step_of(engine)
    reason = TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), engine.joints())
    assert "1 joints" in reason and "1 kinematic bodies" in reason


def test_bodies_that_touch_nothing_are_not_judged():
    """A box resting far from every contact changes nothing of the step's problem."""
    engine = settled_world(THESIS, 901, 60)
    box = engine.world.CreateDynamicBody(position=(100, 100))
    box.CreatePolygonFixture(box=(0.5, 0.5), density=1)
    bodies, points, friction = step_of(engine)
    assert TRAINED.unfamiliar(bodies, points, friction, Physics.thesis(), None) is None


def test_what_is_not_an_envelope_is_refused_in_one_line():
    with pytest.raises(ValueError, match="trained_on"):
        Envelope.from_dict({"shapes": ["disc"], "colour": "red"})
    with pytest.raises(ValueError, match="0 <= low <= high"):
        Envelope.from_dict({"radius": [0.6, 0.5]})
    with pytest.raises(ValueError):
        Envelope.from_scenes([])


def test_a_step_is_rescaled_into_the_density_and_pull_its_envelope_holds_and_left_alone_inside_it():
    from tests.deepcontact.piles import sliding_pile

    bodies, points, _, _ = sliding_pile()
    thesis = Physics.thesis()
    envelope = Envelope()  # the thesis world: density 1, 9.8 m/s^2, 0.01 s
    same = envelope.rescaled(bodies, points, None, thesis)
    assert same[0] is bodies and same[1] is points and same[4] == (1.0, 1.0, 1.0)
    heavy = bodies.copy()
    heavy["mass"] *= 4
    heavy["inertia"] *= 4
    strong = Physics(thesis.dt, (0.0, -19.6))  # twice the pull: g dt twice the trained
    b, p, _, physics, (kl, km, kv) = envelope.rescaled(heavy, points, None, strong)
    assert kl == 1.0 and km == pytest.approx(4, rel=1e-5) and kv == pytest.approx(2, rel=1e-5)
    np.testing.assert_allclose(b["mass"], bodies["mass"], rtol=1e-6)
    np.testing.assert_allclose(b["velocity"], bodies["velocity"] / 2, rtol=1e-6)
    np.testing.assert_allclose(p["builtin"], points["builtin"] / 8, rtol=1e-6)
    assert physics.dt == pytest.approx(0.01) and physics.gravity[1] == pytest.approx(-9.8)
    assert envelope.unfamiliar(heavy, points, None, strong, None) is not None
    assert envelope.unfamiliar(b, p, None, physics, None) is None
