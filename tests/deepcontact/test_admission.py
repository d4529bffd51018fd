"""The admission into the friction cones (deepcontact.admission): the nearest impulses that
move the bodies alike and keep every limit, its compiled rounds against NumPy's, its
factorization and its deadline."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.kinematics import Physics
from simclient.scene import SceneSpec, settled_world
from tests.deepcontact.piles import sliding_pile


def test_cones_keep_what_is_inside_and_take_the_rest_to_the_nearest_edge_or_zero():
    from deepcontact.admission import project_to_cones

    impulses = np.array([[1.0, 0.3], [1.0, 1.0], [-1.0, 0.2], [0.0, -2.0], [2.0, 0.0]])
    mu = np.array([0.5, 0.5, 0.5, 0.5, 0.0])
    # Inside; beyond the edge (1, 0.5): (1 + 0.5) / 1.25 along it; in the polar cone: 0;
    # tangent only: onto the lower edge; no friction: the normal only.
    np.testing.assert_allclose(project_to_cones(impulses, mu),
                               [[1.0, 0.3], [1.2, 0.6], [0.0, 0.0], [0.8, -0.4], [2.0, 0.0]])


def test_the_nearest_admissible_impulses_move_the_bodies_alike_and_keep_every_limit():
    # Box2D's warm start plus the part of this step's correction that moves the bodies
    # leaves friction outside its cone at some points. A self-stress alone (the bodies'
    # motion kept) takes every point back inside; with the points that let go held at 0
    # it finds the solution's own impulses, give or take what moves nothing.
    from deepcontact.admission import nearest_admissible
    from deepcontact.kinematics import body_space_part, contact_jacobian

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


def admission_in_numpy(bodies, points, impulses, mu, open_points, iterations, tolerance=1e-5, rho=100.0, relax=1.0):
    """nearest_admissible's rounds in NumPy, the reference the compiled rounds follow (relax:
    over-relaxed ADMM, the affine step taken to relax x + (1 - relax) z)."""
    from scipy import sparse
    from scipy.sparse.linalg import factorized

    from deepcontact.admission import project_to_cones
    from deepcontact.kinematics import contact_jacobian

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
        pushed = relax * x + (1.0 - relax) * z
        previous, z = z, cones(pushed + scaled)
        scaled += pushed - z
        if max(np.max(np.abs(x - z)), np.max(np.abs(z - previous))) < tolerance:
            break
    return z.reshape(-1, 2)


@pytest.mark.parametrize("rounds, relax", [(1, 1.0), (50, 1.0), (1000, 1.0), (50, 1.6)])
def test_the_compiled_admission_runs_numpys_rounds(rounds, relax):
    from deepcontact.admission import nearest_admissible
    from deepcontact.faces import OPEN, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    solved = solve_on_face(bodies, points, face, mu, Physics.thesis())
    compiled = nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN, iterations=rounds, relax=relax)
    reference = admission_in_numpy(bodies, points, solved, mu, face == OPEN, rounds, relax=relax)
    np.testing.assert_allclose(compiled, reference, atol=1e-9)


def test_over_relaxed_rounds_reach_the_same_admissible_impulses_sooner():
    # Over-relaxation changes the path, not the problem: both end at the one nearest admissible
    # point; pushed past each affine step, a round of rounds gets closer to it.
    from deepcontact.admission import nearest_admissible
    from deepcontact.faces import OPEN, contact_face, solve_on_face

    bodies, points, exact, mu = sliding_pile()
    face = contact_face(exact, mu)
    solved = solve_on_face(bodies, points, face, mu, Physics.thesis())
    admit = lambda rounds, relax: nearest_admissible(bodies, points, solved, mu, open_points=face == OPEN,  # noqa: E731
                                                     iterations=rounds, tolerance=1e-12, relax=relax)
    converged = admit(20000, 1.0)
    np.testing.assert_allclose(admit(20000, 1.6), converged, atol=1e-6)
    assert np.abs(admit(30, 1.6) - converged).max() < np.abs(admit(30, 1.0) - converged).max()


def test_the_admissions_factor_multiplies_back_to_its_gram_in_its_order():
    # P G P^T = C C^T: a sparse Cholesky factor in a minimum degree order of the bodies, each
    # column's diagonal first, far sparser than G's dense factor.
    from scipy import sparse

    from deepcontact import _admission
    from deepcontact.admission import admission_factors
    from deepcontact.kinematics import contact_frame, contact_jacobian_sparse

    bodies, points, _, _ = sliding_pile()
    frame = contact_frame(bodies, points)
    jt_arrays, rows, (lp, li, lx), position = admission_factors(frame)
    jt = contact_jacobian_sparse(frame)
    gram = (jt @ jt.T).toarray()
    gram += 1e-9 * gram.diagonal().max() * np.eye(rows)
    factor = sparse.csc_matrix((lx, li, lp), shape=(rows, rows)).toarray()
    assert not np.triu(factor, 1).any() and (li[lp[:-1]] == np.arange(rows)).all()
    order = np.argsort(position)
    np.testing.assert_allclose(factor @ factor.T, gram[np.ix_(order, order)], atol=1e-10 * np.abs(gram).max())
    assert len(lx) < 0.25 * rows * (rows + 1) / 2
    with pytest.raises(ValueError, match="not a permutation"):
        _admission.gram_cholesky(*jt_arrays, rows, 2 * len(points), np.zeros(rows, np.int32), 1e-9)
    with pytest.raises(ValueError, match="wrong size"):
        _admission.gram_cholesky(*jt_arrays, rows, 2 * len(points), np.arange(rows - 1, dtype=np.int32), 1e-9)


def test_the_body_order_keeps_the_factor_sparser_than_reverse_cuthill_mckee():
    """A minimum degree order of the bodies: the Cholesky factor of J^T J in it has fewer
    entries than in SciPy's reverse Cuthill-McKee order."""
    from scipy import sparse
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    from deepcontact.admission import _body_order
    from deepcontact.kinematics import contact_frame, contact_jacobian_sparse

    bodies, points, _, _ = sliding_pile()
    f = contact_frame(bodies, points)
    row = np.full(len(f.dynamic), -1)
    row[f.dynamic] = np.arange(int(f.dynamic.sum()))
    a, b = row[f.a], row[f.b]
    both = (a >= 0) & (b >= 0)
    n = int(f.dynamic.sum())
    graph = sparse.csr_matrix((np.ones(int(both.sum())), (a[both], b[both])), shape=(n, n))
    jt = contact_jacobian_sparse(f)
    gram = (jt @ jt.T).toarray() + 1e-9 * np.eye(3 * n)

    def entries(body_order):
        order = (3 * np.asarray(body_order)[:, None] + np.arange(3)).ravel()
        return int((np.linalg.cholesky(gram[np.ix_(order, order)]) != 0).sum())

    order = _body_order(f)
    assert sorted(order.tolist()) == list(range(n))
    assert entries(order) < entries(reverse_cuthill_mckee(graph + graph.T, symmetric_mode=True))


def test_impulses_already_admissible_come_back_as_they_are():
    from deepcontact.admission import nearest_admissible, project_to_cones

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

    from deepcontact.admission import nearest_admissible, project_to_cones

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
