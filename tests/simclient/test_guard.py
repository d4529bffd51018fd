"""The guard's decisions, step by step: Box2D's sweeps and a learned start's on the same states.

Each test hands the guard a world as two sequences of sweeps a step (Box2D's own start's and
the learned start's on the same states) and plays it as the simulation client does: ask the
plan, solve from the start it serves, price the other on a probe.
"""

from __future__ import annotations

import numpy as np
import pytest

from simclient.guard import BUILTIN, LEARNED, Guard, GuardSettings


def play(builtin, learned, settings: GuardSettings = GuardSettings(), familiar=False):
    """(sweeps served (N,), trial sweeps spent, guard) over per-step sweeps builtin, learned (N,).
    familiar: what the server says of the world with each answer (a bool, or (N,) bools)."""
    guard, served, spent = Guard(settings), [], 0
    familiar = np.broadcast_to(familiar, len(builtin))
    for b, l, f in zip(builtin, learned, familiar):
        plan = guard.plan()
        if plan.ask:
            guard.heard(bool(f), "" if f else "3 of 3 bodies not discs")
        if plan.probe and guard.mode == LEARNED:  # Box2D's start priced beside the learned one
            guard.probed(learned=l, builtin=b, trial_sweeps=b, builtin_sweeps=b)
            served.append(l)
            spent += b
        elif plan.probe:  # the learned start priced, stopped at the cap, beside Box2D's
            cap = guard.trial_cap()
            trial = min(l, cap)
            guard.probed(learned=trial, builtin=b, trial_sweeps=trial, builtin_sweeps=b, capped=trial >= cap)
            served.append(b)
            spent += trial
        else:
            mode = guard.mode
            served.append(l if mode == LEARNED else b)
            guard.served(mode, served[-1], served[-1])
    return np.array(served), spent, guard


def busy_world(n=250, seed=0):
    """Box2D's sweeps a step in a pile that fills up: 20 growing to about 400, noisy."""
    rng = np.random.default_rng(seed)
    return np.maximum(1, np.linspace(20, 400, n) * rng.lognormal(0.0, 0.4, n)).astype(int)


def test_a_start_that_always_loses_is_never_served():
    builtin = busy_world()
    served, spent, guard = play(builtin, 4 * builtin)
    assert served.sum() <= 1.05 * builtin.sum()
    assert guard.mode == BUILTIN and guard.switches == 0
    assert spent <= 0.05 * builtin.sum()


def test_a_start_that_wins_is_served_on_most_steps():
    builtin = busy_world()
    served, spent, guard = play(builtin, (0.6 * builtin).astype(int))
    assert served.sum() <= 0.66 * builtin.sum()  # the learned start's 0.6, less what finding out cost
    assert guard.mode == LEARNED
    assert spent <= 0.05 * builtin.sum()


def test_a_start_that_goes_wrong_is_dropped_within_a_few_steps():
    builtin = busy_world()
    learned = (0.6 * builtin).astype(int)
    learned[150:] = 1000  # good for 150 steps, then at the solver's cap
    served, _, guard = play(builtin, learned)
    assert guard.mode == BUILTIN
    assert (served[150:] > builtin[150:]).sum() <= 6  # the recent steps' median turns after five
    assert served.sum() < builtin.sum()


def test_a_start_that_goes_far_wrong_is_dropped_after_one_step():
    builtin = busy_world() // 20 + 10  # a quieter world: 11 to 30 sweeps a step
    learned = builtin // 2
    learned[150:] = 1000  # 30 to 100 times Box2D's
    served, _, guard = play(builtin, learned)
    assert guard.mode == BUILTIN and (served[150:] > builtin[150:]).sum() == 1


def test_a_world_at_rest_gets_box2ds_start_and_only_cheap_probes():
    """A stack at rest needs a sweep or two a step: a learned start could save next to nothing,
    and a trial of it stops at those few sweeps."""
    builtin = np.ones(250, int)
    served, spent, guard = play(builtin, np.full(250, 400))
    assert served.sum() == builtin.sum() and guard.switches == 0
    assert spent <= 0.04 * builtin.sum() + guard.settings.free_probes


def test_the_trials_stay_inside_the_budget_whatever_the_world():
    rng = np.random.default_rng(1)
    for _ in range(20):
        builtin = busy_world(seed=int(rng.integers(1000)))
        learned = (builtin * rng.lognormal(0.0, 1.0, len(builtin))).astype(int) + 1  # a coin toss each step
        _, spent, guard = play(builtin, learned)
        # The budget's 4 %, the free first probes, and the alarms' rechecks (one per interval at most).
        assert spent <= 0.04 * builtin.sum() + guard.settings.free_probes * 2 * builtin.max() / 4 + 0.04 * builtin.sum()


def test_settings_that_cannot_work_are_refused():
    with pytest.raises(ValueError, match="inconsistent guard settings"):
        GuardSettings(enter=1.1, leave=1.0)
    with pytest.raises(ValueError):
        GuardSettings(interval=(8, 2))


# -- worlds the server calls familiar (deepcontact.envelope) ---------------------------------

def test_a_familiar_world_is_served_the_learned_start_from_its_first_step():
    builtin = busy_world()
    learned = (0.6 * builtin).astype(int)
    served, spent, guard = play(builtin, learned, familiar=True)
    assert guard.mode == LEARNED and guard.switches == 1  # trusted on the first answer
    assert served.sum() == learned.sum()
    assert spent <= 0.05 * builtin.sum() + guard.settings.checks * builtin.max()


def test_a_familiar_world_keeps_its_start_through_single_steps_at_the_cap():
    """A busy pile's learned start now and then runs to the solver's cap where Box2D's takes
    300 sweeps: no single step is the world."""
    builtin = busy_world()
    learned = (0.5 * builtin).astype(int)
    learned[::25] = 1000
    served, _, guard = play(builtin, learned, familiar=True)
    assert guard.mode == LEARNED and guard.switches == 1
    assert served.sum() == learned.sum() < builtin.sum()


def test_a_familiar_world_whose_start_loses_is_dropped_after_a_few_probes():
    builtin = busy_world()
    served, _, guard = play(builtin, 3 * builtin, familiar=True)
    assert guard.mode == BUILTIN
    assert served.sum() <= 1.25 * builtin.sum()  # the trusted first steps, then Box2D's start


def test_a_world_that_stops_being_familiar_loses_the_trust_at_once():
    builtin = busy_world()
    familiar = np.arange(len(builtin)) < 100  # a box dropped into the pile at step 100
    learned = (0.6 * builtin).astype(int)
    learned[100:] = 4 * builtin[100:]
    served, _, guard = play(builtin, learned, familiar=familiar)
    assert guard.mode == BUILTIN and guard.familiar is False and guard.unfamiliar
    assert (served[100:] > builtin[100:]).sum() <= 2


def test_without_trust_a_familiar_world_is_held_to_box2ds_start_until_probes_say_otherwise():
    builtin = busy_world()
    served, _, guard = play(builtin, 3 * builtin, GuardSettings(trust=False), familiar=True)
    assert guard.switches == 0 and served.sum() <= 1.05 * builtin.sum()
