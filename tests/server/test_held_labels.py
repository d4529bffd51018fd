"""server.held_labels: a stream's classifier labels held by contact point for its later steps."""

import concurrent.futures

import numpy as np

from deepcontact.records import CONTACT_DTYPE
from server.held_labels import MAX_AGE, HeldLabels


def _points(keys) -> np.ndarray:
    points = np.zeros(len(keys), CONTACT_DTYPE)
    points["key"] = keys
    return points


def test_labels_are_found_by_point_key_for_the_next_few_steps_only():
    held = HeldLabels()
    step_7 = _points([30, 10, 20])
    held.keep(step_7, 7, np.array([[1.0, 0.0], [0.0, 1.0], [1.0, -1.0]]))
    # The same points in another order a step later: each gets its own labels back.
    assert np.array_equal(held.lookup(_points([20, 30]), 8), [[1.0, -1.0], [1.0, 0.0]])
    assert held.lookup(_points([20, 40]), 8) is None  # a point new to the stream: none
    assert held.lookup(_points([20]), 7) is None  # not for the step they were given on
    assert held.lookup(_points([20]), 7 + MAX_AGE) is not None
    assert held.lookup(_points([20]), 8 + MAX_AGE) is None  # too old
    assert HeldLabels().lookup(step_7, 8) is None  # nothing held yet


def test_a_step_labelled_in_the_background_is_held_once_done_and_never_waited_on():
    held = HeldLabels()
    held.keep(_points([1, 2]), 3, np.zeros((2, 2)))
    gate = concurrent.futures.Future()
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        assert held.label_later(pool, gate.result, _points([1, 2, 3]), 4)
        assert not held.label_later(pool, lambda: np.ones((3, 2)), _points([1, 2, 3]), 5)  # one at a time
        assert held.lookup(_points([1, 2, 3]), 5) is None  # step 4's labels are not in yet
        gate.set_result(np.full((3, 2), 2.0))
    assert np.array_equal(held.lookup(_points([3, 1]), 5), np.full((2, 2), 2.0))  # step 4's now
    with concurrent.futures.ThreadPoolExecutor(1) as pool:  # a run that fails loses its step's labels only
        held.label_later(pool, lambda: 1 / 0, _points([1]), 5)
    assert np.array_equal(held.lookup(_points([1, 2]), 6), np.full((2, 2), 2.0))


def test_points_with_no_labels_held_take_the_fill_given():
    held = HeldLabels()
    fill = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 0.0]])  # e.g. Box2D's start read as labels
    # Nothing held yet: the fill for every point.
    assert np.array_equal(held.lookup(_points([20, 40, 30]), 8, fill), fill)
    held.keep(_points([30, 10, 20]), 7, np.array([[1.0, 0.0], [0.0, 1.0], [1.0, -1.0]]))
    # 20 and 30 held, 40 new on the step: its row of the fill.
    assert np.array_equal(held.lookup(_points([20, 40, 30]), 8, fill), [[1.0, -1.0], [1.0, 1.0], [1.0, 0.0]])
    assert np.array_equal(held.lookup(_points([20, 40, 30]), 8 + MAX_AGE, fill), fill)  # too old: the fill
