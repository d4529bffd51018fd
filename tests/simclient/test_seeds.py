"""Seed ranges and seed lists."""

import pytest

from simclient.seeds import describe, outside_training, parse_seeds


def test_seed_lists_parse_ranges_and_items():
    assert parse_seeds("1-3,7, 5") == [1, 2, 3, 5, 7]
    with pytest.raises(ValueError):
        parse_seeds("5-1")
    with pytest.raises(ValueError):
        parse_seeds("a-b")


def test_ranges():
    assert [describe(s) for s in (1, 899, 900, 999, 1000, 10000)] == [
        "training", "training", "benchmark", "benchmark", "unassigned", "reserved"]
    assert outside_training([1, 900, 10001]) == [900, 10001]
