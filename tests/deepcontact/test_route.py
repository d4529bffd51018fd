"""The face route after its classifier in one compiled call (deepcontact.faces.route_compiled),
against the same route run piece by piece (deepcontact.faces.solved_on_labels)."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.faces import FACE_IMPULSE, OPEN, SLIDES_MINUS, SLIDES_PLUS, route_compiled, solved_on_labels
from deepcontact.kinematics import Physics
from tests.deepcontact.piles import sliding_pile


def labels_of(exact, mu, rng, wrong=0.0):
    """A classifier's answer for the solution's own labels (about 1 N s where a point presses,
    +-1 N s where it slides), a share `wrong` of the points' answers noised."""
    from deepcontact.faces import contact_face

    face = contact_face(exact, mu)
    labels = np.zeros((len(face), 2))
    labels[face != OPEN, 0] = FACE_IMPULSE
    labels[face == SLIDES_PLUS, 1] = FACE_IMPULSE
    labels[face == SLIDES_MINUS, 1] = -FACE_IMPULSE
    noised = rng.random(len(face)) < wrong
    labels[noised] += rng.normal(0.0, 0.8, (int(noised.sum()), 2))
    return labels


@pytest.mark.parametrize("wrong", [0.0, 0.05, 0.2])
@pytest.mark.parametrize("rounds", [1, 60])
def test_the_compiled_route_is_the_route_piece_by_piece(wrong, rounds):
    bodies, points, exact, mu = sliding_pile()
    labels = labels_of(exact, mu, np.random.default_rng(int(100 * wrong) + rounds), wrong)
    settings = dict(physics=Physics.thesis(), pressing=0.75, share=1.0, rounds=rounds)
    reference, residual = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
    compiled = route_compiled(bodies, points, labels, mu, **settings)
    if compiled is None:  # the compiled dual declined: the piecewise route answered by gelsy
        return
    scale = max(1.0, np.abs(reference).max())
    np.testing.assert_allclose(compiled.impulses, reference, atol=1e-8 * scale)
    assert compiled.residual == pytest.approx(residual, rel=1e-6, abs=1e-12)
    assert compiled.solve_seconds > 0 and compiled.admit_seconds >= 0 and 0 <= compiled.rounds_run <= rounds


@pytest.mark.parametrize("rho", [30.0, 1000.0])
def test_the_compiled_route_admits_at_the_penalty_it_is_given(rho):
    # The admission's ADMM penalty reaches the compiled rounds as it reaches the piecewise ones:
    # cut at a few rounds, the answers at two penalties part, each the same in both routes.
    bodies, points, exact, mu = sliding_pile()
    labels = labels_of(exact, mu, np.random.default_rng(3), 0.2)
    settings = dict(physics=Physics.thesis(), pressing=0.75, share=1.0, rounds=8, relax=1.6)
    reference, _ = solved_on_labels(bodies, points, labels, mu, solver="dual", rho=rho, **settings)
    compiled = route_compiled(bodies, points, labels, mu, rho=rho, **settings)
    if compiled is None:
        return
    np.testing.assert_allclose(compiled.impulses, reference, atol=1e-8 * max(1.0, np.abs(reference).max()))
    other = route_compiled(bodies, points, labels, mu, rho=100.0, **settings)
    if compiled.rounds_run > 0:  # the rounds ran (not admitted as solved): the penalty shows
        assert not np.allclose(other.impulses, compiled.impulses)


def test_the_compiled_route_reads_labels_at_a_friction_of_its_own():
    bodies, points, exact, mu = sliding_pile()
    labels = labels_of(exact, mu, np.random.default_rng(7), 0.1)
    for friction in (0.3, 0.9):
        reference, _ = solved_on_labels(bodies, points, labels, mu, Physics.thesis(), 0.75, 1.0, 60,
                                        label_friction=friction, solver="dual")
        compiled = route_compiled(bodies, points, labels, mu, Physics.thesis(), 0.75, 1.0, friction, 60)
        if compiled is not None:
            np.testing.assert_allclose(compiled.impulses, reference, atol=1e-8 * max(1.0, np.abs(reference).max()))


def test_the_compiled_route_refuses_what_does_not_fit():
    from deepcontact import _route

    bodies, points, exact, mu = sliding_pile()
    with pytest.raises(ValueError, match="wrong size"):
        route_compiled(bodies, points, np.zeros((len(points) + 1, 2)), mu)
    broken = points.copy()
    broken["body_b"][0] = len(bodies) + 3
    with pytest.raises(ValueError, match="outside"):
        route_compiled(bodies, broken, np.zeros((len(points), 2)), mu)
    none = route_compiled(bodies, points[:0], np.zeros((0, 2)), mu[:0])
    assert none is not None and none.impulses.shape == (0, 2) and _route.SERVED == 0


def test_a_geometry_prepared_ahead_gives_the_same_route_and_fits_only_its_step():
    from deepcontact.faces import prepare_route

    bodies, points, exact, mu = sliding_pile()
    labels = labels_of(exact, mu, np.random.default_rng(3), 0.1)
    prepared = prepare_route(bodies, points, Physics.thesis())
    alone = route_compiled(bodies, points, labels, mu, Physics.thesis(), 0.75, 1.0, None, 60)
    ahead = route_compiled(bodies, points, labels, mu, Physics.thesis(), 0.75, 1.0, None, 60, prepared=prepared)
    np.testing.assert_array_equal(ahead.impulses, alone.impulses)
    assert ahead.residual == alone.residual
    with pytest.raises(ValueError, match="another step"):
        route_compiled(bodies, points[:-1], labels[:-1], mu[:-1], Physics.thesis(), prepared=prepared)
