"""The lab's probes (lab.probes) and the oracle variants' parameters, on the real engine."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import lab  # noqa: F401  (registers the lab's warm starts)
from simclient.scene import SceneSpec, settled_world
from simclient.simulate import run_simulation
from simclient.warmstarts import make_provider

SHORT = dataclasses.replace(SceneSpec.thesis(), steps=120)


def test_unknown_lab_warm_starts_are_refused():
    with pytest.raises(ValueError, match="unknown oracle variant"):
        make_provider("oracle:magic")
    with pytest.raises(ValueError, match="grid spacing"):
        make_provider("oracle:grid@-1")
    for name, why in (("pick:", "joined by"), ("pick:pick:server:a", "joined by"), ("pick:builtin", "always tries"),
                      ("shadow:none", "always tries"), ("shadow:pick:jitter@1", "joined by"),
                      ("price:builtin", "always tries"), ("price:price:jitter@1", "joined by"),
                      ("pick:server:", "model name"), ("pick:magic", "unknown warm start"), ("jitter@0", "noise level")):
        with pytest.raises(ValueError, match=why):
            make_provider(name)
    assert make_provider("pick:server:a+jitter@0.1+server:b").models == ("a", "b")


def test_last_change_adds_a_share_of_the_solvers_previous_change_at_persisting_points():
    provider = make_provider("lastchange@-0.5")
    fields = [("key", "<u8"), ("builtin", "<f4", (2,)), ("warm_start", "<f4", (2,)), ("impulse", "<f4", (2,))]
    before = np.zeros(2, dtype=fields)
    before["key"] = [5, 9]
    before["warm_start"] = [[1.0, 0.0], [2.0, 0.1]]
    before["impulse"] = [[1.4, 0.0], [1.0, 0.3]]  # changes +0.4 and (-1.0, +0.2)
    provider.observe(before)
    now = np.zeros(3, dtype=fields)
    now["key"] = [9, 5, 11]
    now["builtin"] = [[1.0, 0.3], [1.4, 0.0], [0.0, 0.0]]  # key 11 is new
    normal, tangent = provider.warm_start(None, None, now, 1)
    np.testing.assert_allclose(normal, [1.5, 1.2, 0.0])
    np.testing.assert_allclose(tangent, [0.2, 0.0, 0.0], atol=1e-7)


@pytest.mark.parametrize("name", ["solve@10", "solve-active@10"])
def test_a_linear_solve_warm_start_runs_and_keeps_the_contact_limits(name):
    from simclient.scene import build_world

    engine = build_world(SHORT, 901)
    provider = make_provider(name)
    provider.prepare(engine)
    for _ in range(80):  # until the pile has contacts
        engine.collide()
        points = engine.contacts()
        warm = provider.warm_start(engine, engine.bodies(), points, engine.step_index)
        if warm is not None:
            normal, tangent = warm
            assert (normal >= 0).all() and (np.abs(tangent) <= 0.5 * normal + 1e-6).all()  # friction 0.5
            engine.set_warm_start(normal, tangent)
        engine.solve()
    assert len(points) > 0


def test_probe_warm_starts_check_their_parameter():
    for name, match in (("lastchange@x", "factor"), ("solve@0", "iterations"), ("oracle:small@0", "correction size"),
                        ("oracle:noisy@-1", "noise level"), ("oracle:some@1.5", "share of the points"),
                        ("oracle:near-admissible@0", "relative to the motion"),
                        ("oracle:near-admissible-abs@-1", "noise level in N s"),
                        ("oracle:near-admissible-scaled@0", "scale of the motion")):
        with pytest.raises(ValueError, match=match):
            make_provider(name)


def test_the_scaled_motion_oracle_at_scale_one_is_the_exact_motion_admitted():
    # oracle:near-admissible-scaled@S admits S times the solution's motion: at S = 1 the plain
    # oracle, at S = 0.5 a start between it and Box2D's warm start, inside the cones either way.
    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()

    def served(name):
        provider = make_provider(name)
        provider.prepare(engine)
        return np.stack(provider.warm_start(engine, bodies, points, engine.step_index), axis=1).astype(np.float64)

    exact, whole, half = (served(n) for n in ("oracle:near-admissible", "oracle:near-admissible-scaled@1",
                                              "oracle:near-admissible-scaled@0.5"))
    np.testing.assert_allclose(whole, exact, atol=1e-6)
    assert (half[:, 0] >= 0).all() and (np.abs(half[:, 1]) <= 0.5 * half[:, 0] + 1e-6).all()  # friction 0.5
    assert not np.allclose(half, exact, atol=1e-3)


def test_rest_admissible_brings_the_slow_bodies_to_rest_inside_the_cones():
    # The guess without the solution: the touching bodies slower than 1 cm/s stopped by their
    # contacts, the rest moved as Box2D's warm start moves them, every point inside its cone.
    from deepcontact.kinematics import REST_SPEED, contact_jacobian

    provider = make_provider("rest-admissible")
    engine = settled_world(SceneSpec.thesis(), 901, 200)
    provider.prepare(engine)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    warm = np.stack(provider.warm_start(engine, bodies, points, engine.step_index), axis=1).astype(np.float64)
    assert (warm[:, 0] >= 0).all() and (np.abs(warm[:, 1]) <= 0.5 * warm[:, 0] + 1e-6).all()  # friction 0.5

    dynamic = bodies["type"] == 2
    touching = np.zeros(len(bodies), bool)
    touching[points["body_a"]] = touching[points["body_b"]] = True
    slow = dynamic & touching & (np.hypot(*bodies["velocity"].T) < REST_SPEED)
    jt = contact_jacobian(bodies, points)
    pushed = (jt @ warm.ravel()).reshape(-1, 3)[slow[dynamic]]
    gravity = np.array([0.0, -9.8]) * SceneSpec.thesis().solver.dt
    stopping = -bodies["mass"][slow, None] * (bodies["velocity"][slow] + gravity)
    # Where the cones admit it (here at every slow body; one held at a single point may not be).
    np.testing.assert_allclose(pushed[:, :2], stopping, atol=1e-3)


def test_prestress_lifts_the_pressing_points_by_impulses_that_barely_move_a_body():
    from deepcontact.kinematics import contact_jacobian

    seen = {}

    class Recording(type(make_provider("prestress@0.1"))):
        def warm_start(self, engine, bodies, points, step):
            seen["bodies"], seen["points"] = bodies, points
            return super().warm_start(engine, bodies, points, step)

    run_simulation(SHORT, 901, Recording(0.1))  # a real pile: the last step's bodies and points are kept
    bodies, points = seen["bodies"], seen["points"]
    builtin = points["builtin"].astype(np.float64)
    for provider in (make_provider("prestress@0.1"), make_provider("preload@0.1")):
        warm = np.stack(provider.warm_start(None, bodies, points, 0), axis=1).astype(np.float64)
        lift = np.zeros_like(builtin)
        lift[:, 0] = np.where(builtin[:, 0] > 0, 0.1 if provider.name.startswith("preload") else
                              np.maximum(0.1 - builtin[:, 0], 0.0), 0.0)
        jt = contact_jacobian(bodies, points)
        # The lift alone would push the bodies; what is added moves them far less: only where the
        # self-stress would take a normal impulse below zero does the clamp leak a push.
        assert np.linalg.norm(jt @ (warm - builtin).ravel()) < 0.25 * np.linalg.norm(jt @ lift.ravel())
        assert np.abs(warm - builtin).max() > 0.01
