"""Seed ranges and seed lists."""

import pytest

from simclient.seeds import as_ranges, describe, outside_training, parse_seeds


def test_seed_lists_parse_ranges_and_items():
    assert parse_seeds("1-3,7, 5") == [1, 2, 3, 5, 7]
    with pytest.raises(ValueError):
        parse_seeds("5-1")
    with pytest.raises(ValueError):
        parse_seeds("a-b")


def test_ranges():
    assert [describe(s) for s in (1, 799, 800, 849, 850, 899, 900, 999, 1000, 10000)] == [
        "training", "training", "validation", "validation", "choosing", "choosing", "benchmark", "benchmark",
        "unassigned", "reserved"]
    assert outside_training([1, 900, 10001]) == [900, 10001]


def test_seed_lists_print_as_ranges():
    assert as_ranges([1, 2, 3, 7, 850, 851]) == "1-3, 7, 850-851"
    assert as_ranges(parse_seeds("800-849")) == "800-849" and as_ranges([]) == ""
