"""`deepcontact bench order`: a projected Gauss-Seidel replica of the solver, run in several
orders from Box2D's warm start on recorded steps.

The command itself loads TensorFlow (the self-stress split), so it runs as its own process:
TensorFlow's threads in the test process break the tests that fork after them."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from bench.order import Steps, gauss_seidel
from deepcontact.cli import main
from training.contact_graph import build_graph_set
from training.graph_loss import colour_points


def deepcontact(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "deepcontact", *args], capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Builtin's first 60 steps of one thesis world: the bodies land and pile up."""
    path = tmp_path_factory.mktemp("order") / "val.h5"
    assert main(["generate", "--steps", "60", "--seeds", "3", "--out", str(path), "--quiet"]) == 0
    return path


def test_the_replica_stops_about_where_the_recorded_solve_did(recorded):
    p = Steps(build_graph_set(recorded, max_steps=20), mu=0.5)  # the thesis world's friction
    lam, sweeps = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=0), threshold=1e-4, max_sweeps=1000)
    correction = np.sqrt(np.mean(np.sum((p.solution - p.builtin) ** 2, axis=1)))
    assert np.sqrt(np.mean(np.sum((lam - p.solution) ** 2, axis=1))) < 0.2 * correction
    assert sweeps.shape == (p.n_steps,) and (sweeps >= 1).all() and sweeps.max() > 1
    assert (lam[:, 0] >= 0).all() and (np.abs(lam[:, 1]) <= 0.5 * lam[:, 0] + 1e-12).all()  # inside the cones


def test_a_solve_already_at_its_answer_stops_at_once(recorded):
    p = Steps(build_graph_set(recorded, max_steps=20), mu=0.5)
    colour = colour_points(p.ends, p.inverse, seed=0)
    lam, _ = gauss_seidel(p, colour, threshold=1e-6, max_sweeps=5000)
    again, sweeps = gauss_seidel(p, colour, threshold=1e-4, max_sweeps=1000, start=lam)
    assert (sweeps == 1).all() and np.allclose(again, lam, atol=1e-4)


def test_the_command_sets_the_orders_answers_side_by_side(recorded, tmp_path):
    out = tmp_path / "order.json"
    done = deepcontact("bench", "order", "--data", str(recorded), "--steps", "20", "--orders", "3", "--model", "",
                       "--json", str(out))
    assert done.returncode == 0, done.stderr
    report = json.loads(out.read_text())
    assert report["steps"] == 20 and len(report["replica_sweeps"]) == 3
    assert len(report["order_spread_rms"]) == len(report["order_spread_self_stress_share"]) == 3  # the pairs
    assert all(0.0 <= s <= 1.0 + 1e-9 for s in report["order_spread_self_stress_share"])
    assert report["answer_moved_rms"] < report["start_moved_rms"]  # the solve keeps little of a moved start
    assert "orders 0-1" in done.stdout and "model" not in report


def test_one_order_is_not_a_comparison(recorded, capsys):
    assert main(["bench", "order", "--data", str(recorded), "--orders", "1"]) == 2
    assert "--orders 2 or more" in capsys.readouterr().err
