"""A step solved on a face of its limits (deepcontact.faces): the solution's own face gives its
motion, the face route's labels read, solved and admitted, the compiled system and gram
against NumPy's dense products."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.kinematics import Physics, contact_velocities
from tests.deepcontact.piles import sliding_pile


def test_closing_relabels_the_open_labels_the_solve_drives_shut_the_wrong_one_and_its_neighbours_with_it():
    # The heaviest pressing point of the answer's own face labelled open: the solve leaves its
    # bodies closing there, and `close` labels it pressing again. But the same wrong solve also
    # drives points shut that the answer leaves open, and they are labelled pressing with it:
    # why the rule costs iterations (docs/results.md, "The solve refined, the classifier trained on").
    from deepcontact.faces import OPEN, contact_face, face_labels, solved_on_labels

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    labels = face_labels(face)
    heaviest = int(np.argmax(np.where(face != OPEN, exact[:, 0], 0.0)))
    wrong = labels.copy()
    wrong[heaviest] = 0.0
    left_open, _ = solved_on_labels(bodies, points, wrong, mu, Physics.thesis(), rounds=200)
    closed, _ = solved_on_labels(bodies, points, wrong, mu, Physics.thesis(), rounds=200, close=1e-4)
    assert left_open[heaviest, 0] == 0.0 < closed[heaviest, 0]
    assert not left_open[face == OPEN, 0].any() and closed[face == OPEN, 0].any()


def test_a_solution_on_its_own_face_gives_its_motion_and_one_wrong_label_changes_it():
    # Given which points let go, stick or slide (the solution's face), a linear solve
    # leaves every pressing point at rest along its normal and every sticking one along its
    # tangent: the bodies move as the solution moves them. A point said to stick that
    # slides moves them otherwise.
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_face, solve_on_face

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
    from deepcontact.faces import OPEN, STICKS, contact_face, solve_on_face

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
    from deepcontact.admission import nearest_admissible
    from deepcontact.faces import OPEN, SLIDES_PLUS, STICKS, contact_face, face_errors, repair_face, solve_on_face

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


def test_a_repair_measures_a_landing_points_closing_speed_from_its_bounce():
    # A tall box lands flat at 3 m/s on two points, restitution 0.5: Box2D's solver holds each
    # point at half its closing speed, moving apart. Pushed at one corner alone, hard enough that
    # the other corner rises at 0.5 m/s, that corner is still closing on its bounce (1.55 m/s):
    # read with the restitution, it presses; read at rest, it lets go.
    import Box2D

    from deepcontact.faces import OPEN, STICKS, repair_face
    from simclient.engine import Engine, SolverConfig

    world = Box2D.b2World(gravity=(0.0, -10.0))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-5.0, 0.0), (5.0, 0.0)], friction=0.5)
    box = world.CreateDynamicBody(position=(0.0, 1.005), linearVelocity=(0.0, -3.0))
    box.CreatePolygonFixture(box=(0.25, 1.0), density=1.0, friction=0.5, restitution=0.5)
    engine = Engine(world, SolverConfig())
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    assert len(points) == 2
    physics = Physics(0.01, (0.0, -10.0))
    mu, restitution = np.full(2, 0.5), engine.point_restitution(points)
    pushed, other = np.argsort(points["point"][:, 0])  # the left corner pushed, the right one left open
    unit = np.zeros((2, 2))
    unit[pushed, 0] = 1.0
    before = contact_velocities(bodies, points, None, physics)[other, 0]
    per_n_s = contact_velocities(bodies, points, unit, physics)[other, 0] - before
    assert before < -3.0 and per_n_s > 0
    impulses = unit * (0.5 - before) / per_n_s
    np.testing.assert_allclose(contact_velocities(bodies, points, impulses, physics)[other, 0], 0.5)
    assert repair_face(bodies, points, impulses, mu, physics)[other] == OPEN
    assert repair_face(bodies, points, impulses, mu, physics, restitution=restitution)[other] == STICKS


def test_a_perfect_classifiers_labels_solved_on_give_the_solutions_motion_inside_the_cones():
    # A classifier answers 1 N s along the normal where a point presses and +-1 N s along the
    # tangent where it slides (train-graph --targets face); solved_on_labels reads that as a
    # face, solves the step on it and admits the result: the face route a server serves.
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, contact_face, solved_on_labels

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


def test_a_face_written_as_labels_reads_back_as_the_same_face():
    # How a classifier's targets and a held step's new points (server.held_labels) write a face.
    from deepcontact.faces import FACE_IMPULSE, OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, contact_face, face_labels

    face = np.array([OPEN, STICKS, SLIDES_PLUS, SLIDES_MINUS], np.int8)
    labels = face_labels(face)
    assert labels.tolist() == [[0, 0], [FACE_IMPULSE, 0], [FACE_IMPULSE, FACE_IMPULSE], [FACE_IMPULSE, -FACE_IMPULSE]]
    mu = np.array([0.2, 0.5, 0.9, 1.0])
    assert np.array_equal(contact_face(labels, mu, pressing=0.75, share=0.99), face)


def test_face_errors_count_each_kind_of_wrong_label():
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, face_errors

    reference = np.array([STICKS, STICKS, OPEN, SLIDES_PLUS, SLIDES_PLUS, STICKS, SLIDES_MINUS])
    face = np.array([STICKS, OPEN, STICKS, STICKS, SLIDES_MINUS, SLIDES_PLUS, SLIDES_MINUS])
    # all, open where it presses, presses where open, sticks where it slides, slides where it sticks, the other way
    assert face_errors(face, reference).tolist() == [5, 1, 1, 1, 1, 1]


def test_the_face_system_is_the_contact_operators_rows_and_columns_on_the_face():
    # face_system sums solve_on_face's system over the point pairs (compiled); it is the dense
    # operator's equation rows, with a sliding point's column its normal one plus +-mu times its
    # tangent one.
    from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, STICKS, face_system
    from deepcontact.kinematics import contact_frame, contact_operator

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
    from deepcontact import _faces
    from deepcontact.kinematics import contact_frame

    bodies, points, _, _ = sliding_pile()
    f = contact_frame(bodies, points)
    n_points = len(points)
    good = [f.a.astype(np.int64), f.b.astype(np.int64), f.dynamic.astype(np.uint8), f.inv_mass, f.inv_inertia,
            f.n.ravel(), f.t.ravel(), f.ra.ravel(), f.rb.ravel(), np.full(2 * n_points, -1, np.int64),
            np.zeros(n_points)]
    indptr, indices, data = _faces.face_system_sum(*good, 0)  # no unknowns: nothing to sum
    assert np.frombuffer(indptr, np.int32).tolist() == [0] and not indices and not data
    with pytest.raises(ValueError, match="wrong size"):
        _faces.face_system_sum(*good[:-1], np.zeros(n_points + 1), 2)
    outside = list(good)
    outside[9] = np.full(2 * n_points, 5, np.int64)  # an unknown past the system's 2 columns
    with pytest.raises(ValueError, match="out of range"):
        _faces.face_system_sum(*outside, 2)


def test_the_dual_solve_is_the_minimum_norm_solution_of_a_singular_consistent_system_and_declines_an_inconsistent_one():
    from deepcontact.faces import minimum_norm_solve

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
    from deepcontact.faces import minimum_norm_solve

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
    from deepcontact import _faces

    rng = np.random.default_rng(5)
    system = rng.standard_normal((40, 40)) * (rng.random((40, 40)) < 0.05)
    gram = np.empty((40, 40))
    _faces.sparse_gram(system, 40, gram)
    np.testing.assert_allclose(gram, system @ system.T, rtol=1e-13, atol=1e-13)
    with pytest.raises(ValueError, match="wrong size"):
        _faces.sparse_gram(system, 40, np.empty((40, 39)))


def test_both_solvers_give_a_solution_its_own_faces_motion():
    from deepcontact.faces import OPEN, STICKS, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    gelsy, dual = (solve_on_face(bodies, points, face, mu, Physics.thesis(), solver=s) for s in ("gelsy", "dual"))
    after = contact_velocities(bodies, points, dual, Physics.thesis())
    assert np.abs(after[face != OPEN, 0]).max() < 1e-9 and np.abs(after[face == STICKS, 1]).max() < 1e-9
    np.testing.assert_allclose(dual, gelsy, atol=1e-6 * np.abs(gelsy).max())
    with pytest.raises(ValueError, match="solver"):
        solve_on_face(bodies, points, face, mu, Physics.thesis(), solver="svd")


def test_the_face_route_is_its_solve_then_its_admission():
    # solved_on_labels is read_and_solve (the labels read, the step solved on them) then
    # admit_solved (the admission, the residual): a server times the two halves apart and must
    # serve the same numbers as the whole.
    from deepcontact.faces import (FACE_IMPULSE, OPEN, SLIDES_MINUS, SLIDES_PLUS, admit_solved, contact_face,
                                   read_and_solve, solved_on_labels)
    from deepcontact.kinematics import contact_frame

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    sliding = np.where(face == SLIDES_PLUS, FACE_IMPULSE, np.where(face == SLIDES_MINUS, -FACE_IMPULSE, 0.0))
    labels = np.stack([np.where(face != OPEN, FACE_IMPULSE, 0.0), sliding], 1)
    labels[np.argmax(exact[:, 0])] = 0.0  # one wrong label: the admission has work to do
    for close in (None, 1e-4):
        whole, residual = solved_on_labels(bodies, points, labels, mu, Physics.thesis(), 0.5, 1.0, 200, close=close)
        frame = contact_frame(bodies, points)
        read, solved = read_and_solve(bodies, points, labels, mu, Physics.thesis(), 0.5, 1.0, frame=frame, close=close)
        halves, halves_residual = admit_solved(bodies, points, read, solved, mu, Physics.thesis(), 200, frame)
        np.testing.assert_array_equal(halves, whole)
        assert halves_residual == residual


def test_the_sparse_dual_solve_agrees_with_the_dense_one_on_a_piles_faces():
    """The face route's solve on S's nonzeros (a sparse Cholesky of S S^T in a reverse
    Cuthill-McKee order) gives the dense factorization's answer, and the face system as CSR
    holds the dense sum's numbers to the bit."""
    from deepcontact import faces
    from deepcontact.faces import contact_face, face_system, face_system_sparse
    from deepcontact.kinematics import contact_frame

    bodies, points, exact, mu = sliding_pile()
    f = contact_frame(bodies, points)
    velocity = contact_velocities(bodies, points, physics=Physics.thesis()).ravel()
    face = contact_face(exact, mu)  # the solution's own: a consistent system
    sparse, rows, _ = face_system_sparse(f, face, mu)
    dense, _, _ = face_system(f, face, mu)
    np.testing.assert_array_equal(sparse.dense(), dense)
    assert len(sparse.data) < 0.1 * dense.size  # a pile's system is mostly zeros
    rhs = -velocity[rows]
    reference = np.linalg.pinv(dense, rcond=1e-10) @ rhs
    np.testing.assert_allclose(faces.minimum_norm_solve(sparse, rhs), reference, atol=1e-10 * np.abs(reference).max())


def test_the_dual_solve_meets_a_pyramid_of_boxes_whose_system_is_half_redundant():
    """A pile of boxes held at two points to each face on a face: the face system's rank is
    about half its unknowns, and rounding leaves S S^T's null-space pivots below the least
    ridge. The compiled solve grows its ridge there and still gives the pseudo-inverse's
    answer, and the route on the solution's own labels serves the solution: one sweep."""
    from deepcontact import faces
    from deepcontact.faces import DUAL_OPTIMALITY, DUAL_REFINEMENTS, DUAL_RIDGE, contact_face, face_system_sparse
    from deepcontact.kinematics import contact_frame
    from tests.deepcontact.piles import pyramid_of_boxes

    bodies, points, exact, mu = pyramid_of_boxes()
    face = contact_face(exact, mu, pressing=1e-6, share=0.99)
    sparse, rows, _ = face_system_sparse(contact_frame(bodies, points), face, mu)
    dense = sparse.dense()
    rank = np.linalg.matrix_rank(dense, tol=1e-10 * np.linalg.norm(dense, 2))
    assert sparse.m > 300 and rank < 0.7 * sparse.m
    rhs = -contact_velocities(bodies, points, physics=Physics.thesis()).ravel()[rows]
    x = np.empty(sparse.m)
    status = faces._compiled.dual_solve(sparse.indptr, sparse.indices, sparse.data, rhs, DUAL_RIDGE,
                                        DUAL_REFINEMENTS, DUAL_OPTIMALITY, x)
    assert status == 0  # solved compiled, not by the dense LU
    reference = np.linalg.pinv(dense, rcond=1e-10) @ rhs
    np.testing.assert_allclose(x, reference, atol=1e-8 * np.abs(reference).max())
    served = faces.route_compiled(bodies, points, exact, mu, Physics.thesis(), pressing=1e-6, share=0.99, rounds=40)
    assert served is not None and served.residual < 0.01  # the cards serve up to 0.3
