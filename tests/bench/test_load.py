"""`deepcontact bench load` against a real server process: counts, order, overload."""

from __future__ import annotations

import json

import pytest

from commands import main
from server.process import ServerProcess


@pytest.fixture(scope="module")
def replay_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "replay.h5"
    assert main(["generate", "--seeds", "1", "--steps", "80", "--out", str(path), "--quiet"]) == 0
    return path


def test_load_levels_report_throughput_latency_and_no_misordered_replies(model_dir, replay_file, tmp_path):
    with ServerProcess(model_dir) as server:
        assert main(["bench", "load", "--server", server.address, "--model", "tiny", "--clients", "1,3",
                     "--duration", "2", "--replay", str(replay_file), "--processes", "2",
                     "--out", str(tmp_path)]) == 0
    results = json.loads((tmp_path / "load.json").read_text())["results"]
    assert [r["clients"] for r in results] == [1, 3]
    for r in results:
        assert r["steps"] > 0 and r["steps_per_s"] > 0
        assert r["sent"] == r["steps"] + sum(r["errors"].values())
        assert r["latency_ms"]["p50"] <= r["latency_ms"]["p99"] <= r["latency_ms"]["p99.9"]
        assert r["wrong_order_or_step"] == 0 and r["errors"] == {}
    assert (tmp_path / "latency_vs_load.png").exists()


def test_past_the_servers_bound_refusals_are_counted_as_resource_exhausted(model_dir, replay_file, tmp_path):
    with ServerProcess(model_dir, "--max-concurrent", "1") as server:
        assert main(["bench", "load", "--server", server.address, "--model", "tiny", "--clients", "3",
                     "--duration", "2", "--replay", str(replay_file), "--processes", "1",
                     "--out", str(tmp_path)]) == 0
    (r,) = json.loads((tmp_path / "load.json").read_text())["results"]
    assert r["errors"].get("RESOURCE_EXHAUSTED", 0) > 0
    assert set(r["errors"]) <= {"RESOURCE_EXHAUSTED"}  # refused promptly, not timed out
    assert r["wrong_order_or_step"] == 0 and r["steps"] > 0
    assert r["sent"] == r["steps"] + sum(r["errors"].values())  # refusals are counted, not lost


def test_live_simulations_can_drive_the_load(model_dir, tmp_path):
    with ServerProcess(model_dir) as server:
        assert main(["bench", "load", "--server", server.address, "--model", "tiny", "--clients", "2",
                     "--duration", "1", "--processes", "1", "--out", str(tmp_path)]) == 0
    (r,) = json.loads((tmp_path / "load.json").read_text())["results"]
    assert r["steps"] > 0 and r["errors"] == {} and r["wrong_order_or_step"] == 0
