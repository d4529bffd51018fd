"""server.revolute: a world of rigid revolute joints, its starts priced with the joints swept as
Box2D sweeps them, and its joints' start served too (the real patched engine, the shipped default
behind a real server)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from deepcontact import wire
from deepcontact.faces import RevoluteRows, sweeps_to_stop
from deepcontact.kinematics import Physics
from server.revolute import KEY_BASE, all_rigid, joint_points, joints_on_b, rows

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def chain_engine(seed: int = 850, settled: int = 0):
    """(spec, engine) of the chain of examples/, stepped `settled` steps by Box2D's own start."""
    from simclient.worlds import WorldSpec, build

    spec = WorldSpec(f"{EXAMPLES / 'chain.py'}:build", steps=120)
    spec.validate()
    engine = build(spec, seed)
    for _ in range(settled):
        engine.collide()
        engine.solve()
    return spec, engine


def test_every_joint_of_the_chain_is_exported_as_a_rigid_revolute_one_with_its_last_impulse():
    _, engine = chain_engine(settled=40)
    revolute = engine.revolute()
    assert revolute.shape == (30, 7) and all_rigid(revolute)
    # The joint list is pybox2d's in reverse; each row is the same joint as Engine.joints names.
    by_bodies = {(int(a), int(b)): r for (a, b), r in zip(engine.joints(), revolute)}
    index = {int(body.this): i for i, body in enumerate(engine.world.bodies)}
    for joint in engine.world.joints:
        r = by_bodies[index[int(joint.bodyA.this)], index[int(joint.bodyB.this)]]
        np.testing.assert_allclose(r[1:5], [*joint.anchorA, *joint.anchorB], atol=1e-5)
        np.testing.assert_allclose(r[5:7], tuple(joint.GetReactionForce(1.0)), atol=1e-6)
    assert not all_rigid(np.concatenate([revolute, np.zeros((1, 7), np.float32)]))  # one other joint: not all


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
