"""The face route after its classifier in one compiled call (deepcontact.faces.route_compiled),
against the same route run piece by piece (deepcontact.faces.solved_on_labels)."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.faces import FACE_IMPULSE, OPEN, SLIDES_MINUS, SLIDES_PLUS, route_compiled, solved_on_labels
from deepcontact.kinematics import Physics
from tests.deepcontact.piles import pyramid_of_boxes, sliding_pile


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


def test_a_carried_admission_begins_where_the_same_points_ended():
    """A stream's admission goes on where each point's stopped on the step before
    (admission.AdmissionCarry): with nothing kept it is the cold route, numbers and all; begun
    from the state a long run ended in, its few rounds stay there; a point it never saw begins
    cold."""
    from deepcontact.admission import AdmissionCarry

    bodies, points, exact, mu = sliding_pile()
    labels = labels_of(exact, mu, np.random.default_rng(5), 0.2)
    settings = dict(physics=Physics.thesis(), pressing=0.75, share=1.0, relax=1.6, rho=1000.0)
    cold = route_compiled(bodies, points, labels, mu, rounds=8, **settings)
    assert cold is not None and cold.rounds_run > 0  # the rounds ran: there is a state to carry
    carry = AdmissionCarry()
    first = carry.begin(points, 10)
    again = route_compiled(bodies, points, labels, mu, rounds=8, carry=first, **settings)
    np.testing.assert_array_equal(again.impulses, cold.impulses)
    np.testing.assert_array_equal(first[2][:, :2], cold.impulses)  # z ends at the answer served
    # The state of a long run, carried into the next step: its rounds begin at its end.
    long = AdmissionCarry()
    args = long.begin(points, 10)
    converged = route_compiled(bodies, points, labels, mu, rounds=2000, carry=args, **settings)
    long.keep(points, 10, args)
    went_on = route_compiled(bodies, points, labels, mu, rounds=8, carry=long.begin(points, 11), **settings)
    gap_cold = np.abs(cold.impulses - converged.impulses).max()
    assert np.abs(went_on.impulses - converged.impulses).max() < 0.2 * gap_cold
    # A gap in the steps, or points it never saw: cold again.
    after_gap = route_compiled(bodies, points, labels, mu, rounds=8, carry=long.begin(points, 13), **settings)
    np.testing.assert_array_equal(after_gap.impulses, cold.impulses)
    renamed = points.copy()
    renamed["key"] += np.uint64(1) << np.uint64(40)
    unseen = route_compiled(bodies, renamed, labels, mu, rounds=8, carry=long.begin(renamed, 11), **settings)
    np.testing.assert_array_equal(unseen.impulses, cold.impulses)


def test_a_carry_of_the_wrong_size_is_refused():
    from deepcontact.admission import AdmissionCarry

    bodies, points, exact, mu = sliding_pile()
    keys, kept, state, dual = AdmissionCarry().begin(points, 0)
    with pytest.raises(ValueError, match="wrong size"):
        route_compiled(bodies, points, np.zeros((len(points), 2)), mu, carry=(keys, kept, state[:-1], dual))
    with pytest.raises(ValueError, match="wrong size"):
        route_compiled(bodies, points, np.zeros((len(points), 2)), mu,
                       carry=(np.zeros(3, np.uint64), np.zeros((2, 4)), state, dual))


def test_the_solvers_sweeps_from_the_solution_change_nothing_and_from_nothing_change_much():
    """sweep_changes plays the solver's sequential impulses on the server's copy of the step:
    from the impulses the engine's own solve converged to, a sweep changes them by about its
    stopping threshold; from no impulses at all, a pile's first sweep moves them by about a
    body's weight over the step, and later sweeps by less."""
    from deepcontact.faces import sweep_changes
    from deepcontact.kinematics import jacobi_change

    bodies, points, exact, mu = sliding_pile()
    physics = Physics.thesis()
    zero = np.zeros_like(exact)
    first, later = (sweep_changes(bodies, points, np.stack([exact, zero]), mu, physics, sweeps) for sweeps in (1, 8))
    assert first[0] < 1e-3 and later[0] < 1e-3
    weight_step = float(bodies["mass"][bodies["type"] == 2].max()) * 9.8 * physics.dt
    assert first[1] > 0.2 * weight_step
    assert later[1] < first[1]
    # One Jacobi step is the crude form: the same verdict on these two starts.
    assert (jacobi_change(bodies, points, exact, mu, physics) < jacobi_change(bodies, points, zero, mu, physics)) \
        == (first[0] < first[1])
    with pytest.raises(ValueError, match="starts"):
        sweep_changes(bodies, points, exact, mu, physics)


def test_the_sweeps_to_the_stopping_rule_are_where_the_replica_first_changes_nothing_by_more():
    """sweeps_to_stop counts the sweeps each start takes to the client's stopping rule (the
    first sweep that changes no impulse by more than the tolerance): from the converged impulses
    one, from nothing more; where a start does not stop within `most` sweeps its count is most + 1
    and its change that of sweep `most`, as sweep_changes gives it."""
    from deepcontact.faces import sweep_changes, sweeps_to_stop

    bodies, points, exact, mu = sliding_pile()
    physics = Physics.thesis()
    starts = np.stack([exact, np.zeros_like(exact)])
    counts, changes = sweeps_to_stop(bodies, points, starts, mu, physics, 1e-3, 500)
    assert counts[0] == 1 and changes[0] <= 1e-3
    cold = int(counts[1])
    assert 1 < cold <= 500 and changes[1] <= 1e-3
    assert sweep_changes(bodies, points, starts, mu, physics, cold - 1)[1] > 1e-3  # the sweep before did not stop
    np.testing.assert_allclose(sweep_changes(bodies, points, starts, mu, physics, cold)[1], changes[1])
    counts, changes = sweeps_to_stop(bodies, points, starts, mu, physics, 1e-15, 5)
    np.testing.assert_array_equal(counts, [6, 6])
    np.testing.assert_array_equal(changes, sweep_changes(bodies, points, starts, mu, physics, 5))
    with pytest.raises(ValueError, match="tolerance"):
        sweeps_to_stop(bodies, points, starts, mu, physics, 0.0, 5)


def test_the_sweeps_solve_a_boxs_two_points_as_one_block_as_box2d_does():
    """A box resting on another meets it at two points of one manifold, which Box2D solves
    together (its block solver): from the impulses the engine's own solve converged to, the
    replica's sweeps change them by about its threshold, as on a pile of discs; from no
    impulses, by about the boxes' weight over the step."""
    from deepcontact.faces import sweep_changes
    from deepcontact.kinematics import Physics
    from simclient.engine import Engine, SolverConfig
    from simclient.worlds import build_user_world

    world, _ = build_user_world("examples/stack.py:build", 901)
    engine = Engine(world, SolverConfig())
    for _ in range(60):  # the stack settles (before it falls asleep)
        engine.collide()
        engine.solve()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    pairs = (points["body_a"][1:] == points["body_a"][:-1]) & (points["body_b"][1:] == points["body_b"][:-1])
    assert pairs.any()  # two-point manifolds, consecutive in the export
    b = points["builtin"]
    exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
    mu = points["friction"].astype(np.float64)
    physics = Physics(engine.config.dt, (0.0, -9.8))
    settled, cold = sweep_changes(bodies, points, np.stack([exact, np.zeros_like(exact)]), mu, physics, 4)
    assert settled < 1e-3 < cold


def test_the_sweeps_see_a_kinematic_body_move_as_it_was_sent():
    """A box riding a lift (a kinematic body rising at 0.4 m/s, which no impulse moves): the
    points' relative velocities take the lift's own velocity, so from the impulses the engine's
    solve converged to, the replica's sweeps change them by about its threshold; a lift taken
    for still would see the box leaving it and drop its weight."""
    import Box2D

    from deepcontact.faces import sweep_changes
    from simclient.engine import Engine, SolverConfig

    world = Box2D.b2World(gravity=(0.0, -9.8))
    lift = world.CreateKinematicBody(position=(0.0, 0.0), linearVelocity=(0.0, 0.4))
    lift.CreatePolygonFixture(box=(2.0, 0.2), friction=0.6)
    rider = world.CreateDynamicBody(position=(0.0, 0.61))
    rider.CreatePolygonFixture(box=(0.4, 0.4), density=1.0, friction=0.6)
    engine = Engine(world, SolverConfig())
    for _ in range(30):  # the box settles on the rising lift
        engine.collide()
        engine.solve()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    assert len(points) == 2 and (bodies["type"] == 1).sum() == 1
    b = points["builtin"]
    exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
    mu = points["friction"].astype(np.float64)
    physics = Physics(engine.config.dt, (0.0, -9.8))
    settled, cold = sweep_changes(bodies, points, np.stack([exact, np.zeros_like(exact)]), mu, physics, 1)
    weight_step = float(bodies["mass"].max()) * 9.8 * engine.config.dt
    assert exact[:, 0].sum() > 0.5 * weight_step  # the lift carries the box
    assert settled < 1e-3 and cold > 0.2 * weight_step


def test_where_no_point_slides_the_route_solves_in_the_bodies_space_to_the_duals_answer():
    """A pyramid of boxes on labels where every pressing point sticks: the face's system is then
    symmetric, and the compiled route solves it on a factor of its bodies' 3 D rows
    (face_kernels.h, face_body_solve) rather than on the dual's S S^T of its unknowns, twice as
    many as the pile has freedoms. Its answer is the route piece by piece's (the dual, whose
    answer is the pseudo-inverse's: tests/deepcontact/test_faces.py), before the admission's
    rounds and after them."""
    from deepcontact.faces import STICKS, contact_face

    bodies, points, exact, mu = pyramid_of_boxes()
    face = contact_face(exact, mu, pressing=1e-6, share=0.99)
    labels = np.zeros((len(points), 2))
    labels[face != OPEN, 0] = FACE_IMPULSE  # pressing, and sticking: no tangent answer
    assert (contact_face(labels, mu, pressing=0.5, share=1.0)[face != OPEN] == STICKS).all()
    assert (face != OPEN).sum() > 150
    for rounds in (0, 60):
        settings = dict(physics=Physics.thesis(), pressing=0.5, share=1.0, rounds=rounds)
        piecewise, residual = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
        compiled = route_compiled(bodies, points, labels, mu, **settings)
        assert compiled.in_bodies
        np.testing.assert_allclose(compiled.impulses, piecewise, atol=1e-9 * max(1.0, np.abs(piecewise).max()))
        assert compiled.residual == pytest.approx(residual, rel=1e-6, abs=1e-12)


def test_where_points_slide_the_bodies_space_answers_where_its_factorization_is_of_full_rank():
    """Where points slide the face's system S = L R^T is not symmetric; the compiled route takes
    R G^-1 K^-1 L^T in the bodies' space, a body one or two unknowns push taken out of both along
    the directions its pushes leave free. Asked not to (a card's slide_in_bodies false), the dual
    answers. Either way the answer is the route piece by piece's."""
    from deepcontact.faces import SLIDES_MINUS, SLIDES_PLUS, contact_face

    bodies, points, exact, mu = pyramid_of_boxes()
    pressing = contact_face(exact, mu, pressing=1e-6, share=0.99) != OPEN
    held = np.zeros((len(points), 2))
    held[pressing, 0] = FACE_IMPULSE
    # Three points low in the pile slide, one each way and one back.
    low = np.flatnonzero(pressing)[np.argsort(points["point"][pressing, 1])][[20, 40, 60]]
    held[low, 1] = [FACE_IMPULSE, -FACE_IMPULSE, FACE_IMPULSE]
    # The same, with the top box let go at all but one of its points: pushed by two unknowns.
    top = int(np.argmax(bodies["position"][:, 1]))
    on_top = np.flatnonzero(pressing & ((points["body_a"] == top) | (points["body_b"] == top)))
    loose = held.copy()
    loose[on_top[1:]] = 0.0
    # And with that one point sliding: the top box pushed by one unknown, free two ways.
    looser = loose.copy()
    looser[on_top[0], 1] = FACE_IMPULSE
    for labels, in_bodies in ((held, True), (loose, True), (looser, True), (held, False)):
        face = contact_face(labels, mu, pressing=0.5, share=1.0)
        assert set(face[low]) <= {SLIDES_PLUS, SLIDES_MINUS}
        settings = dict(physics=Physics.thesis(), pressing=0.5, share=1.0, rounds=60)
        piecewise, residual = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
        compiled = route_compiled(bodies, points, labels, mu, slide_in_bodies=in_bodies, **settings)
        assert compiled.in_bodies == in_bodies
        np.testing.assert_allclose(compiled.impulses, piecewise, atol=1e-9 * max(1.0, np.abs(piecewise).max()))


def test_free_directions_that_several_bodies_share_are_found_and_set_apart():
    """Rows of boxes that stick to one another and slide together on the boxes below leave the
    face's rows free along directions no one body's pushes account for (34 of them on this
    pyramid's step, and 13 bodies free on their own). The compiled route reads them off K's
    factor (face_kernels.h, face_body_shared_directions), keeps R's side off them without giving
    them columns (face_body_off_shared), and answers in the bodies' space what the dual answers."""
    from deepcontact.faces import SLIDES_MINUS, SLIDES_PLUS, contact_face
    from lab.shared_directions import step_of

    # A zoo pyramid (seed 901) after 30 of Box2D's steps, labelled by the oracle's solution.
    bodies, points, labels, mu, physics = step_of(901, 30)
    face = contact_face(labels, mu, pressing=0.5, share=1.0)
    assert ((face == SLIDES_PLUS) | (face == SLIDES_MINUS)).sum() > 100
    for rounds in (0, 60):
        settings = dict(physics=physics, pressing=0.5, share=1.0, rounds=rounds)
        piecewise, residual = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
        compiled = route_compiled(bodies, points, labels, mu, **settings)
        assert compiled.in_bodies
        np.testing.assert_allclose(compiled.impulses, piecewise, atol=1e-9 * max(1.0, np.abs(piecewise).max()))
        assert compiled.residual == pytest.approx(residual, rel=1e-6, abs=1e-12)


def _two_piles(platform: str):
    """An engine after 40 steps of two piles of three discs 8 m apart, on a static ground or on
    one kinematic platform under both (platform "static" or "kinematic"), collided: (engine,
    bodies, points, the solver's own end (P, 2) N s, mu, physics)."""
    import Box2D

    from simclient.engine import Engine, SolverConfig

    world = Box2D.b2World(gravity=(0.0, -9.8))
    make = world.CreateStaticBody if platform == "static" else world.CreateKinematicBody
    ground = make(position=(0.0, 0.0))
    ground.CreatePolygonFixture(box=(10.0, 0.2), friction=0.5)
    for x in (-4.0, 4.0):
        for level in range(3):
            disc = world.CreateDynamicBody(position=(x + 0.05 * level, 0.7 + 1.0 * level))
            disc.CreateCircleFixture(radius=0.5, density=1.0, friction=0.5)
    engine = Engine(world, SolverConfig())
    for _ in range(40):
        engine.collide()
        engine.solve()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    b = points["builtin"]
    exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
    return engine, bodies, points, exact, points["friction"].astype(np.float64), Physics(engine.config.dt, (0.0, -9.8))


def test_each_island_stops_at_its_own_sweep_as_box2ds_solver_stops_it():
    """Two piles on a static ground are two islands (a static body joins none): each island's
    count is the one its points alone give, the step's count the larger (Box2D's iterations are
    its largest island's), and each island can be served from another start. One kinematic
    platform under both joins them into one island."""
    from deepcontact.faces import island_sweeps_to_stop, sweeps_to_stop

    engine, bodies, points, exact, mu, physics = _two_piles("static")
    left = bodies["position"][points["body_b"], 0] < 0  # each point's dynamic body is its body B here
    assert bodies["type"][points["body_b"]].min() == 2
    starts = np.stack([np.where(left[:, None], exact, 0.0), np.where(left[:, None], 0.0, exact)])
    counts, changes, islands = island_sweeps_to_stop(bodies, points, starts, mu, physics, 1e-4, 500)
    assert islands.counts.shape == (2, 2) and len(np.unique(islands.point[left])) == 1
    assert islands.point[left][0] != islands.point[~left][0]
    for i in range(2):
        on = islands.point == i
        alone, last = sweeps_to_stop(bodies, points[on], starts[:, on], mu[on], physics, 1e-4, 500)
        np.testing.assert_array_equal(islands.counts[:, i], alone)
        np.testing.assert_allclose(islands.changes[:, i], last)
    np.testing.assert_array_equal(counts, islands.counts.max(1))
    # Each start is the solver's end on one island and nothing on the other: taken island by
    # island, the start is the solver's end everywhere, which stops at once.
    start, _, chosen = islands.compose(starts)
    assert sorted(chosen) == [0, 1] and counts.min() > 1
    np.testing.assert_array_equal(start, exact)
    assert sweeps_to_stop(bodies, points, start[None], mu, physics, 1e-4, 500)[0][0] == 1
    # The engine agrees: Box2D's own solve from the composed start takes fewer iterations.
    trial = lambda s: engine.trial(s[:, 0].astype(np.float32), s[:, 1].astype(np.float32))  # noqa: E731
    assert trial(start) < min(trial(starts[0]), trial(starts[1]))

    _, bodies, points, exact, mu, physics = _two_piles("kinematic")
    one = island_sweeps_to_stop(bodies, points, exact[None], mu, physics, 1e-4, 500)[2]
    assert one.counts.shape == (1, 1) and (one.point == 0).all()


def _boxes_landing(restitution: float):
    """A row of three boxes falling onto a ground edge at 3 m/s, each fixture of `restitution`:
    an Engine at the step they land (every point closing faster than Box2D's 1 m/s threshold), its
    bodies, points and physics."""
    import Box2D

    from simclient.engine import Engine

    world = Box2D.b2World(gravity=(0.0, -9.8))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-10.0, 0.0), (10.0, 0.0)], friction=0.5,
                                               restitution=restitution)
    for x in (-2.0, 0.0, 2.0):
        box = world.CreateDynamicBody(position=(x, 0.52), linearVelocity=(0.0, -3.0))
        box.CreatePolygonFixture(box=(0.5, 0.5), density=1.0, friction=0.5, restitution=restitution)
    engine = Engine(world)
    while engine.collide() == 0:
        engine.solve()
    return engine, engine.bodies(), engine.contacts(), Physics(dt=engine.config.dt, gravity=(0.0, -9.8))


def test_a_landing_is_solved_and_swept_at_the_bounce_box2d_holds_it_at():
    # Box2D holds a point that closes faster than 1 m/s at its restitution times that speed,
    # apart: the route solves the landing there and the server's copy sweeps it so.
    from deepcontact.faces import contact_face, sweep_changes

    engine, bodies, points, physics = _boxes_landing(0.3)
    restitution = engine.point_restitution(points)
    assert len(points) == 6 and np.allclose(restitution, 0.3)
    mu = points["friction"].astype(np.float64)
    solution = engine.oracle().astype(np.float64)  # Box2D's own: every point bounces
    first = {bounce: sweep_changes(bodies, points, solution[None], mu, physics, sweeps=1,
                                   restitution=restitution if bounce else None)[0] for bounce in (True, False)}
    assert first[True] < 1e-5 and first[False] > 0.1 * solution[:, 0].max()  # its end where the copy knows
    labels = labels_of(solution, mu, np.random.default_rng(0))
    assert (contact_face(solution, mu) != OPEN).all()
    answers = {bounce: route_compiled(bodies, points, labels, mu, physics, pressing=0.75, rounds=100,
                                      restitution=restitution if bounce else None).impulses for bounce in (True, False)}
    np.testing.assert_allclose(answers[True], solution, atol=1e-4 * solution[:, 0].max())
    assert np.abs(answers[False] - solution).max() > 0.1 * solution[:, 0].max()  # held at rest: 1 / 1.3 of it


def test_the_piecewise_route_holds_the_same_bounces_as_the_compiled_one():
    engine, bodies, points, physics = _boxes_landing(0.3)
    mu = points["friction"].astype(np.float64)
    labels = labels_of(engine.oracle().astype(np.float64), mu, np.random.default_rng(0))
    restitution = engine.point_restitution(points)
    settings = dict(physics=physics, pressing=0.75, share=1.0, rounds=100, restitution=restitution)
    reference, residual = solved_on_labels(bodies, points, labels, mu, solver="dual", **settings)
    compiled = route_compiled(bodies, points, labels, mu, **settings)
    np.testing.assert_allclose(compiled.impulses, reference, atol=1e-8 * np.abs(reference).max())
    assert compiled.residual == pytest.approx(residual, rel=1e-6, abs=1e-12)


def test_without_restitution_nothing_bounces():
    # Points of no restitution (or none given) are held at rest: the same answer either way.
    from deepcontact.faces import contact_face

    engine, bodies, points, physics = _boxes_landing(0.0)
    mu = points["friction"].astype(np.float64)
    labels = labels_of(engine.oracle().astype(np.float64), mu, np.random.default_rng(0))
    plain = route_compiled(bodies, points, labels, mu, physics, pressing=0.75, rounds=100)
    given = route_compiled(bodies, points, labels, mu, physics, pressing=0.75, rounds=100,
                           restitution=engine.point_restitution(points))
    np.testing.assert_array_equal(plain.impulses, given.impulses)
    assert (contact_face(plain.impulses, mu) != OPEN).all()
    with pytest.raises(ValueError, match="restitution"):
        route_compiled(bodies, points, labels, mu, physics, restitution=np.ones(2))
