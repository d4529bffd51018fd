"""Seed ranges: which worlds may be used for what.

    1 - 899       training and validation data, tuning, model selection:
        1 - 799       training data (what models are fitted on)
        800 - 849     validation (what stops and compares training runs)
        850 - 899     choosing (what picks one variant over another)
    900 - 999     the project's benchmarks (never trained on; what results report)
    10000 and up  reserved for evaluation outside the project: no training
                  data, tuning or model selection ever touches them

Seeds 0 and 1000 - 9999 belong to no range and are refused for training
data like benchmark seeds are.
"""

from __future__ import annotations

TRAIN = range(1, 900)  # what `generate` records without --allow-bench-seeds
FIT = range(1, 800)
VALIDATION = range(800, 850)
CHOOSING = range(850, 900)
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


def as_ranges(seeds: list[int]) -> str:
    """[1, 2, 3, 7, 850, 851] -> '1-3, 7, 850-851' (sorted, unique seeds)."""
    parts, start = [], None
    for i, seed in enumerate(seeds):
        if start is None:
            start = seed
        if i + 1 == len(seeds) or seeds[i + 1] != seed + 1:
            parts.append(str(start) if start == seed else f"{start}-{seed}")
            start = None
    return ", ".join(parts)


def describe(seed: int) -> str:
    """'training', 'validation', 'choosing', 'benchmark', 'reserved' or 'unassigned'."""
    if seed in FIT:
        return "training"
    if seed in VALIDATION:
        return "validation"
    if seed in CHOOSING:
        return "choosing"
    if seed in BENCHMARK:
        return "benchmark"
    if seed >= RESERVED_FROM:
        return "reserved"
    return "unassigned"
