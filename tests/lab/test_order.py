"""`deepcontact lab order`: the solver's replica (lab.gauss_seidel) run in several
orders from Box2D's warm start on recorded steps.

The command itself loads TensorFlow (the self-stress split), so it runs as its own process:
TensorFlow's threads in the test process break the tests that fork after them."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from commands import main


def deepcontact(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "commands", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Builtin's first 60 steps of one thesis world: the bodies land and pile up."""
    path = tmp_path_factory.mktemp("order") / "val.h5"
    assert main(["generate", "--steps", "60", "--seeds", "3", "--out", str(path), "--quiet"]) == 0
    return path


def test_the_command_sets_the_orders_answers_side_by_side(recorded, tmp_path):
    out = tmp_path / "order.json"
    done = deepcontact("lab", "order", "--data", str(recorded), "--steps", "20", "--orders", "3", "--model", "",
                       "--json", str(out))
    assert done.returncode == 0, done.stderr
    report = json.loads(out.read_text())
    assert report["steps"] == 20 and len(report["replica_sweeps"]) == 3
    assert len(report["order_spread_rms"]) == len(report["order_spread_self_stress_share"]) == 3  # the pairs
    assert all(0.0 <= s <= 1.0 + 1e-9 for s in report["order_spread_self_stress_share"])
    assert report["answer_moved_rms"] < report["start_moved_rms"]  # the solve keeps little of a moved start
    assert "orders 0-1" in done.stdout and "model" not in report


def test_one_order_is_not_a_comparison(recorded, capsys):
    assert main(["lab", "order", "--data", str(recorded), "--orders", "1"]) == 2
    assert "--orders 2 or more" in capsys.readouterr().err
