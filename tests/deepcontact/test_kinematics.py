"""Contact velocities and effective masses (deepcontact.kinematics) agree with Box2D's own
solver, and the compiled kernel with the NumPy implementation, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.kinematics import BODY_DYNAMIC, Physics, contact_velocities, points_at_rest
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from simclient.scene import SceneSpec, settled_world
from tests.deepcontact.piles import sliding_pile


def test_the_oracles_impulses_leave_no_normal_velocity_at_touching_points():
    # Box2D's converged solution of this step is what the solver drives the
    # relative normal velocity of every touching point to zero with, and the
    # tangent velocity of every sticking one.
    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points, exact = engine.bodies(), engine.contacts(), engine.oracle()
    before = contact_velocities(bodies, points, physics=Physics.thesis())
    after = contact_velocities(bodies, points, exact, Physics.thesis())
    touching = exact[:, 0] > 1e-3
    sticking = touching & (np.abs(exact[:, 1]) < 0.49 * exact[:, 0])  # friction 0.5
    assert touching.sum() > 100 and sticking.sum() > 50
    assert np.abs(before[touching, 0]).max() > 0.05  # gravity alone would push bodies into each other
    assert np.abs(after[touching, 0]).max() < 1e-4 and np.abs(after[sticking, 1]).max() < 1e-4
    assert after[:, 0].min() > -1e-4  # nothing left approaching


def test_one_jacobi_step_from_the_oracles_impulses_changes_next_to_nothing():
    # The converged solution is a fixed point of each point's projected update, so one Jacobi
    # step from it changes nothing beyond the oracle's tolerance; from no warm start, or from
    # Box2D's, the same step changes the loaded points by whole impulses.
    from deepcontact.kinematics import effective_masses, jacobi_change

    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points, exact = engine.bodies(), engine.contacts(), engine.oracle()
    mu = np.full(len(points), 0.5)
    masses = effective_masses(bodies, points)
    at_solution = jacobi_change(bodies, points, exact, mu, Physics.thesis(), masses)
    from_zero = jacobi_change(bodies, points, np.zeros((len(points), 2)), mu, Physics.thesis())
    from_builtin = jacobi_change(bodies, points, points["builtin"], mu, Physics.thesis(), masses)
    assert at_solution < 1e-4 < 0.1 < from_zero
    assert at_solution < from_builtin
    assert jacobi_change(bodies, points[:0], np.zeros((0, 2)), mu[:0]) == 0.0


def test_no_points_and_bad_body_indices():
    engine = settled_world(SceneSpec.thesis(), 901, 1)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    assert contact_velocities(bodies, points[:0]).shape == (0, 2)
    points = np.zeros(1, points.dtype)
    points["body_b"] = len(bodies)
    with pytest.raises(ValueError, match="outside"):
        contact_velocities(bodies, points)


def test_effective_mass_is_the_impulse_that_stops_one_point_alone():
    # An impulse m_eff * 1 N s along a point's normal changes that point's relative
    # normal velocity by exactly 1 m/s (Box2D's normalMass), and likewise the tangent.
    from deepcontact.kinematics import effective_masses

    engine = settled_world(SceneSpec.thesis(), 901, 150)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    masses = effective_masses(bodies, points)
    assert masses.shape == (len(points), 2) and (masses > 0).all()
    before = contact_velocities(bodies, points)
    for k in (0, 1):
        unit = np.zeros((len(points), 2))
        unit[7, k] = masses[7, k]
        change = contact_velocities(bodies, points, unit) - before
        assert change[7, k] == pytest.approx(1.0, abs=1e-6)
    assert effective_masses(bodies, points[:0]).shape == (0, 2)


def test_the_contact_physics_put_impulses_through_the_operator_as_the_velocities_do():
    # m_eff * (J M^-1 J^T) lam from contact_physics's three arrays is the change in relative
    # velocity that contact_velocities sees when lam is applied, times the effective masses.
    from deepcontact.kinematics import contact_physics, effective_masses

    engine = settled_world(SceneSpec.thesis(), 901, 150)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    geometry, masses, inverse = contact_physics(bodies, points)
    assert (geometry.shape, masses.shape, inverse.shape) == ((len(points), 8), (len(points), 2), (len(bodies), 2))
    assert geometry.dtype == masses.dtype == inverse.dtype == np.float32
    np.testing.assert_array_equal(masses, effective_masses(bodies, points).astype(np.float32))
    assert not inverse[bodies["type"] != BODY_DYNAMIC].any() and (inverse[bodies["type"] == BODY_DYNAMIC] > 0).all()
    lam = np.random.default_rng(0).normal(size=(len(points), 2))
    n, t, ra, rb = (geometry[:, k:k + 2].astype(np.float64) for k in (0, 2, 4, 6))
    impulse = lam[:, :1] * n + lam[:, 1:] * t  # on B, its opposite on A
    a, b = points["body_a"], points["body_b"]
    force, torque = np.zeros((len(bodies), 2)), np.zeros(len(bodies))
    for end, sign, r in ((b, 1.0, rb), (a, -1.0, ra)):
        np.add.at(force, end, sign * impulse)
        np.add.at(torque, end, sign * (r[:, 0] * impulse[:, 1] - r[:, 1] * impulse[:, 0]))
    dv, dw = force * inverse[:, :1], torque * inverse[:, 1]

    def at(end, r):
        return dv[end] + dw[end][:, None] * np.stack([-r[:, 1], r[:, 0]], axis=1)

    rel = at(b, rb) - at(a, ra)
    by_hand = np.stack([(rel * n).sum(axis=1), (rel * t).sum(axis=1)], axis=1)
    np.testing.assert_allclose(by_hand, contact_velocities(bodies, points, lam) - contact_velocities(bodies, points),
                               rtol=1e-4, atol=1e-5)


def test_points_at_rest_are_those_whose_dynamic_bodies_move_slower_than_the_threshold():
    bodies = np.zeros(4, BODY_DTYPE)
    bodies["type"] = [0, BODY_DYNAMIC, BODY_DYNAMIC, BODY_DYNAMIC]
    bodies["velocity"] = [[5.0, 0.0], [0.0, 0.001], [0.3, 0.0], [0.0, -0.002]]  # a static body's is never read
    points = np.zeros(4, CONTACT_DTYPE)
    points["body_a"], points["body_b"] = [0, 1, 1, 0], [1, 2, 3, 3]
    assert points_at_rest(bodies, points).tolist() == [True, False, True, True]
    assert points_at_rest(bodies, points, speed=0.5).all()


def test_the_body_space_part_moves_the_bodies_as_the_whole_does_and_the_rest_moves_none():
    # A settled pile is held at more points than its bodies have freedoms, so the
    # step's solution splits into a part the bodies' motion fixes and a self-stress
    # that moves nothing: two warm starts that differ by a self-stress leave the
    # same velocities.
    from deepcontact.kinematics import body_space_part, contact_jacobian

    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points, exact = engine.bodies(), engine.contacts(), engine.oracle().astype(np.float64)
    jt = contact_jacobian(bodies, points)
    n_dynamic = int((bodies["type"] == BODY_DYNAMIC).sum())
    assert jt.shape == (3 * n_dynamic, 2 * len(points))
    assert 2 * len(points) > 3 * n_dynamic  # more unknowns than freedoms: self-stresses exist

    part = body_space_part(bodies, points, exact)
    stress = exact - part
    physics = Physics.thesis()
    assert np.allclose(contact_velocities(bodies, points, part, physics),
                       contact_velocities(bodies, points, exact, physics), atol=1e-9)
    assert np.allclose(jt @ stress.ravel(), 0.0, atol=1e-9)
    assert np.abs(stress).max() > 1e-3  # the pile's solution does carry a self-stress
    assert abs(float((part * stress).sum())) < 1e-9 * float((exact * exact).sum())  # orthogonal parts
    assert body_space_part(bodies, points[:0], exact[:0]).shape == (0, 2)


def test_the_body_space_part_of_some_bodies_moves_them_as_the_whole_does_and_the_others_not_at_all():
    # Splitting a change of motion between the bodies that move and those at rest: the
    # two parts add up to the whole change's body-space part.
    from deepcontact.kinematics import bodies_moving, body_space_part, body_space_part_of, contact_jacobian

    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points, exact = engine.bodies(), engine.contacts(), engine.oracle().astype(np.float64)
    change = exact - points["builtin"]
    moving = bodies_moving(bodies)
    assert 0 < moving.sum() < (bodies["type"] == BODY_DYNAMIC).sum()  # a pile with some bodies still moving
    assert not moving[bodies["type"] != BODY_DYNAMIC].any()

    jt = contact_jacobian(bodies, points)
    rows = np.repeat(moving[bodies["type"] == BODY_DYNAMIC], 3)
    part = body_space_part_of(bodies, points, change, moving)
    whole, pushed = jt @ change.ravel(), jt @ part.ravel()
    np.testing.assert_allclose(pushed[rows], whole[rows], atol=1e-6)
    np.testing.assert_allclose(pushed[~rows], 0.0, atol=1e-6)
    np.testing.assert_allclose(part + body_space_part_of(bodies, points, change, ~moving),
                               body_space_part(bodies, points, change), atol=1e-6)
    assert body_space_part_of(bodies, points[:0], change[:0], moving).shape == (0, 2)


def test_the_sparse_jacobian_is_the_dense_one():
    from deepcontact.kinematics import contact_frame, contact_jacobian, contact_jacobian_sparse

    bodies, points, _, _ = sliding_pile()
    np.testing.assert_allclose(contact_jacobian_sparse(contact_frame(bodies, points)).toarray(),
                               contact_jacobian(bodies, points), atol=1e-12)


def _numpy_velocities(bodies, points, warm=None, physics=Physics()):
    from deepcontact.kinematics import contact_frame

    f = contact_frame(bodies, points)
    a, b, dynamic, n, t, ra, rb = f.a, f.b, f.dynamic, f.n, f.t, f.ra, f.rb
    v = bodies["velocity"].astype(np.float64)
    v *= dynamic[:, None]
    w = bodies["angular_velocity"].astype(np.float64)
    w *= dynamic
    if physics.dt:
        v += np.multiply(physics.dt, physics.gravity) * dynamic[:, None]
    if warm is not None:
        warm = np.asarray(warm, np.float64)
        impulse = warm[:, :1] * n + warm[:, 1:] * t
        idx = np.concatenate([b, a])
        dv = np.stack([np.bincount(idx, np.concatenate([impulse[:, k], -impulse[:, k]]), len(bodies))
                       for k in (0, 1)], axis=1)
        cross = lambda r, u: r[:, 0] * u[:, 1] - r[:, 1] * u[:, 0]  # noqa: E731
        dw = np.bincount(idx, np.concatenate([cross(rb, impulse), -cross(ra, impulse)]), len(bodies))
        v += dv * f.inv_mass[:, None]
        w += dw * f.inv_inertia
    wa, wb = w[a], w[b]
    rel = v[b] - v[a]
    rel[:, 0] += wa * ra[:, 1] - wb * rb[:, 1]
    rel[:, 1] += wb * rb[:, 0] - wa * ra[:, 0]
    return np.stack([rel[:, 0] * n[:, 0] + rel[:, 1] * n[:, 1], rel[:, 0] * t[:, 0] + rel[:, 1] * t[:, 1]], axis=1)


def _numpy_masses(bodies, points):
    from deepcontact.kinematics import contact_frame

    f = contact_frame(bodies, points)
    out = np.empty((len(points), 2))
    for k, d in enumerate((f.n, f.t)):
        ca, cb = f.ra[:, 0] * d[:, 1] - f.ra[:, 1] * d[:, 0], f.rb[:, 0] * d[:, 1] - f.rb[:, 1] * d[:, 0]
        inverse = f.inv_mass[f.a] + f.inv_mass[f.b] + f.inv_inertia[f.a] * ca ** 2 + f.inv_inertia[f.b] * cb ** 2
        ok = inverse > 0
        out[:, k] = np.where(ok, 1.0 / np.where(ok, inverse, 1.0), 0.0)
    return out


def _bits(x):
    return np.ascontiguousarray(x, np.float64).view(np.uint64)


@pytest.mark.parametrize("spec,seed,steps", [(SceneSpec.thesis(), 901, 3), (SceneSpec.thesis(), 902, 150),
                                             (SceneSpec(bodies=200, box_size=(25.0, 15.0), radius=(0.3, 0.5)),
                                              903, 120)])
def test_the_compiled_kernel_gives_the_numpy_implementations_numbers_bit_for_bit(spec, seed, steps):
    from deepcontact.kinematics import contact_quantities, effective_masses

    engine = settled_world(spec, seed, steps)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    assert len(points) > 0
    random = np.random.default_rng(seed).normal(size=(len(points), 2))
    for physics in (Physics(), Physics.thesis()):
        for warm in (None, points["builtin"], random):
            got = contact_velocities(bodies, points, warm, physics)
            assert (_bits(got) == _bits(_numpy_velocities(bodies, points, warm, physics))).all()
        quantities = contact_quantities(bodies, points, physics)
        expected = (_numpy_velocities(bodies, points, None, physics),
                    _numpy_velocities(bodies, points, points["builtin"], physics), _numpy_masses(bodies, points))
        assert all((_bits(q) == _bits(e)).all() for q, e in zip(quantities, expected))
    assert (_bits(effective_masses(bodies, points)) == _bits(_numpy_masses(bodies, points))).all()


def test_records_of_another_layout_are_read_by_field_and_missing_fields_are_named():
    engine = settled_world(SceneSpec.thesis(), 901, 100)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    fields = ["type", "position", "velocity", "angular_velocity", "mass", "inertia"]
    narrow = np.zeros(len(bodies), [(f, BODY_DTYPE.fields[f][0]) for f in fields])
    for f in fields:
        narrow[f] = bodies[f]
    every_other = np.repeat(points, 2)[::2]  # the same records, not contiguous
    assert not every_other.flags.c_contiguous
    assert np.array_equal(contact_velocities(narrow, every_other, points["builtin"]),
                          contact_velocities(bodies, points, points["builtin"]))
    with pytest.raises(ValueError, match="inertia"):
        contact_velocities(narrow[["type", "position", "velocity", "angular_velocity", "mass"]], points)
    with pytest.raises(ValueError, match=r"warm must be \(\d+, 2\)"):
        contact_velocities(bodies, points, np.zeros((len(points), 3)))


def test_the_contact_operator_is_the_jacobians_product():
    from deepcontact.kinematics import contact_frame, contact_jacobian, contact_operator

    bodies, points, _, _ = sliding_pile()
    f = contact_frame(bodies, points)
    jt = contact_jacobian(bodies, points, f)
    inverse = np.stack([f.inv_mass, f.inv_mass, f.inv_inertia], axis=1)[f.dynamic].ravel()
    np.testing.assert_allclose(contact_operator(f), jt.T @ (inverse[:, None] * jt), atol=1e-12)


def test_velocities_before_and_after_are_the_two_calls_of_contact_velocities_in_one():
    from deepcontact.kinematics import velocities_before_and_after

    bodies, points, exact, _ = sliding_pile()
    before, after = velocities_before_and_after(bodies, points, exact, Physics.thesis())
    assert (_bits(before) == _bits(contact_velocities(bodies, points, physics=Physics.thesis()))).all()
    assert (_bits(after) == _bits(contact_velocities(bodies, points, exact, Physics.thesis()))).all()


def test_the_admission_and_the_faces_live_in_modules_of_their_own():
    # One home per name: kinematics keeps velocities, masses and frames; callers import the
    # admission from deepcontact.admission and a face's solve from deepcontact.faces.
    from deepcontact import admission, faces, kinematics

    for name in ("project_to_cones", "nearest_admissible", "admission_factors", "contact_face", "solve_on_face",
                 "face_system", "minimum_norm_solve", "solved_on_labels", "face_residual", "OPEN", "SOLVERS"):
        assert not hasattr(kinematics, name), name
    assert callable(admission.nearest_admissible) and callable(faces.solved_on_labels)
