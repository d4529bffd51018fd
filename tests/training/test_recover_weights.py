"""training.recover_weights: a shipped graph model's weights back from its ONNX file,
in the form `train-graph --init` reads."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from deepcontact.modelcard import ModelCard
from training.graph_model import GraphConfig
from training.recover_weights import PARITY_TOLERANCE, main, recover
from training.train_graph import initial_weights

SHIPPED = Path(__file__).parents[2] / "lab" / "models"  # the research store


def test_the_default_s_weights_come_back_and_init_accepts_them(tmp_path):
    card = SHIPPED / "graph-projected-max-1-799-long-e2.json"
    out = tmp_path / "cache" / "long-e2.weights.npz"
    assert main([str(card), "--out", str(out)]) == 0
    assert out.exists() and not list(out.parent.glob("*.part*"))

    config = GraphConfig(**ModelCard.load(card).architecture["config"])
    weights = initial_weights(out, config)   # what --init does: raises if the network differs
    assert sum(w.size for w in weights.values()) == ModelCard.load(card).parameters

    again, parity = recover(card)
    assert parity < PARITY_TOLERANCE
    assert all(np.array_equal(again[k], weights[k]) for k in weights)


def test_a_network_with_probes_comes_back_through_its_physics_inputs(tmp_path):
    card = SHIPPED / "graph-mse-20k-r8-probes8.json"
    config = GraphConfig(**ModelCard.load(card).architecture["config"])
    assert config.probes == 8   # its ONNX file reads geometry, masses and inverse too

    weights, parity = recover(card)
    assert parity < PARITY_TOLERANCE
    assert sum(w.size for w in weights.values()) == ModelCard.load(card).parameters


def test_a_grid_model_is_refused(tmp_path, capsys):
    assert main([str(SHIPPED / "pressure.json"), "--out", str(tmp_path / "x.npz")]) == 2
    assert "graph models only" in capsys.readouterr().err
    assert not (tmp_path / "x.npz").exists()


def test_a_rebuild_is_compared_with_the_shipped_weights(tmp_path, capsys):
    card = SHIPPED / "graph-mse-1-799-e16.json"
    same = tmp_path / "same.npz"
    assert main([str(card), "--out", str(same)]) == 0
    assert main([str(card), "--against", str(same)]) == 0
    assert "identical" in capsys.readouterr().out

    weights = dict(np.load(same))
    weights["decode1/bias"] = weights["decode1/bias"] + 0.25
    moved = tmp_path / "moved.npz"
    np.savez(moved, **weights)
    assert main([str(card), "--against", str(moved)]) == 1
    assert "largest difference 0.25 (decode1/bias), 1 of 32 tensors differ" in capsys.readouterr().out
    assert main([str(card), "--against", str(tmp_path / "none.npz")]) == 2
