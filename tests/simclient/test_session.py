"""WarmStartSession: a world built by hand, attached to a real server over gRPC."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

import Box2D
from server.process import ServerProcess
from simclient import WarmStartSession
from simclient.engine import Engine, SolverConfig
from tests.server.conftest import write_conv_model

SUMMARY_KEYS = {"steps", "steps_with_contacts", "mean_velocity_iterations", "median_velocity_iterations",
                "fallback_steps", "fallbacks_by_reason", "p50_latency_ms", "served_by", "guarded_steps",
                "learned_steps", "guard_probes", "guard_switches", "guard_trial_iterations", "refusal"}


def everything_world(seed: int = 0) -> Box2D.b2World:
    """Every kind of thing a user's world holds: circles, boxes and convex polygons, edge and
    chain terrain, a body of several fixtures, a kinematic body, revolute (with a motor),
    prismatic, weld and distance joints, two islands apart, sleeping on (Box2D's default),
    and bodies that fall for a while before anything touches."""
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))  # doSleep: Box2D's default, on
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-30.0, 0.0), (0.0, 0.0)], friction=0.6)
    ground.CreateChainFixture(vertices_chain=[(0.0, 0.0), (5.0, 0.8), (10.0, 0.2), (30.0, 0.0)], friction=0.7)
    for i in range(12):  # a heap, dropped from 3 m: some steps with no contact first
        body = world.CreateDynamicBody(position=(float(rng.uniform(-6, -2)), 3.0 + 0.9 * i),
                                       angle=float(rng.uniform(0, math.pi)))
        if i % 3 == 0:
            body.CreateCircleFixture(radius=0.35, density=1.0, friction=0.5)
        elif i % 3 == 1:
            body.CreatePolygonFixture(box=(0.35, 0.25), density=1.0, friction=0.5)
        else:
            body.CreatePolygonFixture(vertices=[(-0.4, -0.3), (0.4, -0.3), (0.0, 0.4)], density=2.0, friction=0.5)
    dumbbell = world.CreateDynamicBody(position=(-4.0, 15.0))  # several fixtures, off its origin
    dumbbell.CreatePolygonFixture(box=(0.6, 0.1, (0.3, 0.0), 0.0), density=1.0, friction=0.5)
    dumbbell.CreateCircleFixture(radius=0.3, pos=(1.0, 0.0), density=1.0, friction=0.5)
    lift = world.CreateKinematicBody(position=(-10.0, 1.0), linearVelocity=(0.0, 0.3))
    lift.CreatePolygonFixture(box=(1.0, 0.1), friction=0.6)
    rider = world.CreateDynamicBody(position=(-10.0, 1.5))
    rider.CreatePolygonFixture(box=(0.3, 0.3), density=1.0, friction=0.6)
    # Jointed bodies, far from the heap: another island.
    base = world.CreateDynamicBody(position=(15.0, 0.6))
    base.CreatePolygonFixture(box=(1.0, 0.3), density=1.0, friction=0.6)
    arm = world.CreateDynamicBody(position=(15.0, 1.6))
    arm.CreatePolygonFixture(box=(0.1, 0.6), density=1.0, friction=0.6)
    world.CreateRevoluteJoint(bodyA=base, bodyB=arm, anchor=(15.0, 1.0), enableMotor=True, motorSpeed=1.0,
                              maxMotorTorque=5.0)
    slider = world.CreateDynamicBody(position=(18.0, 0.5))
    slider.CreatePolygonFixture(box=(0.3, 0.3), density=1.0, friction=0.6)
    world.CreatePrismaticJoint(bodyA=ground, bodyB=slider, anchor=(18.0, 0.5), axis=(1.0, 0.0))
    welded = world.CreateDynamicBody(position=(15.0, 2.4))
    welded.CreateCircleFixture(radius=0.2, density=1.0)
    world.CreateWeldJoint(bodyA=arm, bodyB=welded, anchor=(15.0, 2.2))
    bob = world.CreateDynamicBody(position=(21.0, 2.0))
    bob.CreateCircleFixture(radius=0.3, density=1.0, friction=0.5)
    world.CreateDistanceJoint(bodyA=slider, bodyB=bob, anchorA=slider.position, anchorB=bob.position)
    return world


def positions(world) -> np.ndarray:
    return np.array([tuple(b.position) + (b.angle,) for b in world.bodies])


@pytest.fixture(scope="module")
def test_server(tmp_path_factory):
    """tiny (a grid model), with the providers zero, random, bad."""
    folder = tmp_path_factory.mktemp("models")
    write_conv_model(folder, "tiny")
    with ServerProcess(folder, local_socket=True) as srv:
        yield srv


@pytest.mark.parametrize("guard", [True, False])
def test_every_kind_of_world_steps_without_a_crash_a_nan_or_a_fallback(default_server, guard):
    world = everything_world()
    with WarmStartSession(world, default_server.address, model="default", deadline_ms=2000, guard=guard) as session:
        results = []
        for k in range(220):
            if k == 60:  # a body made, one destroyed, between steps
                extra = world.CreateDynamicBody(position=(-5.0, 6.0))
                extra.CreateCircleFixture(radius=0.3, density=1.0, friction=0.5)
                world.DestroyBody(world.bodies[3])
            results.append(session.step(0.01, 1000, 10))
        summary = session.summary()
    assert SUMMARY_KEYS <= set(summary)
    assert np.isfinite(positions(world)).all()
    assert summary["steps"] == 220 and 0 < summary["steps_with_contacts"] < 220  # the first steps fall freely
    assert summary["fallback_steps"] == 0, summary["fallbacks_by_reason"]
    asked = [r for r in results if r.latency_ms is not None]
    assert asked and all(r.fallback is None for r in results)
    if guard:
        assert summary["guard_probes"] > 0 and all(r.start in (None, "learned", "builtin") for r in results)
    else:
        assert summary["guard_probes"] == 0 and summary["learned_steps"] == 0


def test_a_world_asleep_is_not_sent():
    from simclient.stepping import Stepper
    from simclient.warmstarts import Remote

    world = Box2D.b2World(gravity=(0.0, -9.8))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-5.0, 0.0), (5.0, 0.0)])
    world.CreateDynamicBody(position=(0.0, 0.5)).CreatePolygonFixture(box=(0.5, 0.5), density=1.0)
    engine = Engine(world, SolverConfig())
    for _ in range(200):  # a box at rest falls asleep within a second
        engine.step()
    assert not engine.awake().any()
    record = Stepper(engine, Remote("default"), client=None).step(0)
    # No server at all, yet no fallback: a step whose every point sleeps needs no warm start.
    assert record.contact_points == 0 and not record.fallback


def test_the_guard_keeps_a_bad_warm_start_from_costing_more_than_builtin(test_server):
    """`bad` answers 50 N s at every point: served blind it costs many times Box2D's iterations."""
    def run(**kw):
        world = everything_world(1)
        with WarmStartSession(world, test_server.address, model="bad", deadline_ms=2000, **kw) as session:
            for _ in range(200):
                session.step(0.01, 1000, 10)
            return session.summary()

    builtin = Engine(everything_world(1), SolverConfig(dt=0.01, position_iterations=10))
    its = [s.velocity_iterations for s in (builtin.step() for _ in range(200)) if s.contact_points]
    guarded, blind = run(), run(guard=False)
    assert blind["mean_velocity_iterations"] > 2 * np.mean(its)
    assert guarded["mean_velocity_iterations"] <= 1.05 * np.mean(its)
    assert guarded["learned_steps"] == 0 and guarded["guard_probes"] >= 2
    assert guarded["guard_trial_iterations"] <= 0.05 * sum(its)  # within the guard's budget


def test_the_guard_serves_a_start_that_wins(test_server):
    """grid-identity answers the step's own solution, smoothed through the grids: on a pile
    of discs it beats Box2D's start, and the guard serves it."""
    from simclient.scene import SceneSpec, build_world

    engine = build_world(SceneSpec.thesis(), 903)
    with WarmStartSession(engine.world, test_server.address, model="grid-identity", deadline_ms=2000) as session:
        for _ in range(200):
            session.step(0.01, 1000, 1000)
        summary = session.summary()
    assert summary["learned_steps"] > summary["guarded_steps"] and summary["guard_switches"] >= 1


def test_a_step_past_the_servers_limits_is_refused_once_then_builtin(tmp_path, caplog):
    write_conv_model(tmp_path, "tiny")
    world = everything_world(2)
    with ServerProcess(tmp_path, "--max-points", "6", local_socket=True) as srv, caplog.at_level(logging.WARNING):
        with WarmStartSession(world, srv.address, model="tiny", deadline_ms=2000, guard=False) as session:
            results = [session.step(0.01, 1000, 10) for _ in range(200)]
            summary = session.summary()
    refused = [r for r in results if r.fallback is not None]
    assert refused and {r.fallback for r in refused} <= {"INVALID_ARGUMENT", "REFUSED"}
    assert sum(r.fallback == "INVALID_ARGUMENT" for r in results) <= 3  # asked again only for smaller steps
    assert "point_count" in summary["refusal"] and "limit of 6" in summary["refusal"]
    assert sum("refuses" in r.message for r in caplog.records) == 1
    assert np.isfinite(positions(world)).all()


def test_a_model_gone_wrong_costs_fallbacks_not_the_world(tmp_path):
    write_conv_model(tmp_path, "nan", weights=np.nan)  # every answer NaN: the server refuses to send it
    world = everything_world(3)
    with ServerProcess(tmp_path, local_socket=True) as srv:
        with WarmStartSession(world, srv.address, model="nan", deadline_ms=2000, guard=False) as session:
            for _ in range(150):
                session.step(0.01, 1000, 10)
            summary = session.summary()
    assert summary["fallback_steps"] == summary["steps_with_contacts"] > 0
    assert "INTERNAL" in summary["fallbacks_by_reason"]
    assert np.isfinite(positions(world)).all()


class _ForeignServer:
    """A client of a server that is not deepcontact's: its replies have NaN in them, or the wrong length."""

    reconnects = 0

    def __init__(self, fill, extra=0):
        self.fill, self.extra = fill, extra

    def step(self, request, timeout):
        from deepcontact import wire

        n = request.point_count + self.extra
        return wire.encode_impulses(request.step, request.model, np.full((n, 2), self.fill, np.float32))


@pytest.mark.parametrize("fill, extra", [(np.nan, 0), (np.inf, 0), (0.0, 1)])
def test_a_reply_that_cannot_be_injected_never_is(fill, extra):
    from simclient.stepping import Stepper
    from simclient.warmstarts import Remote

    engine = Engine(everything_world(3), SolverConfig(position_iterations=10))
    stepper = Stepper(engine, Remote("default"), client=_ForeignServer(fill, extra))
    records = [stepper.step(k) for k in range(150)]
    asked = [r for r in records if r.latency_ms is not None]
    assert asked and all(r.fallback_reason == "BAD_REPLY" for r in asked)
    assert np.isfinite(positions(engine.world)).all()


def test_no_server_is_a_clear_error_or_with_allow_fallback_builtin_every_step(tmp_path):
    world = everything_world()
    with pytest.raises(ConnectionError, match="no warm-start server"):
        WarmStartSession(world, f"unix:{tmp_path / 'nobody.sock'}", connect_timeout=0.2)
    with WarmStartSession(world, f"unix:{tmp_path / 'nobody.sock'}", connect_timeout=0.2,
                          allow_fallback=True, guard=False) as session:
        for _ in range(120):
            session.step(0.01, 1000, 10)
        summary = session.summary()
    assert summary["fallbacks_by_reason"] == {"NO_SERVER": summary["steps_with_contacts"]}


def test_an_unknown_model_or_a_stock_world_is_refused_at_once(test_server):
    with pytest.raises(ValueError, match="does not serve 'nope'"):
        WarmStartSession(everything_world(), test_server.address, model="nope")
    with pytest.raises(ValueError, match="patched Box2D.b2World"):
        WarmStartSession(object(), test_server.address)


def test_steps_follow_the_callers_time_step_and_iterations(test_server):
    world = everything_world()
    with WarmStartSession(world, test_server.address, model="zero", deadline_ms=2000, tolerance=None) as session:
        fixed = [session.step(0.01, 7, 3) for _ in range(100)]
        halves = [session.step(0.005, 7, 3) for _ in range(40)]  # a new dt: the server is told on a new stream
        summary = session.summary()
    assert all(r.velocity_iterations == 7 for r in fixed + halves if r.points)  # no tolerance: Box2D's fixed count
    assert summary["fallback_steps"] == 0


def test_the_server_says_whether_it_knows_the_world(default_server):
    """The shipped default was trained on piles of discs and measured to win there: a thesis
    pile is familiar, and the guard serves the learned start from its first step with contacts;
    a world of boxes, polygons and joints is not, and the summary says why."""
    from simclient.scene import SceneSpec, build_world

    engine = build_world(SceneSpec.thesis(), 903)
    with WarmStartSession(engine.world, default_server.address, model="default", deadline_ms=2000) as pile:
        results = [pile.step(0.01, 1000, 1000) for _ in range(60)]
        summary = pile.summary()
    touching = [r for r in results if r.points]
    assert summary["unfamiliar_steps"] == 0 and summary["familiar_steps"] > 0
    assert touching[0].start == "learned" and summary["guarded_steps"] == 0
    with WarmStartSession(everything_world(), default_server.address, model="default", deadline_ms=2000) as mixed:
        for _ in range(120):
            mixed.step(0.01, 1000, 10)
        summary = mixed.summary()
    assert summary["familiar_steps"] == 0 and summary["unfamiliar_steps"] > 0
    assert "not discs" in summary["unfamiliar"]
