"""server.deadline: a route's recent cost by step size decides whether it fits a deadline."""

from server.deadline import BUCKET_POINTS, DEFAULT_POWER, MAX_POWER, MIN_POWER, OFFSET, PROBE_EVERY, TRIALS, WINDOW, CostBySize


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
    # Nothing known at or below 45: the steps seen within a fifth of its size, scaled to it.
    assert abs(cost.estimate(45) - 0.004 * ((40 + OFFSET) / (50 + OFFSET)) ** DEFAULT_POWER) < 1e-12
    assert cost.estimate(30) == 0.0  # none within a fifth of 30 points
    assert cost.estimate(50 + BUCKET_POINTS - 1) == 0.004  # the same bucket
    assert abs(cost.estimate(60) - 0.004 * ((60 + OFFSET) / (50 + OFFSET)) ** DEFAULT_POWER) < 1e-12
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


def test_a_stream_whose_steps_grow_past_every_bucket_is_judged_by_all_its_steps_so_far():
    # A pile whose steps grow by 10-30 points a step fills no bucket for a while. Each size new to
    # the server is tried once, but only until three steps of any size have been seen; then
    # their median, scaled to the size asked, turns the next one away.
    cost = CostBySize()
    sizes = [458, 468, 502, 521, 552, 557]
    tried = []
    for points in sizes:
        tried.append(cost.fits(points, now=0.0, deadline=0.008))
        if tried[-1]:
            cost.observe(points, 0.015 * ((points + OFFSET) / (500 + OFFSET)) ** 2)  # past the budget
    assert tried == [True, True, True, False, False, False]
    # A cold first call among quick steps does not turn the next size away, nor do a few small
    # steps' costs grown to a far larger size.
    cold = CostBySize()
    for points, seconds in ((100, 0.090), (110, 0.002), (120, 0.002)):
        cold.observe(points, seconds)
    assert cold.fits(125, now=0.0, deadline=0.008)
    small = CostBySize()
    for points in (30, 40, 87):
        small.observe(points, 0.003)
    assert small.fits(400, now=0.0, deadline=0.008)


def test_a_size_not_seen_yet_is_grown_by_the_power_the_known_sizes_show():
    # A pile's route: 1.6 ms at 36 points, 3 ms at 110, about linear in (size + OFFSET) from
    # there. Learned from its first steps, the sizes it grows to are tried as they come.
    pile = CostBySize()
    for _ in range(TRIALS):
        pile.observe(36, 0.0016)
    assert pile.fits(111, now=0.0, deadline=0.0058)  # the default power: 3.8 ms expected
    for _ in range(TRIALS):
        pile.observe(111, 0.0016 * (111 + OFFSET) / (36 + OFFSET))
    assert abs(pile._power - MIN_POWER) < 1e-9  # linear, as the two sizes show
    assert abs(pile.estimate(320) - pile.estimate(111) * (320 + OFFSET) / (110 + OFFSET)) < 1e-12
    # A route that grows with the cube is held at MAX_POWER: one far larger is still not tried.
    steep = CostBySize()
    for points in (30, 150):
        for _ in range(TRIALS):
            steep.observe(points, 0.0005 * ((points + OFFSET) / 80) ** 3)
    assert steep._power == MAX_POWER
    assert not steep.fits(400, now=0.0, deadline=0.008)
