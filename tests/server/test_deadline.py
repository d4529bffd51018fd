"""server.deadline: a route's recent cost by step size decides whether it fits a deadline."""

from server.deadline import BUCKET_POINTS, OFFSET, PROBE_EVERY, TRIALS, WINDOW, CostBySize


def test_a_route_fits_until_it_has_been_seen_to_cost_more_than_is_left():
    cost = CostBySize()
    assert cost.fits(150, now=0.0, deadline=0.008)  # nothing seen: tried, so that it is learned
    assert cost.fits(150, now=0.0, deadline=None)  # no deadline: always
    for _ in range(TRIALS + 1):
        cost.observe(150, 0.012)
    assert cost.estimate(150) == 0.012
    assert not cost.fits(150, now=0.0, deadline=0.008)
    assert cost.fits(150, now=0.0, deadline=0.013)


def test_a_size_is_estimated_from_the_nearest_smaller_one_known_until_it_is_known_itself():
    cost = CostBySize()
    for _ in range(TRIALS):
        cost.observe(50, 0.004)
    assert cost.estimate(40) == 0.0  # nothing known at or below it
    assert cost.estimate(50 + BUCKET_POINTS - 1) == 0.004  # the same bucket
    assert abs(cost.estimate(60) - 0.004 * ((60 + OFFSET) / (50 + OFFSET)) ** 2) < 1e-12
    assert cost.fits(60, now=0.0, deadline=0.008)  # a little larger: tried
    assert not cost.fits(200, now=0.0, deadline=0.008)  # far larger: not before the sizes between
    cost.observe(60, 0.100)  # one cold first call at 60 points decides nothing yet
    assert cost.fits(60, now=0.0, deadline=0.008)


def test_the_estimate_follows_the_recent_steps_not_one_cold_first_call():
    cost = CostBySize()
    cost.observe(40, 0.050)  # a first call that imported and planned
    for _ in range(WINDOW - 1):
        cost.observe(40, 0.003)
    assert cost.estimate(40) == 0.003  # the window's upper quartile
    cost.observe(40, 0.003)
    assert max(cost._seen[40 // BUCKET_POINTS]) == 0.003  # the cold call has left the window


def test_a_declined_size_is_tried_again_now_and_then_where_its_fastest_step_would_fit():
    cost = CostBySize()
    for seconds in (0.004, 0.012, 0.012, 0.012):  # a busy moment raised the estimate
        cost.observe(80, seconds)
    tries = [cost.fits(80, now=0.0, deadline=0.008) for _ in range(3 * PROBE_EVERY)]
    assert tries.count(True) == 3 and tries[PROBE_EVERY - 1]
    never = CostBySize()
    for _ in range(TRIALS):
        never.observe(80, 0.020)  # even its fastest step would miss: never tried
    assert not any(never.fits(80, now=0.0, deadline=0.008) for _ in range(3 * PROBE_EVERY))
