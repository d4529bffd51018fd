"""lab/graph_size.py: a shipped contact-graph model timed on synthetic steps of given sizes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from lab.graph_size import parse_sizes, synthetic_step
from commands import main

MODELS = Path(__file__).resolve().parents[2] / "lab" / "models"  # the research store


def test_sizes_read_as_points_by_bodies_and_bad_ones_are_refused():
    assert parse_sizes("140x100, 400X1600") == [(140, 100), (400, 1600)]
    with pytest.raises(ValueError, match="POINTSxBODIES"):
        parse_sizes("400")
    with pytest.raises(ValueError, match="at least 1"):
        parse_sizes("0x10")


def test_a_synthetic_step_has_the_server_s_shapes_and_ends_within_the_bodies():
    points, ends, dynamic = synthetic_step(7, 3, 14, np.random.default_rng(0))
    assert points.shape == (7, 14) and points.dtype == np.float32
    assert ends.shape == (7, 2) and ends.dtype == np.int32 and ends.min() >= 0 and ends.max() < 3
    assert dynamic.shape == (3, 1) and np.all(dynamic == 1)
    *_, geometry, masses, inverse = synthetic_step(7, 3, 14, np.random.default_rng(0), physics=True)  # probes
    assert geometry.shape == (7, 8) and masses.shape == (7, 2) and inverse.shape == (3, 2)
    np.testing.assert_allclose(np.linalg.norm(geometry[:, :2], axis=1), 1.0, rtol=1e-6)  # unit normals
    np.testing.assert_allclose((geometry[:, :2] * geometry[:, 2:4]).sum(axis=1), 0.0, atol=1e-6)  # tangents across


def test_the_default_and_a_named_model_are_timed_at_every_size(tmp_path, capsys):
    out = tmp_path / "sizes.json"
    code = main(["lab", "graph-size", "--models", str(MODELS), "--model", "default,graph-projected-max-1-799-long-e2",
                 "--sizes", "5x3,20x10", "--repeats", "2", "--json", str(out)])
    assert code == 0
    rows = json.loads(out.read_text())["rows"]
    target = json.loads((MODELS / "default.json").read_text())["alias_of"]
    assert [(r["model"], r["points"], r["bodies"]) for r in rows] == [
        ("default", 5, 3), ("default", 20, 10),
        ("graph-projected-max-1-799-long-e2", 5, 3), ("graph-projected-max-1-799-long-e2", 20, 10)]
    assert rows[0]["served"] == target and rows[2]["rounds"] == 3
    assert all(r["passes"] == 1 for r in rows)
    assert all(r["median_ms"] > 0 for r in rows)
    assert f"default ({target})" in capsys.readouterr().out


def test_a_grid_model_is_refused_with_a_message():
    with pytest.raises(SystemExit, match="not a contact-graph one"):
        main(["lab", "graph-size", "--models", str(MODELS), "--model", "pressure", "--sizes", "5x3", "--repeats", "1"])


def test_a_card_with_two_passes_is_timed_as_two_runs_of_its_network(tmp_path, monkeypatch):
    from server.predictors import GraphPredictor
    from training.card_variant import card_variant

    for suffix in (".json", ".onnx"):
        (tmp_path / f"graph-projected-max-1-799-long-e2{suffix}").write_bytes(
            (MODELS / f"graph-projected-max-1-799-long-e2{suffix}").read_bytes())
    card_variant(tmp_path / "graph-projected-max-1-799-long-e2.json", passes=2)
    runs, run_session = {}, GraphPredictor.run_session

    def counted(self, *feed):
        runs[self.name] = runs.get(self.name, 0) + 1
        return run_session(self, *feed)

    monkeypatch.setattr(GraphPredictor, "run_session", counted)
    out = tmp_path / "sizes.json"
    assert main(["lab", "graph-size", "--models", str(tmp_path), "--model",
                 "graph-projected-max-1-799-long-e2,graph-projected-max-1-799-long-e2-p2", "--sizes", "5x3",
                 "--repeats", "7", "--json", str(out)]) == 0
    once, twice = json.loads(out.read_text())["rows"]
    assert (once["passes"], twice["passes"]) == (1, 2)
    # Each model also runs once when it loads and once to plan the size's memory, untimed.
    assert runs == {"graph-projected-max-1-799-long-e2": 2 + 7, "graph-projected-max-1-799-long-e2-p2": 2 + 2 * 7}
