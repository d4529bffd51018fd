"""Refusals are logged at most once per RPC and status per interval."""

from __future__ import annotations

from server.rejects import LogLimiter


def test_a_flood_of_refusals_logs_one_line_per_interval_and_counts_the_rest():
    now = [0.0]
    limiter = LogLimiter(interval_s=10.0, clock=lambda: now[0])
    assert limiter.admit(("Predict", "INVALID_ARGUMENT")) == 0
    assert [limiter.admit(("Predict", "INVALID_ARGUMENT")) for _ in range(99)] == [None] * 99
    assert limiter.admit(("Stream", "INVALID_ARGUMENT")) == 0  # another RPC has its own budget
    now[0] = 10.0
    assert limiter.admit(("Predict", "INVALID_ARGUMENT")) == 99  # the next line says how many it left out
    assert limiter.admit(("Predict", "INVALID_ARGUMENT")) is None
