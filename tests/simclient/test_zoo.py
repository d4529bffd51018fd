"""The zoo of scenes: each class builds its world from the seed alone, draws its physics over the
promised ranges, touches within its first steps, and holds what its name and envelope say."""

from __future__ import annotations

import math

import numpy as np
import pytest

import Box2D
from deepcontact.envelope import Envelope
from deepcontact.records import BODY_DTYPE
from simclient import zoo

NAMES = list(zoo.CLASSES)


def snapshot(world: Box2D.b2World) -> np.ndarray:
    """Every body as the patch exports it: type, position, angle, mass, inertia, shape, bounding radius."""
    out = np.empty(world.bodyCount, BODY_DTYPE)
    world.ExportBodies(out)
    return out


def test_the_classes_in_their_order():
    assert NAMES == ["discs", "pyramid", "stack", "polygons", "jointed", "ragdolls", "terrain", "rotating"]


@pytest.mark.parametrize("name", NAMES)
def test_a_seed_builds_one_world_bit_for_bit_and_another_seed_another(name):
    build = zoo.CLASSES[name]
    (a, dt_a), (b, dt_b), (c, dt_c) = build(850), build(850), build(851)
    assert isinstance(a, Box2D.b2World) and dt_a == dt_b and dt_a != dt_c
    first, again, other = snapshot(a), snapshot(b), snapshot(c)
    assert first.tobytes() == again.tobytes()  # positions, angles, masses, shapes
    assert (a.jointCount, a.contactCount) == (b.jointCount, b.contactCount)
    assert len(first) != len(other) or not np.array_equal(first["position"], other["position"])


@pytest.mark.parametrize("name", NAMES)
def test_dt_and_gravity_lie_in_the_promised_ranges(name):
    for seed in (1, 900):
        world, dt = zoo.CLASSES[name](seed)
        assert 1 / 120 <= dt <= 1 / 30
        gx, gy = world.gravity
        assert gx == 0.0 and 2.0 <= -gy <= 20.0  # pointing down


def test_the_physics_is_drawn_over_the_whole_of_each_range():
    draws = [zoo._Physics.draw(np.random.default_rng(seed)) for seed in range(1, 400)]
    for key, (lo, hi) in (("gravity", zoo.GRAVITY), ("dt", zoo.DT), ("density", zoo.DENSITY),
                          ("friction", zoo.FRICTION), ("restitution", zoo.RESTITUTION)):
        values = np.array([getattr(d, key) for d in draws])
        assert lo <= values.min() and values.max() <= hi, key
        assert values.max() - values.min() > 0.8 * (hi - lo), key  # all of it, not a corner
    # Log-uniform: as many time steps below the geometric mean as above it.
    below = np.mean([d.dt < math.sqrt(zoo.DT[0] * zoo.DT[1]) for d in draws])
    assert 0.4 < below < 0.6
    # A world's bodies share its material, or each draws its own within the ranges.
    rng = np.random.default_rng(7)
    per_body = next(d for d in draws if d.per_body)
    bodies = [per_body.body(rng) for _ in range(200)]
    density = np.array([m["density"] for m in bodies])
    assert zoo.DENSITY[0] <= density.min() and density.max() <= zoo.DENSITY[1]
    assert density.max() / density.min() <= 2.0 + 1e-9
    assert all(zoo.FRICTION[0] <= m["friction"] <= zoo.FRICTION[1] for m in bodies)
    shared = next(d for d in draws if not d.per_body)
    assert shared.body(rng) == shared.body(rng) == {"density": shared.density, "friction": shared.friction,
                                                     "restitution": shared.restitution}


@pytest.mark.parametrize("name", NAMES)
def test_its_bodies_touch_and_stay_finite_over_150_steps(name):
    world, dt = zoo.CLASSES[name](1)
    dynamic = [b for b in world.bodies if b.type == Box2D.b2_dynamicBody]
    assert 1 <= len(dynamic) <= 250
    contacts, points = [], []
    for _ in range(150):
        world.Step(dt, 1000, 10)
        contacts.append(world.contactCount)
        points.append(world.contactPointCount)  # points of touching contacts
    assert max(contacts) > 0
    assert next(k for k, p in enumerate(points) if p > 0) < 100  # touching within the first 100 steps
    positions = snapshot(world)["position"]
    assert np.isfinite(positions).all()


def test_each_class_holds_what_its_name_says():
    worlds = {name: zoo.CLASSES[name](2)[0] for name in NAMES}

    def fixtures(world, shape):
        return [f for b in world.bodies for f in b.fixtures if isinstance(f.shape, shape)]

    def dynamic(world, shape):
        return [f for b in world.bodies if b.type == Box2D.b2_dynamicBody for f in b.fixtures
                if isinstance(f.shape, shape)]

    assert worlds["jointed"].jointCount > 0 and worlds["ragdolls"].jointCount > 0
    assert {type(j) for j in worlds["jointed"].joints} == {Box2D.b2RevoluteJoint, Box2D.b2PrismaticJoint,
                                                           Box2D.b2WeldJoint}
    assert worlds["ragdolls"].jointCount % 9 == 0  # nine joints a ragdoll
    assert all(j.limitEnabled for j in worlds["ragdolls"].joints)
    assert any(b.type == Box2D.b2_kinematicBody and b.angularVelocity != 0 for b in worlds["rotating"].bodies)
    assert len(fixtures(worlds["terrain"], Box2D.b2ChainShape)) == 1
    assert not dynamic(worlds["discs"], Box2D.b2PolygonShape)
    for name in ("pyramid", "stack"):
        assert not dynamic(worlds[name], Box2D.b2CircleShape)
    for name in ("polygons", "jointed", "terrain", "rotating"):
        assert dynamic(worlds[name], Box2D.b2CircleShape) and dynamic(worlds[name], Box2D.b2PolygonShape)
    assert any(len(b.fixtures) == 2 for b in worlds["polygons"].bodies if b.type == Box2D.b2_dynamicBody)
    for name in ("discs", "pyramid", "stack", "polygons", "jointed", "ragdolls", "terrain"):
        assert not any(b.type == Box2D.b2_kinematicBody for b in worlds[name].bodies), name


@pytest.mark.parametrize("name", NAMES)
def test_the_envelope_holds_the_worlds_the_class_builds(name):
    card = zoo.envelope_of(name)
    assert list(card) == ["shapes", "radius", "density", "friction", "gravity", "dt", "joints", "kinematic"]
    envelope = Envelope.from_dict(card)
    assert (envelope.joints, envelope.kinematic) == (name in ("jointed", "ragdolls"), name == "rotating")
    for seed in (3, 901):
        world, dt = zoo.CLASSES[name](seed)
        bodies = snapshot(world)
        moving = bodies[bodies["type"] == 2]
        assert envelope.radius[0] <= moving["radius"].min() and moving["radius"].max() <= envelope.radius[1]
        disc = np.abs(moving["inertia"] / (moving["mass"] * moving["radius"] ** 2) - 0.5) <= 0.02
        assert set(np.where(disc, "disc", "other")) <= set(envelope.shapes)
        density = moving["mass"][disc] / (np.pi * moving["radius"][disc] ** 2)
        assert (density >= 0.5 * (1 - 1e-6)).all() and (density <= 10.0 * (1 + 1e-6)).all()
        assert envelope.dt[0] <= dt <= envelope.dt[1]
        assert envelope.gravity[0] <= -world.gravity[1] <= envelope.gravity[1]
        friction = [f.friction for b in world.bodies for f in b.fixtures]
        assert envelope.friction[0] - 1e-6 <= min(friction) and max(friction) <= envelope.friction[1] + 1e-6
    with pytest.raises(KeyError, match="no zoo class 'tower'"):
        zoo.envelope_of("tower")


def test_a_class_is_named_as_a_world_source():
    assert zoo.source("terrain") == "simclient.zoo:terrain"
    with pytest.raises(ValueError, match="no zoo class 'tower'"):
        zoo.source("tower")


def test_a_class_runs_where_a_users_world_does_with_its_own_time_step():
    from simclient import worlds

    world, dt = worlds.build_user_world(zoo.source("stack"), 7)
    assert isinstance(world, Box2D.b2World) and dt == zoo.stack(7)[1]
    engine = worlds.build(worlds.WorldSpec(zoo.source("stack"), steps=5), 7)
    assert engine.config.dt == pytest.approx(dt)  # the seed's, not the command line's 0.01 s
