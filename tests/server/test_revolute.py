"""server.revolute: a world of revolute joints, its starts priced with the joints swept as
Box2D sweeps them (their angle limits and motors too), and its joints' start served too (the real patched engine, the shipped default
behind a real server)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from deepcontact import wire
from deepcontact.faces import RevoluteRows, sweeps_to_stop
from deepcontact.kinematics import Physics
from server.revolute import KEY_BASE, all_held, joint_points, joints_on_b, limits, rows

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def settled_engine(source: str, steps: int, seed: int, settled: int):
    """(spec, engine) of the world `source` (PATH.py:FUNCTION or MODULE:FUNCTION), stepped
    `settled` steps by Box2D's own start."""
    from simclient.worlds import WorldSpec, build

    spec = WorldSpec(source, steps=steps)
    spec.validate()
    engine = build(spec, seed)
    for _ in range(settled):
        engine.collide()
        engine.solve()
    return spec, engine


def chain_engine(seed: int = 850, settled: int = 0):
    """(spec, engine) of the chain of examples/ (free revolute joints)."""
    return settled_engine(f"{EXAMPLES / 'chain.py'}:build", 120, seed, settled)


def test_every_joint_of_the_chain_is_exported_as_a_revolute_one_with_its_last_impulse():
    _, engine = chain_engine(settled=40)
    revolute = engine.revolute()
    assert revolute.shape == (30, 15) and all_held(revolute) and (revolute[:, 0] == 1).all()
    assert not revolute[:, 7:].any() and limits(engine.bodies(), engine.joints(), revolute, 0.01) is None  # no limit, no motor
    # The joint list is pybox2d's in reverse; each row is the same joint as Engine.joints names.
    by_bodies = {(int(a), int(b)): r for (a, b), r in zip(engine.joints(), revolute)}
    index = {int(body.this): i for i, body in enumerate(engine.world.bodies)}
    for joint in engine.world.joints:
        r = by_bodies[index[int(joint.bodyA.this)], index[int(joint.bodyB.this)]]
        np.testing.assert_allclose(r[1:5], [*joint.anchorA, *joint.anchorB], atol=1e-5)
        np.testing.assert_allclose(r[5:7], tuple(joint.GetReactionForce(1.0)), atol=1e-6)
    assert not all_held(np.concatenate([revolute, np.zeros((1, 15), np.float32)]))  # one other joint: not all


def test_a_joint_is_two_points_at_its_anchor_that_hold_its_last_impulse():
    _, engine = chain_engine(settled=40)
    engine.collide()
    points, joints, revolute = engine.contacts(), engine.joints(), engine.revolute()
    pairs = joint_points(points, joints, revolute)
    assert len(pairs) == 2 * len(joints) and len(np.unique(pairs["key"])) == len(pairs)
    assert (pairs["key"] >= np.uint64(KEY_BASE)).all()
    np.testing.assert_array_equal(pairs["normal"][:, 0], np.tile([1.0, -1.0], len(joints)))
    np.testing.assert_allclose(joints_on_b(pairs["builtin"]), revolute[:, 5:7], atol=1e-6)


def test_the_servers_copy_of_a_chains_step_counts_the_sweeps_the_engine_does_once_it_holds_the_joints():
    spec, engine = chain_engine()
    tolerance = engine.config.velocity_threshold
    with_joints, without, steps = 0, 0, 0
    from bench.inprocess import declared_world

    physics = declared_world(spec, engine).physics
    for _ in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points):
            start = np.asarray(points["builtin"], np.float64)[None]
            mu = np.asarray(points["friction"], np.float64)
            ab, arms, own = rows(bodies, engine.joints(), engine.revolute())
            joined = sweeps_to_stop(bodies, points, start, mu, physics, tolerance, 1000, None,
                                    RevoluteRows(ab, arms, own[None]))[0][0]
            alone = sweeps_to_stop(bodies, points, start, mu, physics, tolerance, 1000)[0][0]
            own_sweeps = engine.trial(points["builtin"][:, 0].copy(), points["builtin"][:, 1].copy())
            with_joints += abs(int(joined) - own_sweeps) <= 3
            without += abs(int(alone) - own_sweeps) <= 3
            steps += 1
            engine.set_warm_start(points["builtin"][:, 0].copy(), points["builtin"][:, 1].copy())
        engine.solve()
    assert steps > 50
    assert with_joints >= 0.8 * steps and with_joints > without


def ragdolls_engine(seed: int = 850, settled: int = 0):
    """(spec, engine) of the zoo's ragdolls (limited revolute joints, some with joint friction)."""
    return settled_engine("simclient.zoo:ragdolls", 150, seed, settled)


def test_a_ragdolls_joints_are_exported_with_their_limits_and_motors_as_the_next_solve_holds_them():
    _, engine = ragdolls_engine(settled=60)
    engine.collide()
    revolute = engine.revolute()
    assert all_held(revolute) and (revolute[:, 0] == 1).all()
    by_bodies = {(int(a), int(b)): r for (a, b), r in zip(engine.joints(), revolute)}
    index = {int(body.this): i for i, body in enumerate(engine.world.bodies)}
    dt = 0.01
    for joint in engine.world.joints:
        r = by_bodies[index[int(joint.bodyA.this)], index[int(joint.bodyB.this)]]
        angle = joint.angle  # bodyB's angle less bodyA's less the reference angle, as the solver reads it
        lower, upper = joint.limits
        state = 1 if angle <= lower else 2 if angle >= upper else 0
        assert r[7] == state
        if state == 0:
            assert r[8] == 0.0  # an inactive limit starts from no impulse
        assert r[9] == float(joint.motorEnabled) and r[11] == pytest.approx(joint.GetMaxMotorTorque())
        assert r[12] == pytest.approx(joint.motorSpeed)
    held = limits(engine.bodies(), engine.joints(), revolute, dt)
    assert held.shape == (len(revolute), 13) and np.allclose(held[:, 5], revolute[:, 11] * dt)
    assert not held[:, 0].any()  # no prismatic joint
    assert (revolute[:, 7] > 0).any()  # some limit is reached in a pile of ragdolls


def test_an_active_limit_starts_from_the_impulse_it_is_given_and_an_inactive_one_from_none():
    """Engine.set_revolute_impulses with a third column starts each active angle limit from that
    impulse (N m s), kept by the solve even where the limit has just become active (Box2D zeroes
    a limit's impulse where its state changes); an inactive limit starts from none whatever it is
    given, and the point impulses are set as with two columns."""
    _, engine = ragdolls_engine(settled=60)
    engine.collide()
    revolute = engine.revolute()
    active = revolute[:, 7] > 0
    assert active.any() and (~active).any()
    given = np.concatenate([revolute[:, 5:7], np.full((len(revolute), 1), 0.25, np.float32)], 1)
    engine.set_revolute_impulses(given)
    after = engine.revolute()
    np.testing.assert_array_equal(after[active, 8], 0.25)
    np.testing.assert_array_equal(after[~active, 8], 0.0)
    np.testing.assert_array_equal(after[:, 5:7], revolute[:, 5:7])
    with pytest.raises(ValueError, match="revolute impulses are"):
        engine.set_revolute_impulses(np.zeros((len(revolute), 4), np.float32))


def copy_agreement(engine, physics: Physics, steps: int) -> dict[str, int]:
    """Along Box2D's own trajectory, how many steps with points the server's copy counts within 3
    of the engine's own sweeps from Box2D's start: with the joints as the request holds them
    (`held`), with every joint a free revolute one (`free`), without the joints (`alone`); and
    how many steps had points (`steps`)."""
    tolerance, counts = engine.config.velocity_threshold, {"held": 0, "free": 0, "alone": 0, "steps": 0}
    for _ in range(steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points):
            start = np.asarray(points["builtin"], np.float64)
            mu, revolute, joints = np.asarray(points["friction"], np.float64), engine.revolute(), engine.joints()
            ab, arms, own = rows(bodies, joints, revolute)
            copies = {"held": RevoluteRows(ab, arms, own[None], limits(bodies, joints, revolute, physics.dt)),
                      "free": RevoluteRows(ab, arms, own[None]), "alone": None}
            normal, tangent = start[:, 0].astype(np.float32), start[:, 1].astype(np.float32)
            own_sweeps = engine.trial(normal, tangent)
            for name, joint_rows in copies.items():
                count = sweeps_to_stop(bodies, points, start[None], mu, physics, tolerance, 1000, None, joint_rows)[0][0]
                counts[name] += abs(int(count) - own_sweeps) <= 3
            counts["steps"] += 1
            engine.set_warm_start(normal, tangent)
        engine.solve()
    return counts


def test_the_servers_copy_of_a_ragdolls_step_counts_the_engines_sweeps_better_with_the_limits_and_motors():
    from bench.inprocess import declared_world

    spec, engine = ragdolls_engine()
    counts = copy_agreement(engine, declared_world(spec, engine).physics, 120)
    assert counts["steps"] > 50
    assert counts["held"] >= 0.6 * counts["steps"] and counts["held"] > max(counts["free"], counts["alone"])


def test_the_joints_rows_must_fit_the_starts():
    _, engine = chain_engine()
    engine.collide()
    for _ in range(30):
        engine.solve()
        engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    ab, arms, own = rows(bodies, engine.joints(), engine.revolute())
    start = np.zeros((2, len(points), 2))
    with pytest.raises(ValueError, match="joints"):
        sweeps_to_stop(bodies, points, start, np.full(len(points), 0.5), Physics(dt=0.01, gravity=(0.0, -9.8)), 1e-4,
                       10, None, RevoluteRows(ab, arms, own[None]))  # one joint start for two starts


@pytest.mark.parametrize("guard", [False, True])
def test_the_default_starts_a_chains_joints_over_the_wire(default_server, guard):
    from simclient.session import WarmStartSession

    _, engine = chain_engine()
    with WarmStartSession(engine.world, default_server.address, model="default", deadline_ms=2000,
                          guard=guard) as session:
        results = [session.step(0.01, 1000, 10) for _ in range(120)]
        summary = session.summary()
    assert summary["fallback_steps"] == 0, summary["fallbacks_by_reason"]
    started = [r for r in results if r.joints_started]
    assert started and summary["joints_started_steps"] == len(started)
    assert all(r.points > 0 and r.fallback is None for r in started)
    positions = np.array([tuple(b.position) for b in engine.world.bodies])
    assert np.isfinite(positions).all()


def test_a_reply_that_starts_the_joints_carries_one_impulse_a_joint():
    reply = wire.pb.Impulses(joint_impulses=np.arange(6, dtype=np.float32).tobytes())
    np.testing.assert_array_equal(wire.decode_joint_impulses(reply, 3), np.arange(6).reshape(3, 2))
    assert wire.decode_joint_impulses(wire.pb.Impulses(), 3) is None  # the joints keep their own
    with pytest.raises(wire.WireError, match="joint_impulses"):
        wire.decode_joint_impulses(reply, 2)


def test_a_step_the_pricing_would_not_finish_by_its_deadline_keeps_the_served_answer():
    import time

    from bench.inprocess import declared_world
    from server.predictors import Prediction, load_model
    from server.revolute import PricingTime, joint_route, start_with_joints

    spec, engine = chain_engine(settled=40)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    route = joint_route(load_model(Path(__file__).resolve().parents[2] / "models" / "default.json"))
    assert route is not None and route.name == "zoo"
    world = declared_world(spec, engine)
    served = Prediction(np.asarray(points["builtin"], np.float32))
    args = (route, bodies, points, engine.joints(), engine.revolute(), world, 40, None, points["friction"], served)
    timing = PricingTime()
    priced = start_with_joints(*args, timing=timing)
    assert timing.seconds > 0 and priced.stages["admit"] > 0  # priced: it took time, and says where
    late = PricingTime()
    late.observe(1.0)  # a second a step: no 10 ms deadline fits it
    assert start_with_joints(*args, deadline=time.perf_counter() + 0.01, timing=late) is served


def test_a_request_carries_the_joints_limits_and_motors_beside_their_point_constraints():
    _, engine = ragdolls_engine(settled=60)
    engine.collide()
    revolute = engine.revolute()
    msg = wire.encode_step(60, "default", engine.bodies(), engine.contacts(), joints=engine.joints(),
                           revolute=revolute)
    np.testing.assert_array_equal(wire.decode_revolute(msg), revolute)
    older = wire.encode_step(60, "default", engine.bodies(), engine.contacts(), joints=engine.joints(),
                             revolute=revolute[:, :7])  # a client that sends no limits: none are read
    decoded = wire.decode_revolute(older)
    np.testing.assert_array_equal(decoded[:, :7], revolute[:, :7])
    assert not decoded[:, 7:].any() and limits(engine.bodies(), engine.joints(), decoded, 0.01) is None


def sliders_and_welds(seed: int):
    """A world of every other kind the copy holds: boxes on prismatic joints to the ground (limits
    on, half of them driven) sliding down onto loose boxes, and box-and-disc pairs on rigid welds."""
    import math

    import Box2D

    from simclient.engine import Engine

    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-8.0, 0.0), (8.0, 0.0)], friction=0.5)
    for i in range(12):
        world.CreateDynamicBody(position=(float(rng.uniform(-6, 6)), 0.3 + 0.6 * i)).CreatePolygonFixture(
            box=(0.3, 0.25), density=1.0, friction=0.5)
    for k in range(4):
        x, y, tilt = -6.0 + 4.0 * k, 5.0, float(rng.uniform(-0.4, 0.4))
        body = world.CreateDynamicBody(position=(x, y), angle=float(rng.uniform(-0.3, 0.3)))
        body.CreatePolygonFixture(box=(0.4, 0.3), density=1.0, friction=0.5)
        drive = {"enableMotor": True, "motorSpeed": -0.5, "maxMotorForce": 5.0} if k % 2 else {}
        world.CreatePrismaticJoint(bodyA=ground, bodyB=body, anchor=(x, y), axis=(math.sin(tilt), math.cos(tilt)),
                                   enableLimit=True, lowerTranslation=-y, upperTranslation=0.5, **drive)
    for k in range(3):
        box = world.CreateDynamicBody(position=(-5.0 + 5.0 * k, 8.0))
        box.CreatePolygonFixture(box=(0.3, 0.3), density=1.0, friction=0.5)
        disc = world.CreateDynamicBody(position=(-4.4 + 5.0 * k, 8.0))
        disc.CreateCircleFixture(radius=0.3, density=1.0, friction=0.5)
        world.CreateWeldJoint(bodyA=box, bodyB=disc, anchor=(-4.7 + 5.0 * k, 8.0))
    return Engine(world)


def test_prismatic_and_weld_joints_are_held_by_the_servers_copy_as_box2d_sweeps_them():
    from deepcontact.kinematics import Physics

    engine = sliders_and_welds(850)
    kinds = engine.revolute()[:, 0]
    assert sorted(kinds.tolist()) == [2.0] * 3 + [3.0] * 4  # three welds, four sliders
    counts = copy_agreement(engine, Physics(dt=engine.config.dt, gravity=(0.0, -9.8)), 200)
    assert counts["steps"] > 100
    assert counts["held"] >= 0.9 * counts["steps"] and counts["held"] > counts["alone"]


def test_an_active_angle_limit_is_held_on_a_lever_whose_normal_turns_the_way_the_limit_allows():
    from server.revolute import LEVER_ARM, lever_points

    _, engine = ragdolls_engine(settled=60)
    engine.collide()
    points, joints, revolute, bodies = engine.contacts(), engine.joints(), engine.revolute(), engine.bodies()
    levers, owner = lever_points(points, bodies, joints, revolute)
    state = revolute[:, 7]
    assert len(levers) == int((state > 0).sum() + (state == 3).sum()) > 0
    assert set(owner.tolist()) == set(np.flatnonzero(state > 0).tolist())
    # At a lower limit the limit's impulse turns B positively: a push along +y on a lever along +x.
    expected = np.where(state[owner] == 2, -1.0, 1.0)
    np.testing.assert_array_equal(levers["normal"][:, 1], expected)
    np.testing.assert_array_equal(levers["body_a"], joints[owner, 0])
    arm = levers["point"][:, 0] - revolute[owner, 3]
    assert (arm >= LEVER_ARM - 1e-6).all() and np.allclose(levers["point"][:, 1], revolute[owner, 4])
    # Its builtin is the limit's last impulse over the lever, where it pushes the lever's way.
    np.testing.assert_allclose(levers["builtin"][:, 0], np.maximum(expected * revolute[owner, 8] / arm, 0), rtol=1e-4,
                               atol=1e-7)
    assert len(np.unique(levers["key"])) == len(levers)
    assert len(lever_points(points, bodies, joints, revolute[:, :7])[0]) == 0  # no limits sent: none held


def test_the_joints_route_repairs_its_answer_and_a_chains_steps_then_stop_sooner():
    """With the card's repairs, the route with the joints in it also prices its answer repaired
    (the contacts' labels read off the answer's motion, the joints' points held as they were), each
    with its joints' start: on the chain settling over its heap, Box2D's own sweeps from what it
    serves add up to fewer than from the same route without repairs."""
    import copy

    from bench.inprocess import declared_world
    from server.predictors import Prediction, load_model
    from server.revolute import joint_route, start_with_joints

    spec, engine = chain_engine(settled=60)
    repaired = joint_route(load_model(Path(__file__).resolve().parents[2] / "models" / "default.json"))
    assert repaired.settings["repairs"] == 3
    plain = copy.copy(repaired)
    plain.settings = {**repaired.settings, "repairs": 0}
    world = declared_world(spec, engine)
    sweeps = {"repaired": 0, "plain": 0}
    for step in range(60, 90):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        served = Prediction(np.asarray(points["builtin"], np.float32))
        for name, route in (("repaired", repaired), ("plain", plain)):
            answer = start_with_joints(route, bodies, points, engine.joints(), engine.revolute(), world, step, None,
                                       points["friction"], served)
            before = engine.joint_state()
            if answer.joint_impulses is not None:
                engine.set_revolute_impulses(answer.joint_impulses)
            x = np.asarray(answer.impulses)
            sweeps[name] += engine.trial(np.ascontiguousarray(x[:, 0]), np.ascontiguousarray(x[:, 1]))
            engine.set_joint_state(before)
        engine.set_warm_start(*engine.builtin_start())
        engine.solve()
    assert sweeps["repaired"] < 0.8 * sweeps["plain"], sweeps
