"""Seed ranges: which worlds may be used for what.

    1 - 899       training and validation data, tuning, model selection
    900 - 999     the project's benchmarks (never trained on)
    10000 and up  reserved for evaluation outside the project: no training
                  data, tuning or model selection ever touches them

Seeds 0 and 1000 - 9999 belong to no range and are refused for training
data like benchmark seeds are.
"""

from __future__ import annotations

TRAIN = range(1, 900)
BENCHMARK = range(900, 1000)
RESERVED_FROM = 10000


def parse_seeds(text: str) -> list[int]:
    """'1-100', '901,905', '1-10,20' -> sorted unique seeds. ValueError on bad text."""
    seeds: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        try:
            if "-" in part:
                lo, hi = (int(x) for x in part.split("-", 1))
                if hi < lo:
                    raise ValueError
                seeds.update(range(lo, hi + 1))
            else:
                seeds.add(int(part))
        except ValueError:
            raise ValueError(f"bad seed list {text!r}: use e.g. '1-100' or '901,903,910-915'") from None
    if not seeds:
        raise ValueError(f"bad seed list {text!r}: no seeds")
    if min(seeds) < 0:
        raise ValueError(f"seeds must be >= 0, got {min(seeds)}")
    return sorted(seeds)


def outside_training(seeds: list[int]) -> list[int]:
    """The seeds a training file must not contain."""
    return [s for s in seeds if s not in TRAIN]


def describe(seed: int) -> str:
    if seed in TRAIN:
        return "training"
    if seed in BENCHMARK:
        return "benchmark"
    if seed >= RESERVED_FROM:
        return "reserved"
    return "unassigned"
