"""Local warm-start providers on the real engine."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from simclient.scene import SceneSpec, settled_world
from simclient.simulate import run_simulation
from simclient.warmstarts import Extrapolate, make_provider

SHORT = dataclasses.replace(SceneSpec.thesis(), steps=120)


def mean_iterations(name, spec=SHORT):
    return run_simulation(spec, 901, make_provider(name))["summary"]["mean_velocity_iterations"]


def test_the_thesis_ordering_of_simple_warm_starts():
    # Builtin pulls ahead of none once the pile has formed: whole thesis runs for those two.
    its = {name: mean_iterations(name, SceneSpec.thesis()) for name in ("none", "builtin")}
    its.update({name: mean_iterations(name) for name in ("copy", "copy2")})
    assert its["copy"] <= 2.0  # the oracle: about one sweep
    assert its["copy"] < its["copy2"] < its["builtin"] < its["none"]


def test_extrapolate_uses_the_last_two_impulses_of_persisting_points():
    ex = Extrapolate()
    keys = np.array([5, 7, 9], np.uint64)
    before = np.zeros(3, dtype=[("key", "<u8"), ("builtin", "<f4", (2,))])
    before["key"], before["builtin"] = keys, [[1.0, 0.1], [0.0, 0.0], [2.0, -0.2]]  # J(t-2); key 7 new then
    ex.observe(before)
    now = np.zeros(4, dtype=[("key", "<u8"), ("builtin", "<f4", (2,))])
    now["key"] = [5, 7, 9, 11]
    now["builtin"] = [[1.5, 0.1], [0.5, 0.0], [1.0, -0.1], [0.0, 0.0]]  # J(t-1)
    normal, tangent = ex.warm_start(None, None, now, 0)
    np.testing.assert_allclose(normal, [2.0, 0.5, 0.0, 0.0])  # 2*J(t-1) - J(t-2) where both exist
    np.testing.assert_allclose(tangent, [0.1, 0.0, 0.0, 0.0], atol=1e-7)


def test_oracle_experiments_say_where_a_warm_start_pays():
    # The oracle at persisting points is nearly the whole oracle's gain; at new points, none of it.
    # Through a 0.25 m grid most of it survives (the thesis's Grid model); through 2 m, little.
    its = {name: mean_iterations(name) for name in ("builtin", "oracle:persisting", "oracle:new", "oracle:grid@0.25",
                                                    "oracle:grid@2")}
    assert its["oracle:persisting"] < 0.6 * its["builtin"]
    assert its["oracle:new"] > 0.9 * its["builtin"]
    assert its["oracle:grid@0.25"] < 0.7 * its["builtin"] < its["oracle:grid@2"]


def test_oracle_experiments_pass_steps_without_contacts_quietly():
    import warnings

    falling = dataclasses.replace(SceneSpec.thesis(), steps=40)  # no contact for the first steps
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for name in ("oracle:heavy", "oracle:grid@0.5"):
            assert mean_iterations(name, falling) is not None


def test_unknown_warm_starts_are_refused():
    with pytest.raises(ValueError, match="unknown warm start"):
        make_provider("magic")
    with pytest.raises(ValueError, match="model name"):
        make_provider("server:")
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


def test_shadow_serves_its_first_candidate_as_it_would_alone_and_prices_builtin_beside_it():
    alone = run_simulation(SHORT, 901, make_provider("jitter@0.01"))
    shadowed = run_simulation(SHORT, 901, make_provider("shadow:jitter@0.01"))
    assert shadowed["per_step"]["velocity_iterations"] == alone["per_step"]["velocity_iterations"]
    its = [i for i, n in zip(alone["per_step"]["velocity_iterations"], alone["per_step"]["contact_points"]) if n]
    assert [t[1] for t in shadowed["trials"]] == its  # builtin's count on the same states is t[0]


def test_price_steps_as_builtin_and_prices_each_candidate_on_builtins_states():
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    jitter = run_simulation(SHORT, 901, make_provider("shadow:jitter@0.01"))
    priced = run_simulation(SHORT, 901, make_provider("price:jitter@0.01"))
    assert priced["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    its = [i for i, n in zip(builtin["per_step"]["velocity_iterations"], builtin["per_step"]["contact_points"]) if n]
    assert [t[0] for t in priced["trials"]] == its  # a trial from builtin's start is the step's own solve
    # the same states in every run: a second run prices the same candidate the same way
    assert run_simulation(SHORT, 901, make_provider("price:jitter@0.01"))["trials"] == priced["trials"]
    assert [t[1] for t in priced["trials"]] != [t[1] for t in jitter["trials"]]  # jitter's own states differ


def test_mean_serves_the_candidates_mean_and_prices_it_beside_each_of_them():
    provider = make_provider("mean:jitter@0.1+jitter@0.1")
    assert provider.labels == ["builtin", "jitter@0.1", "jitter@0.1", "mean"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[3] for t in served["trials"]] == its
    assert any(t[3] not in (t[1], t[2]) for t in served["trials"])  # the mean is neither candidate


def test_a_shadow_whose_server_is_away_serves_builtin_and_counts_the_fallbacks():
    shadowed = run_simulation(SHORT, 901, make_provider("shadow:server:zero"), client=None)
    builtin = run_simulation(SHORT, 901, make_provider("builtin"))
    assert shadowed["per_step"]["velocity_iterations"] == builtin["per_step"]["velocity_iterations"]
    assert shadowed["summary"]["fallback_steps"] == builtin["summary"]["steps_with_contacts"] > 0


def test_pick_never_does_worse_than_builtin_and_jitter_alone_wins_some_steps():
    # Candidates that know nothing: the per-step choice still finds cheaper starts
    # (docs/results.md, "Nor does choosing per step").
    picked = run_simulation(SHORT, 901, make_provider("pick:jitter@0.01+jitter@0.01"))
    its = [i for i, n in zip(picked["per_step"]["velocity_iterations"], picked["per_step"]["contact_points"]) if n]
    assert its == [min(t) for t in picked["trials"]]
    assert any(t[1] != t[2] for t in picked["trials"])  # the two jitters draw different noise
    assert np.mean(its) < mean_iterations("builtin")


def test_the_value_of_a_warm_start_lies_in_its_small_corrections():
    # The oracle at the points whose correction is small is worth much more than at those
    # where it is large once the pile has formed (docs/results.md, "Where the iterations are"),
    # and noise erodes it: a whole thesis run.
    its = {name: mean_iterations(name, SceneSpec.thesis()) for name in ("builtin", "oracle:small@1", "oracle:big@1",
                                                                        "oracle:noisy@0.01", "oracle:noisy@1")}
    assert its["oracle:small@1"] < 0.7 * its["builtin"]
    assert its["oracle:small@1"] < its["oracle:big@1"]
    assert its["oracle:small@1"] <= its["oracle:noisy@0.01"] < its["oracle:noisy@1"]


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


def test_the_oracle_at_half_the_points_is_worth_much_less_than_at_all_of_them():
    # A warm start pays only where it is right nearly everywhere: exact at a random half of
    # the points, the solver still redoes most of the work (docs/results.md).
    its = {name: mean_iterations(name) for name in ("builtin", "oracle:some@0.5", "oracle:some@1")}
    assert its["oracle:some@1"] <= 2.0  # every point exact: the oracle itself
    assert its["oracle:some@1"] < 0.5 * its["oracle:some@0.5"]
    assert its["oracle:some@0.5"] < its["builtin"]


def test_probe_warm_starts_check_their_parameter():
    for name, match in (("lastchange@x", "factor"), ("solve@0", "iterations"), ("oracle:small@0", "correction size"),
                        ("oracle:noisy@-1", "noise level"), ("oracle:some@1.5", "share of the points"),
                        ("oracle:near-admissible@0", "relative to the motion"),
                        ("oracle:near-admissible-abs@-1", "noise level in N s")):
        with pytest.raises(ValueError, match=match):
            make_provider(name)


@pytest.mark.parametrize("name", ["oracle:previous", "oracle:near-previous"])
def test_the_previous_steps_oracle_is_served_at_persisting_points_only(name):
    from simclient.scene import build_world

    engine = build_world(SHORT, 901)
    provider = make_provider(name)
    assert provider.name == name
    provider.prepare(engine)
    served = []
    for _ in range(80):
        engine.collide()
        points = engine.contacts()
        warm = provider.warm_start(engine, engine.bodies(), points, engine.step_index)
        if warm is not None:
            engine.set_warm_start(*warm)
            new = ~points["builtin"].any(axis=1)
            assert (warm[0][new] == 0).all()  # nothing carried into a point Box2D has not seen
            served.append(not np.allclose(warm[0], points["builtin"][:, 0]))
        engine.solve()
        provider.observe(engine.contacts())
    assert any(served)  # the previous solve stopped at the threshold, the oracle did not


def test_the_oracle_pays_at_resting_contacts_as_well_as_at_moving_ones():
    # A settled pile's contacts (bodies slower than 1 cm/s) hold little of the error of Box2D's
    # warm start and about as much of its iterations as the contacts of moving bodies.
    spec = SceneSpec.thesis()
    its = {name: mean_iterations(name, spec) for name in ("builtin", "oracle:settled", "oracle:moving")}
    assert its["oracle:settled"] < 0.8 * its["builtin"] and its["oracle:moving"] < 0.8 * its["builtin"]


def test_the_solutions_self_stress_pays_and_the_part_that_moves_the_bodies_little():
    # Of the correction from Box2D's warm start to the solution its own solve converges
    # to, the self-stress (impulses that move no body) saves far more iterations than the
    # part that moves the bodies, though the latter is most of the correction's size.
    spec = dataclasses.replace(SceneSpec.thesis(), steps=250)
    its = {name: mean_iterations(name, spec) for name in ("builtin", "oracle:near", "oracle:near-body-space",
                                                        "oracle:near-self-stress")}
    assert its["oracle:near"] <= 2.0  # a solution already: about one sweep
    assert its["oracle:near-self-stress"] < 0.85 * its["builtin"]
    assert its["oracle:near-self-stress"] < its["oracle:near-body-space"]


def test_split_serves_its_warm_start_and_prices_the_two_parts_of_its_correction():
    provider = make_provider("split:oracle:near")
    assert provider.labels == ["builtin", "oracle:near", "oracle:near body-space", "oracle:near self-stress"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[1] for t in served["trials"]] == its  # serves the warm start itself
    assert all(t[1] <= 2 for t in served["trials"])
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("split:oracle:near+oracle:half")


def test_near_release_and_switch_touch_only_the_contacts_that_open_or_close():
    class Solved:  # an engine whose step converges, from Box2D's warm start, to `near`
        near = np.array([[0.0, 0.0], [2.0, 0.1], [0.5, 0.0], [1.5, 0.2]], np.float32)

        def oracle(self, start=None):
            assert start is not None  # the near oracles solve from Box2D's warm start
            return self.near

    points = np.zeros(4, dtype=[("builtin", "<f4", (2,))])
    points["builtin"] = [[1.0, 0.1], [0.0, 0.0], [0.4, 0.0], [1.0, 0.1]]  # 0 opens, 1 closes, 2 and 3 stay
    release = np.stack(make_provider("oracle:near-release").warm_start(Solved(), None, points, 0), axis=1)
    switch = np.stack(make_provider("oracle:near-switch").warm_start(Solved(), None, points, 0), axis=1)
    np.testing.assert_allclose(release, [[0.0, 0.0], [0.0, 0.0], [0.4, 0.0], [1.0, 0.1]])
    np.testing.assert_allclose(switch, [[0.0, 0.0], [2.0, 0.1], [0.4, 0.0], [1.0, 0.1]])


def test_near_cone_and_inside_split_the_points_by_whether_friction_is_at_its_cone_at_either_end():
    class Solved:
        near = np.array([[1.0, 0.5], [1.0, 0.1], [1.0, 0.2], [0.0, 0.0]], np.float32)

        def oracle(self, start=None):
            return self.near

    points = np.zeros(4, dtype=[("builtin", "<f4", (2,)), ("body_a", "<i4"), ("body_b", "<i4")])
    points["body_a"], points["body_b"] = 0, 1  # friction 0.5 on both bodies: the cone is 0.5 x normal
    # 0 slides in the solution, 1 slid in Box2D's warm start, 2 sticks at both ends, 3 opens.
    points["builtin"] = [[1.0, 0.1], [0.4, 0.2], [0.9, 0.1], [0.3, 0.0]]
    cone, inside = make_provider("oracle:near-cone"), make_provider("oracle:near-inside")
    for provider in (cone, inside):
        provider._friction = np.array([0.5, 0.5])  # what prepare() reads from the world
    at_cone = np.stack(cone.warm_start(Solved(), None, points, 0), axis=1)
    within = np.stack(inside.warm_start(Solved(), None, points, 0), axis=1)
    np.testing.assert_allclose(at_cone, [[1.0, 0.5], [1.0, 0.1], [0.9, 0.1], [0.3, 0.0]])
    np.testing.assert_allclose(within, [[1.0, 0.1], [0.4, 0.2], [1.0, 0.2], [0.0, 0.0]])


def test_boost_serves_its_warm_start_and_prices_it_with_its_self_stress_scaled():
    provider = make_provider("boost:oracle:near")
    assert provider.labels == ["builtin", "oracle:near"] + [f"oracle:near self-stress x{k:g}" for k in (0.5, 1.5, 2, 3)]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    assert [t[1] for t in served["trials"]] == its  # serves the warm start itself
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("boost:oracle:near+oracle:half")


def test_admit_serves_its_warm_start_and_prices_its_admissible_forms():
    # Served here: the solution's body-space part alone (oracle:near-body-space). Brought
    # inside the friction cones by the smallest self-stress, the same motion takes far
    # fewer iterations: given the motion, the limits choose the self-stress.
    provider = make_provider("admit:oracle:near-body-space")
    assert provider.labels == ["builtin", "oracle:near-body-space", "oracle:near-body-space admissible",
                               "oracle:near-body-space body-space admissible",
                               "oracle:near-body-space body-space admissible, separating open",
                               "oracle:near-body-space moving bodies' motion admissible",
                               "oracle:near-body-space moving bodies' motion"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the warm start itself
    assert trials[:, 2].sum() < 0.8 * trials[:, 1].sum()  # the same motion inside the cones
    assert trials[:, 3].sum() < 0.8 * trials[:, 1].sum()  # W's motion from Box2D's warm start: W itself, near enough
    assert trials.shape[1] == 7 and trials.min() >= 1  # and with the contacts its motion pulls apart; its moving bodies
    with pytest.raises(ValueError, match="one warm start"):
        make_provider("admit:oracle:near+oracle:half")


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


def test_graft_serves_the_first_and_prices_it_with_the_seconds_moving_bodies_motion():
    # The base has the solution's motion at the resting bodies only (oracle:near-admissible-settled),
    # the donor at every body (oracle:near-body-space). The donor's moving bodies' motion grafted
    # onto the base and admitted puts every body's motion right: far fewer iterations than the base.
    provider = make_provider("graft:oracle:near-admissible-settled+oracle:near-body-space")
    assert provider.labels == ["builtin", "oracle:near-admissible-settled", "oracle:near-body-space",
                               "oracle:near-admissible-settled with oracle:near-body-space's moving bodies' motion admissible",
                               "oracle:near-admissible-settled with oracle:near-body-space's moving bodies' motion"]
    served = run_simulation(SHORT, 901, provider)
    its = [i for i, n in zip(served["per_step"]["velocity_iterations"], served["per_step"]["contact_points"]) if n]
    trials = np.array(served["trials"])
    assert trials[:, 1].tolist() == its  # serves the first warm start itself
    assert trials[:, 3].sum() < 0.8 * trials[:, 1].sum()
    with pytest.raises(ValueError, match="two warm starts"):
        make_provider("graft:oracle:near")


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
