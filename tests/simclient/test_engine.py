"""The patched engine: two-phase step, warm starts, stopping rule, export, oracle.

Everything here runs the real patched Box2D on the thesis world.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from simclient.engine import BODY_DTYPE, CONTACT_DTYPE, Box2D
from tests.conftest import settled


def test_oracle_warm_start_converges_in_at_most_two_iterations(thesis_spec):
    engine = settled(thesis_spec)
    n = engine.collide()
    assert n > 100
    exact = engine.oracle()
    assert np.isfinite(exact).all()
    engine.set_warm_start(np.ascontiguousarray(exact[:, 0]), np.ascontiguousarray(exact[:, 1]))
    stats = engine.solve()
    assert stats.velocity_iterations <= 2
    assert stats.contact_points == n


def test_oracle_leaves_the_world_unchanged(thesis_spec):
    with_oracle, without = settled(thesis_spec), settled(thesis_spec)
    for _ in range(5):
        with_oracle.collide()
        with_oracle.oracle()
        with_oracle.solve()
        without.step()
    assert with_oracle.bodies().tobytes() == without.bodies().tobytes()


def test_solved_from_builtins_warm_start_the_pile_converges_to_another_solution_that_moves_it_the_same(thesis_spec):
    # A settled pile is held at more points than its bodies have freedoms: solved from
    # Box2D's warm start rather than from zero, the step converges to a solution that
    # differs from the oracle's by a self-stress (the same bodies' velocities), and lies
    # far closer to the start. (A pile still moving, at 150 steps, may not converge to
    # 1e-6 within the oracle's 20000 iterations: this one has come to rest.)
    from deepcontact.kinematics import body_space_part, contact_velocities

    engine = settled(thesis_spec, steps=300)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    builtin = points["builtin"].astype(np.float64)
    start = tuple(np.ascontiguousarray(points["builtin"][:, k]) for k in (0, 1))
    zero, near = engine.oracle().astype(np.float64), engine.oracle(start=start).astype(np.float64)
    assert np.isfinite(near).all()
    difference = near - zero
    assert np.abs(difference).max() > 0.01  # two solutions ...
    assert np.abs(body_space_part(bodies, points, difference)).max() < 1e-3  # ... that move no body apart
    physics = thesis_spec.physics
    assert np.allclose(contact_velocities(bodies, points, near, physics),
                       contact_velocities(bodies, points, zero, physics), atol=1e-4)
    assert np.linalg.norm(near - builtin) < 0.5 * np.linalg.norm(zero - builtin)
    engine.set_warm_start(*(np.ascontiguousarray(near[:, k], np.float32) for k in (0, 1)))
    assert engine.solve().velocity_iterations <= 2


def test_a_trial_solve_costs_what_the_solve_does_and_changes_nothing(thesis_spec):
    tried, plain = settled(thesis_spec), settled(thesis_spec)
    for _ in range(5):
        tried.collide()
        points = tried.contacts()
        builtin = (np.ascontiguousarray(points["builtin"][:, 0]), np.ascontiguousarray(points["builtin"][:, 1]))
        zeros = np.zeros(len(points), np.float32)
        cost = tried.trial(*builtin)
        assert tried.trial(zeros, zeros) != cost  # another start, another count
        tried.set_warm_start(*builtin)  # the trial from zeros left zeros as the step's warm start
        assert tried.solve().velocity_iterations == cost
        plain.step()
    assert tried.bodies().tobytes() == plain.bodies().tobytes()


def test_a_trial_solve_traces_the_residual_as_the_solve_does(thesis_spec):
    engine = settled(thesis_spec)
    engine.collide()
    points = engine.contacts()
    builtin = (np.ascontiguousarray(points["builtin"][:, 0]), np.ascontiguousarray(points["builtin"][:, 1]))
    trace = engine.trial_trace(*builtin)  # (iterations,) N s, the largest impulse change of each sweep
    assert len(trace) == engine.trial(*builtin)
    assert trace[-1] <= engine.config.velocity_threshold < trace[:-1].min()  # the stopping rule's first sweep
    engine.set_warm_start(*builtin)
    assert np.array_equal(engine.solve().residual_trace, trace)


def test_a_trial_at_the_cap_ends_unconverged_and_says_how_far(thesis_spec):
    engine = settled(thesis_spec, velocity_iterations=3)
    engine.collide()
    zeros = np.zeros(len(engine.contacts()), np.float32)
    trace = engine.trial_trace(zeros, zeros)  # from zero, three sweeps cannot converge a pile
    assert len(trace) == 3 and trace[-1] > engine.config.velocity_threshold


def test_a_trial_solve_needs_a_warm_start_first(thesis_spec):
    engine = settled(thesis_spec)
    engine.collide()
    with pytest.raises(RuntimeError, match="SetWarmStart"):
        engine.world.SolveTrial(0.01, 100, 1e-4)


def test_builtin_needs_fewer_iterations_than_none_on_a_settled_pile(thesis_spec):
    builtin, none = settled(thesis_spec, steps=200), settled(thesis_spec, steps=200)
    none.world.warmStarting = False
    its_builtin = [builtin.step().velocity_iterations for _ in range(30)]
    its_none = [none.step().velocity_iterations for _ in range(30)]
    assert np.mean(its_builtin) < np.mean(its_none)


def test_threshold_zero_reproduces_plain_step_exactly(thesis_spec):
    fixed = dict(velocity_iterations=40, position_iterations=10)
    plain = settled(thesis_spec, steps=0, velocity_threshold=-1.0, statistics=False, **fixed)
    zero = settled(thesis_spec, steps=0, velocity_threshold=0.0, **fixed)
    for _ in range(120):
        plain.step()
        stats = zero.step()
        assert stats.residual_trace.size == stats.velocity_iterations
    assert zero.bodies().tobytes() == plain.bodies().tobytes()


def test_collide_then_solve_equals_step(thesis_spec):
    two_phase, plain = settled(thesis_spec, steps=0), settled(thesis_spec, steps=0)
    for _ in range(150):
        two_phase.collide()
        two_phase.solve()
        plain.step()
    assert two_phase.bodies().tobytes() == plain.bodies().tobytes()


def test_velocity_threshold_is_respected(thesis_spec):
    engine = settled(thesis_spec, steps=60)
    threshold = engine.config.velocity_threshold
    for _ in range(40):
        stats = engine.step()
        trace = stats.residual_trace
        assert trace.size == stats.velocity_iterations >= 1
        # Every sweep but the last was above the threshold; the last is within
        # it unless the iteration cap stopped the solve.
        assert (trace[:-1] > threshold).all()
        assert trace[-1] <= threshold or stats.velocity_iterations == engine.config.velocity_iterations


def test_exported_bodies_agree_with_swig_objects(thesis_spec):
    engine = settled(thesis_spec, steps=100)
    bodies = engine.bodies()
    assert bodies.dtype == BODY_DTYPE
    swig = engine.world.bodies  # pybox2d lists bodies in creation order too
    assert len(swig) == len(bodies) == 101
    np.testing.assert_array_equal(bodies["index"], np.arange(101))
    assert bodies["type"][0] == Box2D.b2_staticBody and (bodies["type"][1:] == Box2D.b2_dynamicBody).all()
    np.testing.assert_allclose(bodies["position"], [tuple(b.position) for b in swig], rtol=0, atol=0)
    np.testing.assert_allclose(bodies["velocity"], [tuple(b.linearVelocity) for b in swig], rtol=0, atol=0)
    np.testing.assert_allclose(bodies["angular_velocity"], [b.angularVelocity for b in swig], rtol=0, atol=0)
    np.testing.assert_allclose(bodies["mass"], [b.mass for b in swig], rtol=1e-7)
    np.testing.assert_allclose(bodies["radius"][1:], 0.5)
    assert (bodies["shape"][1:] == 0).all() and bodies["shape"][0] == -1  # circles; the box has 3 edges


def test_exported_contacts_agree_with_swig_objects(thesis_spec):
    engine = settled(thesis_spec, steps=100)
    n = engine.collide()
    points = engine.contacts()
    assert points.dtype == CONTACT_DTYPE and points.shape == (n,)
    position_to_index = {tuple(b.position): i for i, b in enumerate(engine.world.bodies)}
    expected = []
    # Export order is Box2D's contact list (newest first); pybox2d reverses it.
    for c in reversed(engine.world.contacts):
        if not (c.touching and c.enabled):
            continue
        wm = c.worldManifold
        for j in range(c.manifold.pointCount):
            expected.append((
                position_to_index[tuple(c.fixtureA.body.position)],
                position_to_index[tuple(c.fixtureB.body.position)],
                wm.points[j][0], wm.points[j][1], wm.normal[0], wm.normal[1],
                c.manifold.points[j].normalImpulse, c.manifold.points[j].tangentImpulse,
            ))
    expected = np.array(expected)
    assert len(expected) == n
    np.testing.assert_array_equal(points["body_a"], expected[:, 0])
    np.testing.assert_array_equal(points["body_b"], expected[:, 1])
    np.testing.assert_allclose(points["point"], expected[:, 2:4], atol=1e-5)
    np.testing.assert_allclose(points["normal"], expected[:, 4:6], atol=1e-6)
    np.testing.assert_array_equal(points["builtin"], expected[:, 6:8].astype(np.float32))
    assert np.isnan(points["impulse"]).all()
    engine.solve()
    solved = engine.contacts()
    assert np.isfinite(solved["impulse"]).all()
    np.testing.assert_array_equal(solved["warm_start"], solved["builtin"])  # builtin mode, dt constant


def test_point_keys_are_stable_and_carry_last_steps_impulse(thesis_spec):
    engine = settled(thesis_spec, steps=150)
    engine.collide()
    engine.solve()
    before = engine.contacts()
    engine.collide()
    after = engine.contacts()
    assert len(np.unique(after["key"])) == len(after)
    common, i_before, i_after = np.intersect1d(before["key"], after["key"], return_indices=True)
    assert len(common) > 0.8 * len(after)
    # Box2D's own warm start is the previous step's final impulse of the same point.
    np.testing.assert_array_equal(after["builtin"][i_after], before["impulse"][i_before])
    engine.solve()


@pytest.mark.parametrize(
    "normal, tangent, error",
    [
        (np.zeros(3, np.float32), np.zeros(3, np.float32), ValueError),  # wrong length
        ("float64", "float32", TypeError),  # wrong dtype
        ("nan", "float32", ValueError),  # not finite
        ("inf", "float32", ValueError),
        ("2d", "float32", TypeError),
    ],
)
def test_bad_warm_starts_raise_and_leave_the_step_unchanged(thesis_spec, normal, tangent, error):
    engine, twin = settled(thesis_spec, steps=120), settled(thesis_spec, steps=120)
    n = engine.collide()
    make = {
        "float64": lambda: np.zeros(n, np.float64),
        "float32": lambda: np.zeros(n, np.float32),
        "nan": lambda: np.full(n, np.nan, np.float32),
        "inf": lambda: np.full(n, np.inf, np.float32),
        "2d": lambda: np.zeros((n, 1), np.float32),
    }
    normal = make[normal]() if isinstance(normal, str) else normal
    tangent = make[tangent]() if isinstance(tangent, str) else tangent
    with pytest.raises(error):
        engine.set_warm_start(normal, tangent)
    engine.solve()  # falls back to builtin, exactly like the twin
    twin.step()
    assert engine.bodies().tobytes() == twin.bodies().tobytes()


def test_phase_order_is_enforced(thesis_spec):
    engine = settled(thesis_spec, steps=100)
    with pytest.raises(RuntimeError, match="before Collide"):
        engine.set_warm_start(np.zeros(1, np.float32), np.zeros(1, np.float32))
    with pytest.raises(RuntimeError, match="without Collide"):
        engine.solve()
    engine.collide()
    with pytest.raises(RuntimeError, match="twice"):
        engine.collide()
    with pytest.raises(RuntimeError, match="between Collide"):
        engine.step()
    with pytest.raises(AssertionError):  # Box2D's own lock: no new bodies mid-step
        engine.world.CreateDynamicBody(position=(1, 1))
    engine.solve()
    engine.step()


def test_external_warm_start_is_what_the_solver_starts_from(thesis_spec):
    engine = settled(thesis_spec, steps=120)
    n = engine.collide()
    normal = np.linspace(-1, 1, n, dtype=np.float32)
    tangent = np.full(n, 0.25, np.float32)
    engine.set_warm_start(normal, tangent)
    engine.solve()
    used = engine.contacts()["warm_start"]
    np.testing.assert_array_equal(used[:, 0], np.maximum(normal, 0))  # normal clamped at 0
    np.testing.assert_array_equal(used[:, 1], tangent)


def test_stock_box2d_is_refused_with_a_build_hint(tmp_path):
    fake = tmp_path / "Box2D"
    fake.mkdir()
    (fake / "__init__.py").write_text("__version__ = '2.3.8'\n")
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(tmp_path)!r})
        try:
            import simclient
        except ImportError as e:
            print(e)
            sys.exit(3)
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 3, result.stderr
    assert "make box2d" in result.stdout and "stock" in result.stdout


def _jointed_world():
    """A chain of ten links on revolute joints hung from a static anchor, falling onto discs on a floor."""
    from simclient.engine import Engine, SolverConfig

    world = Box2D.b2World(gravity=(0.0, -9.8))
    floor = world.CreateStaticBody()
    floor.CreateEdgeFixture(vertices=[(-10.0, 0.0), (10.0, 0.0)], friction=0.6)
    previous = floor
    for i in range(10):
        link = world.CreateDynamicBody(position=(0.5 * i, 3.0))
        link.CreatePolygonFixture(box=(0.25, 0.05), density=1.0, friction=0.3)
        world.CreateRevoluteJoint(bodyA=previous, bodyB=link, anchor=(0.5 * i - 0.25, 3.0))
        previous = link
    for i in range(15):
        disc = world.CreateDynamicBody(position=(np.sin(i) * 2.0, 0.3 + 0.45 * i))
        disc.CreateCircleFixture(radius=0.2, density=1.0, friction=0.5)
    return Engine(world, SolverConfig())


def test_a_trial_in_a_world_with_joints_costs_what_the_solve_does_and_puts_the_joints_back():
    tried, plain = _jointed_world(), _jointed_world()
    probed = 0
    for _ in range(200):
        tried.collide()
        if tried.world.contactPointCount:
            normal, tangent = tried.builtin_start()
            cost = tried.trial(np.zeros_like(normal), np.zeros_like(tangent), cap=7)  # a trial of another start
            assert cost <= 7
            cost = tried.trial(normal, tangent)
            tried.set_warm_start(normal, tangent)
            assert tried.solve().velocity_iterations == cost
            probed += 1
        else:
            tried.solve()
        plain.step()
    assert probed > 100
    assert tried.bodies().tobytes() == plain.bodies().tobytes()  # Box2D's own start, given back, bit for bit


def test_the_joints_start_where_the_oracle_left_them_and_are_put_back():
    engine = _jointed_world()
    for _ in range(80):  # the chain falls onto the discs
        engine.step()
    engine.collide()
    assert engine.world.contactPointCount > 0
    normal, tangent = engine.builtin_start()
    as_box2d = engine.joint_state()
    builtin = engine.trial(normal, tangent)
    # Solved to convergence with its joints kept, the step starts from both answers at once:
    # the contacts' and the joints' converged impulses leave next to nothing to sweep.
    converged = engine.oracle(start=(normal, tangent), keep_joints=True)
    converged = np.where(np.isfinite(converged), converged, np.stack([normal, tangent], 1))
    both = engine.trial(np.ascontiguousarray(converged[:, 0]), np.ascontiguousarray(converged[:, 1]))
    engine.set_joint_state(as_box2d)
    contacts_alone = engine.trial(np.ascontiguousarray(converged[:, 0]), np.ascontiguousarray(converged[:, 1]))
    assert both <= 2 < contacts_alone < builtin  # the chain's links wait on their joints' impulses
    # The same joints' start given as impulses: each revolute joint's point impulse is all of it.
    engine.oracle(start=(normal, tangent), keep_joints=True)
    row = {int(b.this): i for i, b in enumerate(engine.world.bodies)}
    reaction = {(row[int(j.bodyA.this)], row[int(j.bodyB.this)]): tuple(j.GetReactionForce(1.0))
                for j in engine.world.joints}  # inv_dt 1: the joint's impulse, N s
    engine.set_joint_state(as_box2d)
    engine.set_revolute_impulses(np.array([reaction[tuple(pair)] for pair in engine.joints()], np.float32))
    assert engine.trial(np.ascontiguousarray(converged[:, 0]), np.ascontiguousarray(converged[:, 1])) == both
    # Put back, the step solves as Box2D's own did.
    engine.set_joint_state(as_box2d)
    assert engine.joint_state() == as_box2d and engine.trial(normal, tangent) == builtin
    with pytest.raises(ValueError, match="joints need"):
        engine.set_revolute_impulses(np.zeros((1, 2), np.float32))


def test_joints_bodies_awake_and_each_points_friction_are_exported():
    engine = _jointed_world()
    joints = engine.joints()
    assert joints.shape == (10, 2) and joints.dtype == np.int32
    assert sorted(map(tuple, joints.tolist())) == [(i, i + 1) for i in range(10)]  # the floor is body 0
    for _ in range(60):
        engine.step()
    engine.collide()
    points, awake = engine.contacts(), engine.awake()
    assert awake.dtype == bool and not awake[0] and awake[1:].all()  # static bodies never are
    links = (points["body_a"] <= 10) & (points["body_b"] <= 10) & (points["body_a"] != points["body_b"])
    floor_discs = (np.minimum(points["body_a"], points["body_b"]) == 0) & (np.maximum(points["body_a"], points["body_b"]) > 10)
    np.testing.assert_allclose(points["friction"][floor_discs], np.sqrt(0.6 * 0.5), rtol=1e-6)  # Box2D's mix
    assert links.any() or floor_discs.any()
    engine.solve()


def test_a_bodys_position_is_its_centre_of_mass():
    from simclient.engine import Engine

    world = Box2D.b2World(gravity=(0.0, 0.0))
    body = world.CreateDynamicBody(position=(1.0, 2.0))
    body.CreatePolygonFixture(box=(0.5, 0.5, (1.0, 0.0), 0.0), density=1.0)  # the box sits off the origin
    np.testing.assert_allclose(Engine(world).bodies()["position"][0], tuple(body.worldCenter), rtol=0, atol=1e-6)
    np.testing.assert_allclose(tuple(body.worldCenter), (2.0, 2.0), atol=1e-6)
