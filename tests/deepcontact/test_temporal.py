"""deepcontact.temporal: Box2D's start extrapolated along a stream, point by point, where it moves smoothly."""

import numpy as np

from deepcontact.records import CONTACT_DTYPE
from deepcontact.temporal import ImpulseHistory


def _points(keys, builtin):
    points = np.zeros(len(keys), CONTACT_DTYPE)
    points["key"] = keys
    points["builtin"] = builtin
    return points


def test_a_point_moving_steadily_starts_on_the_line_through_its_last_two_starts():
    history = ImpulseHistory()
    np.testing.assert_array_equal(history.extrapolated(_points([7], [[1.0, 0.1]]), step=0), np.float32([[1.0, 0.1]]))
    np.testing.assert_array_equal(history.extrapolated(_points([7], [[2.0, 0.2]]), step=1), np.float32([[2.0, 0.2]]))
    # Steady (the line through steps 0 and 1 would have hit step 2's start): drawn on to step 3's.
    np.testing.assert_allclose(history.extrapolated(_points([7], [[3.1, 0.3]]), step=2), [[4.2, 0.4]], rtol=1e-6)


def test_a_point_whose_impulse_jumped_keeps_box2ds_start():
    history = ImpulseHistory()
    for step, value in enumerate([1.0, 1.0, 5.0, 5.5]):  # a landing: the line would have missed by more than the copy
        start = history.extrapolated(_points([3], [[value, 0.0]]), step=step)
        np.testing.assert_array_equal(start, np.float32([[value, 0.0]]))


def test_points_are_matched_by_key_and_new_or_left_out_points_keep_box2ds_start():
    history = ImpulseHistory()
    history.extrapolated(_points([1, 2, 3], [[1.0, 0.0], [0.0, 0.0], [1.0, 0.0]]), step=4)
    history.extrapolated(_points([3, 2, 1], [[2.0, 0.0], [1.0, 0.0], [2.0, 0.0]]), step=5)
    # key 2 was new on step 4 (Box2D carried nothing to it), key 9 is new now, key 3 is not asked about.
    start = history.extrapolated(_points([1, 2, 9, 3], [[3.0, 0.0], [2.0, 0.0], [0.0, 0.0], [3.0, 0.0]]), step=6,
                                 where=np.array([True, True, True, False]))
    np.testing.assert_array_equal(start, np.float32([[4.0, 0.0], [2.0, 0.0], [0.0, 0.0], [3.0, 0.0]]))


def test_after_a_gap_of_steps_nothing_is_extrapolated_until_three_steps_follow_in_turn():
    history = ImpulseHistory()
    for step, value in ((0, 1.0), (1, 2.0), (3, 4.0), (4, 5.0)):
        np.testing.assert_array_equal(history.extrapolated(_points([1], [[value, 0.0]]), step=step),
                                      np.float32([[value, 0.0]]))
    np.testing.assert_array_equal(history.extrapolated(_points([1], [[6.0, 0.0]]), step=5), np.float32([[7.0, 0.0]]))


def test_the_same_step_asked_again_gets_the_same_start():
    history = ImpulseHistory()
    history.extrapolated(_points([1], [[1.0, 0.0]]), step=0)
    history.extrapolated(_points([1], [[2.0, 0.0]]), step=1)
    once = history.extrapolated(_points([1], [[3.0, 0.0]]), step=2)
    again = history.extrapolated(_points([1], [[3.0, 0.0]]), step=2)
    np.testing.assert_array_equal(once, again)
    np.testing.assert_array_equal(again, np.float32([[4.0, 0.0]]))
