"""`deepcontact bench soak`: a short soak against a real server process, and its checks."""

from __future__ import annotations

import json

from bench.soak import accounting_check, memory_check
from commands import main


def test_a_short_soak_accounts_for_every_step_and_samples_the_servers_memory(model_dir, tmp_path):
    assert main(["bench", "soak", "--models", str(model_dir), "--model", "tiny", "--clients", "2",
                 "--processes", "1", "--duration", "2", "--sample-s", "0.2", "--warmup-s", "0.5",
                 "--rss-bound-mb", "500", "--out", str(tmp_path)]) == 0
    result = json.loads((tmp_path / "soak.json").read_text())
    steps, memory = result["steps"], result["memory"]
    assert steps["sent"] > 0 and steps["balanced"]
    assert steps["sent"] == steps["answered"] + sum(steps["errors"].values())
    assert steps["server_answered"] >= steps["answered"]
    assert memory["samples_after_warmup"] >= 2 and memory["within_bound"] is True
    assert 10 < memory["rss_after_warmup_mb"] <= memory["rss_max_after_warmup_mb"] < 10_000
    assert [s["steps_answered"] for s in result["samples"]][-1] == steps["server_answered"]
    assert (tmp_path / "soak.png").stat().st_size > 0


def test_growth_after_the_warm_up_past_the_bound_fails_the_check():
    flat = [(t, 100.0 + (5.0 if t < 10 else 0.2 * (t % 2)), 10 * t) for t in range(0, 60, 2)]
    check = memory_check(flat, warmup_s=10, bound_mb=1.0)
    assert check["within_bound"] and check["growth_after_warmup_mb"] <= 0.2 + 1e-9  # warm-up growth is excused
    leaking = [(t, 100.0 + 0.5 * t, 10 * t) for t in range(0, 60, 2)]
    check = memory_check(leaking, warmup_s=10, bound_mb=5.0)
    assert not check["within_bound"] and check["slope_mb_per_h"] > 1000


def test_a_step_neither_answered_nor_counted_unbalances_the_books():
    level = {"sent": 10, "steps": 8, "errors": {"DEADLINE_EXCEEDED": 1}}
    assert not accounting_check(level, server_answered=9)["balanced"]
    assert accounting_check({**level, "sent": 9}, server_answered=9)["balanced"]
    assert not accounting_check({**level, "sent": 9}, server_answered=7)["balanced"]  # clients got more than sent
