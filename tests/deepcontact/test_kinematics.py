"""Contact velocities (deepcontact.kinematics) agree with Box2D's own solver."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.kinematics import BODY_DYNAMIC, Physics, contact_velocities, points_at_rest
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from simclient.scene import SceneSpec, settled_world


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


def test_cones_keep_what_is_inside_and_take_the_rest_to_the_nearest_edge_or_zero():
    from deepcontact.kinematics import project_to_cones

    impulses = np.array([[1.0, 0.3], [1.0, 1.0], [-1.0, 0.2], [0.0, -2.0], [2.0, 0.0]])
    mu = np.array([0.5, 0.5, 0.5, 0.5, 0.0])
    # Inside; beyond the edge (1, 0.5): (1 + 0.5) / 1.25 along it; in the polar cone: 0;
    # tangent only: onto the lower edge; no friction: the normal only.
    np.testing.assert_allclose(project_to_cones(impulses, mu),
                               [[1.0, 0.3], [1.2, 0.6], [0.0, 0.0], [0.8, -0.4], [2.0, 0.0]])


def test_closing_relabels_the_open_labels_the_solve_drives_shut_the_wrong_one_and_its_neighbours_with_it():
    # The heaviest pressing point of the answer's own face labelled open: the solve leaves its
    # bodies closing there, and `close` labels it pressing again. But the same wrong solve also
    # drives points shut that the answer leaves open, and they are labelled pressing with it:
    # why the rule costs iterations (docs/results.md, "The solve refined, the classifier trained on").
    from deepcontact.kinematics import FACE_IMPULSE, OPEN, SLIDES_MINUS, SLIDES_PLUS, contact_face, solved_on_labels

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    labels = np.stack([np.where(face != OPEN, FACE_IMPULSE, 0.0),
                       np.where(face == SLIDES_PLUS, FACE_IMPULSE, np.where(face == SLIDES_MINUS, -FACE_IMPULSE, 0.0))], 1)
    heaviest = int(np.argmax(np.where(face != OPEN, exact[:, 0], 0.0)))
    wrong = labels.copy()
    wrong[heaviest] = 0.0
    left_open, _ = solved_on_labels(bodies, points, wrong, mu, Physics.thesis(), rounds=200)
    closed, _ = solved_on_labels(bodies, points, wrong, mu, Physics.thesis(), rounds=200, close=1e-4)
    assert left_open[heaviest, 0] == 0.0 < closed[heaviest, 0]
    assert not left_open[face == OPEN, 0].any() and closed[face == OPEN, 0].any()


def test_the_nearest_admissible_impulses_move_the_bodies_alike_and_keep_every_limit():
    # Box2D's warm start plus the part of this step's correction that moves the bodies
    # leaves friction outside its cone at some points. A self-stress alone (the bodies'
    # motion kept) takes every point back inside; with the points that let go held at 0
    # it finds the solution's own impulses, give or take what moves nothing.
    from deepcontact.kinematics import body_space_part, contact_jacobian, nearest_admissible

    engine = settled_world(SceneSpec.thesis(), 901, 200)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    builtin = points["builtin"].astype(np.float64)
    exact = engine.oracle(start=(points["builtin"][:, 0].copy(), points["builtin"][:, 1].copy())).astype(np.float64)
    mu = np.full(len(points), 0.5)  # the thesis world's friction at every pair
    motion = builtin + body_space_part(bodies, points, exact - builtin)

    def outside(x):
        return np.maximum(np.abs(x[:, 1]) - mu * x[:, 0], 0.0).sum() + np.maximum(-x[:, 0], 0.0).sum()

    assert outside(motion) > 0.1
    admitted = nearest_admissible(bodies, points, motion, mu)
    jt = contact_jacobian(bodies, points)
    assert outside(admitted) < 1e-9
    assert np.abs(jt @ (admitted - motion).ravel()).max() < 1e-4
    np.testing.assert_allclose(nearest_admissible(bodies, points, exact, mu), exact, atol=1e-4)  # admissible already

    released = exact[:, 0] <= 1e-6
    with_release = nearest_admissible(bodies, points, motion, mu, open_points=released)
    assert not with_release[released].any()
    start = lambda x: tuple(np.ascontiguousarray(x[:, k], np.float32) for k in (0, 1))  # noqa: E731
    assert engine.trial(*start(with_release)) <= 3 < engine.trial(*start(admitted)) < engine.trial(*start(motion))
    assert nearest_admissible(bodies, points[:0], exact[:0], mu[:0]).shape == (0, 2)


def sliding_pile():
    """A thesis pile at step 120, with points that let go, stick and slide both ways: its
    bodies, points, the step's solution ((P, 2) N s, the oracle's) and friction (P,)."""
    engine = settled_world(SceneSpec.thesis(), 901, 120)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    b = points["builtin"]
    exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
    return bodies, points, exact, np.full(len(points), 0.5)


def test_a_solution_on_its_own_face_gives_its_motion_and_one_wrong_label_changes_it():
    # Given which points let go, stick or slide (the solution's face), a linear solve
    # leaves every pressing point at rest along its normal and every sticking one along its
    # tangent: the bodies move as the solution moves them. A point said to stick that
    # slides moves them otherwise.
    from deepcontact.kinematics import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    assert {OPEN, STICKS, SLIDES_PLUS, SLIDES_MINUS} <= set(face.tolist())
    solved = solve_on_face(bodies, points, face, mu, Physics.thesis())
    after = contact_velocities(bodies, points, solved, Physics.thesis())
    assert np.abs(after[face != OPEN, 0]).max() < 1e-9 and np.abs(after[face == STICKS, 1]).max() < 1e-9
    sliding = face >= SLIDES_PLUS
    sign = np.where(face == SLIDES_PLUS, 1.0, -1.0)[sliding]
    np.testing.assert_allclose(solved[sliding, 1], sign * 0.5 * solved[sliding, 0])  # at the edge, cone or not
    assert not solved[face == OPEN].any()
    exact_after = contact_velocities(bodies, points, exact, Physics.thesis())
    assert np.abs(after - exact_after).max() < 0.02  # the motion, to the oracle's own tolerance and the cone's share

    wrong = face.copy()
    wrong[np.flatnonzero(sliding)[0]] = STICKS
    moved = contact_velocities(bodies, points, solve_on_face(bodies, points, wrong, mu, Physics.thesis()), Physics.thesis())
    assert np.abs(moved - exact_after).max() > 0.02
    assert solve_on_face(bodies, points[:0], face[:0], mu[:0]).shape == (0, 2)


def test_a_damped_solve_gives_the_same_motion_on_a_right_face_and_stays_bounded_on_a_wrong_one():
    # Damped least squares (a card's face damping) is the exact route's answer where the face
    # is the solution's own; on a face whose system is inconsistent it is no larger.
    from deepcontact.kinematics import OPEN, STICKS, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    exact_route = solve_on_face(bodies, points, face, mu, Physics.thesis())
    damped = solve_on_face(bodies, points, face, mu, Physics.thesis(), damping=1e-10)
    np.testing.assert_allclose(contact_velocities(bodies, points, damped, Physics.thesis()),
                               contact_velocities(bodies, points, exact_route, Physics.thesis()), atol=1e-4)
    wrong = np.where(face == OPEN, STICKS, face)  # every point said to press: points that let go held shut
    assert np.abs(solve_on_face(bodies, points, wrong, mu, Physics.thesis(), damping=1e-10)).max() \
        <= np.abs(solve_on_face(bodies, points, wrong, mu, Physics.thesis())).max() + 1e-9


def test_a_repair_puts_back_a_sliding_point_said_to_stick_but_moves_other_labels():
    # One step of an active-set method on a settled pile: a point said to stick whose friction
    # the admitted solve takes to the cone's edge slides again, the way it slid. The same step
    # reads other labels off the admitted impulses and moves some of them (docs/results.md,
    # "The active set alone": why a repair does not make a classifier's face right).
    from deepcontact.kinematics import (OPEN, SLIDES_PLUS, STICKS, contact_face, face_errors, nearest_admissible,
                                        repair_face, solve_on_face)

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)

    def repaired(labels):
        solved = solve_on_face(bodies, points, labels, mu, Physics.thesis())
        admitted = nearest_admissible(bodies, points, solved, mu, open_points=labels == OPEN)
        return repair_face(bodies, points, admitted, mu, Physics.thesis())

    wrong = face.copy()
    sliding = np.flatnonzero(face >= SLIDES_PLUS)[0]
    wrong[sliding] = STICKS
    assert repaired(wrong)[sliding] == face[sliding]
    moved = face_errors(repaired(face), face)[0]
    assert 0 < moved < 0.1 * len(points)


def admission_in_numpy(bodies, points, impulses, mu, open_points, iterations, tolerance=1e-5, rho=100.0):
    """nearest_admissible's rounds in NumPy, the reference the compiled rounds follow."""
    from scipy import sparse
    from scipy.sparse.linalg import factorized

    from deepcontact.kinematics import contact_jacobian, project_to_cones

    jt = sparse.csr_matrix(contact_jacobian(bodies, points))
    gram = (jt @ jt.T).tocsc()
    ridge = 1e-9 * gram.diagonal().max()
    solve = factorized((gram + ridge * sparse.identity(gram.shape[0], format="csc")).tocsc())
    flat = np.asarray(impulses, np.float64).ravel()
    keep = (~open_points).astype(np.float64)
    cones = lambda x: (project_to_cones(x.reshape(-1, 2), mu) * keep[:, None]).ravel()  # noqa: E731
    z, scaled = cones(flat), np.zeros_like(flat)
    for _ in range(iterations):
        x = (flat + rho * (z - scaled)) / (1.0 + rho)
        x = x - jt.T @ solve(jt @ (x - flat))  # onto J^T x = J^T c
        previous, z = z, cones(x + scaled)
        scaled += x - z
        if max(np.max(np.abs(x - z)), np.max(np.abs(z - previous))) < tolerance:
            break
    return z.reshape(-1, 2)


@pytest.mark.parametrize("rounds", [1, 50, 1000])
def test_the_compiled_admission_runs_numpys_rounds(rounds):
    from deepcontact.kinematics import OPEN, contact_face, nearest_admissible, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    solved = solve_on_face(bodies, points, face, mu, Physics.thesis())
    compiled = nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, iterations=rounds)
    reference = admission_in_numpy(bodies, points, solved, mu, face == OPEN, rounds)
    np.testing.assert_allclose(compiled, reference, atol=1e-9)


def test_the_admissions_factors_multiply_back_to_its_gram_in_their_order():
    # Pr G Pc = L U, as admission_rounds reads SuperLU's factors: here a Cholesky factor in
    # the envelope of a reverse Cuthill-McKee order, L unit lower and U = D L^T.
    from scipy import sparse

    from deepcontact import _kinematics
    from deepcontact.kinematics import admission_factors, contact_frame, contact_jacobian_sparse

    bodies, points, _, _ = sliding_pile()
    frame = contact_frame(bodies, points)
    jt_arrays, rows, (lp, li, ld, up, ui, ud), (perm_r, perm_c) = admission_factors(frame)
    jt = contact_jacobian_sparse(frame)
    gram = (jt @ jt.T).toarray()
    gram += 1e-9 * gram.diagonal().max() * np.eye(rows)
    lower = sparse.csc_matrix((ld, li, lp), shape=(rows, rows)).toarray()
    upper = sparse.csc_matrix((ud, ui, up), shape=(rows, rows)).toarray()
    np.testing.assert_array_equal(np.diag(lower), 1.0)
    assert not np.triu(lower, 1).any() and not np.tril(upper, -1).any()
    np.testing.assert_allclose(lower @ upper, gram[np.argsort(perm_r)][:, np.argsort(perm_c)],
                               atol=1e-10 * np.abs(gram).max())
    args = [*jt_arrays, rows, 2 * len(points)]
    out = [np.empty(rows + 1, np.int32), np.empty(rows * rows, np.int32), np.empty(rows * rows),
           np.empty(rows + 1, np.int32), np.empty(rows * rows, np.int32), np.empty(rows * rows), np.empty(rows, np.int32)]
    with pytest.raises(ValueError, match="not a permutation"):
        _kinematics.envelope_cholesky(*args, np.zeros(rows, np.int32), 1e-9, *out)
    with pytest.raises(ValueError, match="wrong size"):
        _kinematics.envelope_cholesky(*args, np.arange(rows - 1, dtype=np.int32), 1e-9, *out)


def test_the_sparse_jacobian_is_the_dense_one():
    from deepcontact.kinematics import contact_frame, contact_jacobian, contact_jacobian_sparse

    bodies, points, _, _ = sliding_pile()
    np.testing.assert_allclose(contact_jacobian_sparse(contact_frame(bodies, points)).toarray(),
                               contact_jacobian(bodies, points), atol=1e-12)


def test_a_perfect_classifiers_labels_solved_on_give_the_solutions_motion_inside_the_cones():
    # A classifier answers 1 N s along the normal where a point presses and +-1 N s along the
    # tangent where it slides (train-graph --targets face); solved_on_labels reads that as a
    # face, solves the step on it and admits the result: the face route a server serves.
    from deepcontact.kinematics import OPEN, SLIDES_MINUS, SLIDES_PLUS, contact_face, solved_on_labels

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    labels = np.stack([(face != OPEN).astype(float),
                       np.where(face == SLIDES_PLUS, 1.0, np.where(face == SLIDES_MINUS, -1.0, 0.0))], axis=1)
    served, residual = solved_on_labels(bodies, points, labels, mu, Physics.thesis(), pressing=0.5, share=1.0)
    assert not served[face == OPEN].any()
    assert (served[:, 0] >= 0).all() and (np.abs(served[:, 1]) <= mu * served[:, 0] + 1e-9).all()
    after = contact_velocities(bodies, points, served, Physics.thesis())
    exact_after = contact_velocities(bodies, points, exact, Physics.thesis())
    assert np.abs(after - exact_after).max() < 0.02
    # Labels read at a fixed friction: the same where the world's is that friction.
    np.testing.assert_array_equal(served, solved_on_labels(bodies, points, labels, mu, Physics.thesis(),
                                                           pressing=0.5, share=1.0, label_friction=0.5)[0])
    # Read pressing above 2 N s, every point lets go: nothing to solve, nothing served, and the
    # bodies close on each other where the labels say nothing presses: a large residual.
    nothing, wrong = solved_on_labels(bodies, points, labels, mu, Physics.thesis(), pressing=2.0)
    assert not nothing.any()
    assert residual < 0.1 < wrong


def test_face_errors_count_each_kind_of_wrong_label():
    from deepcontact.kinematics import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, face_errors

    reference = np.array([STICKS, STICKS, OPEN, SLIDES_PLUS, SLIDES_PLUS, STICKS, SLIDES_MINUS])
    face = np.array([STICKS, OPEN, STICKS, STICKS, SLIDES_MINUS, SLIDES_PLUS, SLIDES_MINUS])
    # all, open where it presses, presses where open, sticks where it slides, slides where it sticks, the other way
    assert face_errors(face, reference).tolist() == [5, 1, 1, 1, 1, 1]


# The NumPy implementation the compiled kernel (deepcontact/_kinematics.c) replaced: the
# numbers every shipped model was trained on. The kernel must give them bit for bit.

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


def test_the_face_system_is_the_contact_operators_rows_and_columns_on_the_face():
    # face_system sums solve_on_face's system over the point pairs (compiled); it is the dense
    # operator's equation rows, with a sliding point's column its normal one plus +-mu times its
    # tangent one.
    from deepcontact.kinematics import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_frame, contact_operator, face_system

    bodies, points, _, mu = sliding_pile()
    face = np.array([OPEN, STICKS, SLIDES_PLUS, SLIDES_MINUS] * len(points), np.int8)[:len(points)]
    f = contact_frame(bodies, points)
    system, rows, slide = face_system(f, face, mu)
    op = contact_operator(f)
    pressing, sticking = np.flatnonzero(face != OPEN), np.flatnonzero(face == STICKS)
    np.testing.assert_array_equal(rows, np.concatenate([2 * pressing, 2 * sticking + 1]))
    np.testing.assert_array_equal(slide, np.where(face == SLIDES_PLUS, 0.5, np.where(face == SLIDES_MINUS, -0.5, 0.0))[pressing])
    expected = np.concatenate([op[np.ix_(rows, 2 * pressing)] + op[np.ix_(rows, 2 * pressing + 1)] * slide,
                               op[np.ix_(rows, 2 * sticking + 1)]], axis=1)
    np.testing.assert_allclose(system, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())


def test_the_compiled_face_system_refuses_arrays_that_do_not_fit():
    from deepcontact import _kinematics
    from deepcontact.kinematics import contact_frame

    bodies, points, _, _ = sliding_pile()
    f = contact_frame(bodies, points)
    n_points = len(points)
    good = [f.a.astype(np.int64), f.b.astype(np.int64), f.dynamic.astype(np.uint8), f.inv_mass, f.inv_inertia,
            f.n.ravel(), f.t.ravel(), f.ra.ravel(), f.rb.ravel(), np.full(2 * n_points, -1, np.int64),
            np.zeros(n_points)]
    _kinematics.face_system_sum(*good, 0, np.zeros(0))  # no unknowns: nothing to sum
    with pytest.raises(ValueError, match="wrong size"):
        _kinematics.face_system_sum(*good, 2, np.zeros(3))
    outside = list(good)
    outside[9] = np.full(2 * n_points, 5, np.int64)  # an unknown past the system's 2 columns
    with pytest.raises(ValueError, match="out of range"):
        _kinematics.face_system_sum(*outside, 2, np.zeros(4))


def test_the_dual_solve_is_the_minimum_norm_solution_of_a_singular_consistent_system_and_declines_an_inconsistent_one():
    from deepcontact.kinematics import minimum_norm_solve

    rng = np.random.default_rng(3)
    left, right = rng.standard_normal((60, 45)), rng.standard_normal((45, 60))
    system = left @ right  # rank 45 of 60: singular, as a face's system is in a pile
    rhs = system @ rng.standard_normal(60)  # consistent
    # The pseudo-inverse with the rank read right (gelsy at LAPACK's rcond of machine precision
    # takes this product's rounding for 15 more singular values, and its answer is not the least).
    expected = np.linalg.pinv(system, rcond=1e-10) @ rhs
    np.testing.assert_allclose(minimum_norm_solve(system, rhs), expected, rtol=1e-7, atol=1e-9)
    inconsistent = rhs + np.linalg.svd(system)[0][:, -1]  # plus a direction off its range
    assert minimum_norm_solve(system, inconsistent) is None
    np.testing.assert_array_equal(minimum_norm_solve(np.zeros((3, 3)), np.zeros(3)), np.zeros(3))
    assert minimum_norm_solve(np.zeros((0, 0)), np.zeros(0)).shape == (0,)


def test_the_dual_solve_refines_its_way_to_the_pseudo_inverse_where_squaring_loses_the_weak_directions():
    from deepcontact.kinematics import minimum_norm_solve

    rng = np.random.default_rng(4)
    u, _ = np.linalg.qr(rng.standard_normal((80, 80)))
    v, _ = np.linalg.qr(rng.standard_normal((80, 80)))
    # A face's spectrum: singular values from 1 down to 1e-6 (S S^T's condition 1e12), then a null space.
    sigma = np.concatenate([np.logspace(0, -6, 70), np.zeros(10)])
    system = (u * sigma) @ v.T
    rhs = system @ rng.standard_normal(80)
    expected = np.linalg.pinv(system, rcond=1e-10) @ rhs
    np.testing.assert_allclose(minimum_norm_solve(system, rhs), expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())


def test_the_compiled_gram_of_a_mostly_zero_system_is_its_product_with_its_transpose():
    from deepcontact import _kinematics

    rng = np.random.default_rng(5)
    system = rng.standard_normal((40, 40)) * (rng.random((40, 40)) < 0.05)
    gram = np.empty((40, 40))
    _kinematics.sparse_gram(system, 40, gram)
    np.testing.assert_allclose(gram, system @ system.T, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="wrong size"):
        _kinematics.sparse_gram(system, 40, np.empty((40, 39)))


def test_both_solvers_give_a_solution_its_own_faces_motion():
    from deepcontact.kinematics import OPEN, STICKS, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    gelsy, dual = (solve_on_face(bodies, points, face, mu, Physics.thesis(), solver=s) for s in ("gelsy", "dual"))
    after = contact_velocities(bodies, points, dual, Physics.thesis())
    assert np.abs(after[face != OPEN, 0]).max() < 1e-9 and np.abs(after[face == STICKS, 1]).max() < 1e-9
    np.testing.assert_allclose(dual, gelsy, atol=1e-6 * np.abs(gelsy).max())
    with pytest.raises(ValueError, match="solver"):
        solve_on_face(bodies, points, face, mu, Physics.thesis(), solver="svd")


def test_impulses_already_admissible_come_back_as_they_are():
    from deepcontact.kinematics import nearest_admissible, project_to_cones

    bodies, points, exact, mu = sliding_pile()
    inside = project_to_cones(exact, mu)
    np.testing.assert_array_equal(nearest_admissible(bodies, points, inside, mu), inside)
    held = np.zeros(len(points), bool)
    held[0] = True
    if inside[0].any():  # a point held open but pressing: not admissible as it is, so moved
        assert not nearest_admissible(bodies, points, inside, mu, open_points=held)[0].any()


def test_the_admission_stops_its_rounds_at_its_deadline():
    # until: no round begins after it (the clock read every eight rounds): a deadline already
    # past leaves the first eight rounds' answer, which is inside every cone all the same.
    import time

    from deepcontact.kinematics import nearest_admissible, project_to_cones

    bodies, points, exact, mu = sliding_pile()
    start = exact * 1.3 + 0.05  # off the cones somewhere: the rounds have work to do
    unbounded = nearest_admissible(bodies, points, start, mu, iterations=5000, tolerance=1e-12)
    late = nearest_admissible(bodies, points, start, mu, iterations=5000, tolerance=1e-12,
                              until=time.perf_counter() - 1.0)
    eight = nearest_admissible(bodies, points, start, mu, iterations=8, tolerance=1e-12)
    np.testing.assert_array_equal(late, eight)
    assert not np.array_equal(late, unbounded)
    np.testing.assert_array_equal(project_to_cones(late, mu), late)
    far = nearest_admissible(bodies, points, start, mu, iterations=5000, tolerance=1e-12,
                             until=time.perf_counter() + 3600.0)
    np.testing.assert_array_equal(far, unbounded)
