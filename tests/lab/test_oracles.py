"""Oracle experiments (lab.oracles) on the real engine: where a warm start's value lies."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
import lab  # noqa: F401  (registers the lab's warm starts)
from simclient.warmstarts import make_provider

SHORT = dataclasses.replace(SceneSpec.thesis(), steps=120)


def mean_iterations(name, spec=SHORT):
    return run_simulation(spec, 901, make_provider(name))["summary"]["mean_velocity_iterations"]


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


def test_the_value_of_a_warm_start_lies_in_its_small_corrections():
    # The oracle at the points whose correction is small is worth much more than at those
    # where it is large once the pile has formed (docs/results.md, "Where the iterations are"),
    # and noise erodes it: a whole thesis run.
    its = {name: mean_iterations(name, SceneSpec.thesis()) for name in ("builtin", "oracle:small@1", "oracle:big@1",
                                                                        "oracle:noisy@0.01", "oracle:noisy@1")}
    assert its["oracle:small@1"] < 0.7 * its["builtin"]
    assert its["oracle:small@1"] < its["oracle:big@1"]
    assert its["oracle:small@1"] <= its["oracle:noisy@0.01"] < its["oracle:noisy@1"]


def test_the_oracle_at_half_the_points_is_worth_much_less_than_at_all_of_them():
    # A warm start pays only where it is right nearly everywhere: exact at a random half of
    # the points, the solver still redoes most of the work (docs/results.md).
    its = {name: mean_iterations(name) for name in ("builtin", "oracle:some@0.5", "oracle:some@1")}
    assert its["oracle:some@1"] <= 2.0  # every point exact: the oracle itself
    assert its["oracle:some@1"] < 0.5 * its["oracle:some@0.5"]
    assert its["oracle:some@0.5"] < its["builtin"]


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


def test_every_listed_oracle_variant_makes_a_provider_and_unknown_ones_are_refused():
    from lab.oracles import ORACLES

    for variant in ORACLES:
        name = "oracle:" + variant.split("@")[0] + ("@0.5" if "@" in variant else "")
        assert make_provider(name).name == name
    with pytest.raises(ValueError, match="unknown oracle variant"):
        make_provider("oracle:nearest")


def test_the_simple_mixes_take_the_solution_where_their_names_say():
    class Solved:  # an engine whose step converges, from zero, to `exact`
        exact = np.array([[2.0, 0.4], [0.5, 0.1], [1.2, -0.2]], np.float32)

        def oracle(self, start=None):
            return self.exact

    points = np.zeros(3, dtype=[("builtin", "<f4", (2,))])
    points["builtin"] = [[1.0, 0.2], [0.0, 0.0], [1.0, 0.0]]  # point 1 is new: Box2D carries nothing into it

    def served(name):
        return np.stack(make_provider(name).warm_start(Solved(), None, points, 0), axis=1)

    exact, builtin = Solved.exact, points["builtin"]
    np.testing.assert_allclose(served("oracle:persisting"), [exact[0], [0.0, 0.0], exact[2]])
    np.testing.assert_allclose(served("oracle:new"), [builtin[0], exact[1], builtin[2]])
    np.testing.assert_allclose(served("oracle:normal"), [[2.0, 0.2], [0.5, 0.0], [1.2, 0.0]])
    np.testing.assert_allclose(served("oracle:tangent"), [[1.0, 0.4], [0.0, 0.1], [1.0, -0.2]])
    np.testing.assert_allclose(served("oracle:half"), (exact + builtin) / 2, rtol=1e-6)
    # corrections of the normal impulse: 1.0, 0.5, 0.2 N s
    np.testing.assert_allclose(served("oracle:small@0.5"), [builtin[0], exact[1], exact[2]])
    np.testing.assert_allclose(served("oracle:big@0.5"), [exact[0], builtin[1], builtin[2]])
