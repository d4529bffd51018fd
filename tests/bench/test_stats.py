"""Bootstrap intervals of ratios to Builtin (bench.stats)."""

from __future__ import annotations

import numpy as np
import pytest

from bench.stats import ratio_interval



def test_ratio_is_the_ratio_of_pooled_statistics_as_numpy_computes_them():
    rng = np.random.default_rng(2)
    warm = [rng.integers(1, 1001, size=n) for n in (250, 249, 3)]
    ref = [rng.integers(1, 1001, size=n) for n in (250, 250, 1)]
    w, r = np.concatenate(warm), np.concatenate(ref)
    assert ratio_interval(warm, ref, "mean").value == pytest.approx(w.mean() / r.mean())
    assert ratio_interval(warm, ref, "median").value == pytest.approx(np.median(w) / np.median(r))
    assert ratio_interval(warm, ref, "p90").value == pytest.approx(np.percentile(w, 90) / np.percentile(r, 90))


def test_a_clear_gain_has_its_whole_interval_below_one():
    rng = np.random.default_rng(0)
    ref = [rng.integers(100, 900, size=250) for _ in range(30)]
    warm = [(a * 0.7).astype(int) for a in ref]
    r = ratio_interval(warm, ref)
    assert r.low < r.value < r.high < 1.0 and r.below_one() and r.seeds == 30
    assert r.value == pytest.approx(0.7, abs=0.01)


def test_a_few_percent_on_noisy_seeds_is_not_a_win():
    # Worlds differ: the warm start's ratio to Builtin varies from seed to seed
    # (here by about 15 %) around a 4 % gain.
    rng = np.random.default_rng(1)
    ref = [rng.integers(1, 1000, size=250) for _ in range(10)]
    warm = [(a * 0.96 * np.exp(rng.normal(0, 0.15))).astype(int) for a in ref]
    r = ratio_interval(warm, ref)
    assert r.low < 1.0 < r.high and not r.below_one()


def test_same_seed_same_interval_and_one_seed_has_none():
    ref, warm = [np.array([5, 6, 7])] * 3, [np.array([4, 6, 6])] * 3
    assert ratio_interval(warm, ref) == ratio_interval(warm, ref)
    one = ratio_interval(warm[:1], ref[:1])
    assert one.value is not None and one.low is None and one.text().count("[") == 0


def test_no_steps_and_mismatched_seeds():
    assert ratio_interval([np.array([], int)], [np.array([], int)]).value is None
    assert ratio_interval([], []).text() == "–"
    with pytest.raises(ValueError, match="same seeds"):
        ratio_interval([np.array([1])], [])
