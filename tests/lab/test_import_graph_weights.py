"""lab.import_graph_weights: a network trained elsewhere (lab.train_graph_jax) served
here, over a real server; and the JAX trainer's batching, which needs no JAX."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from deepcontact.modelcard import ModelCard
from training.contact_graph import build_graph_set
from lab.import_graph_weights import import_weights, main
from training.recover_weights import recover
from lab.train_graph_jax import concatenate, padded_batch, parse_config

from tests.training.test_ensemble import served

SHIPPED = Path(__file__).parents[2] / "lab" / "models"  # the research store
SOURCE = "graph-projected-max-1-799"  # a network train-graph wrote: width 32, 3 rounds


def probe_for(card: ModelCard, key: str) -> dict:
    """What train_graph_jax writes in probe.json for one network of `card`'s shape."""
    config = card.architecture["config"]
    return {"command": "python -m lab.train_graph_jax ...", "jax": "test", "device": "cpu",
            "train": ["a.h5"], "val": ["b.h5"], "train_steps": 1, "train_points": 1, "val_steps": 1, "val_points": 1,
            "read_seconds": 0.0, "train_seconds": 1.0, "batch_steps": 1, "lr": 1e-3, "seed": 0,
            "normalization": {k: list(v) for k, v in card.gridspec.normalization.items()}, "loss": "mse",
            "loss_no_correction": 2.0, "steps": 1, "epochs": 0.1,
            "networks": {key: {"width": config["width"], "rounds": config["rounds"],
                               "layer_norm": config.get("layer_norm", False), "best_loss": 0.5,
                               "best_at_seconds": 1.0, "history": [[1.0, 1, 0.6, 0.5]]}}}


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """The shipped SOURCE, and `imported`: its weights and normalization brought in as a
    train_graph_jax run leaves them."""
    folder = tmp_path_factory.mktemp("imported")
    for suffix in (".json", ".onnx"):
        shutil.copy(SHIPPED / f"{SOURCE}{suffix}", folder)
    run = tmp_path_factory.mktemp("run")  # not the served folder: the server reads every card there
    weights, _ = recover(folder / f"{SOURCE}.json")
    np.savez(run / "jax-w32-r3.weights.npz", **weights)
    (run / "probe.json").write_text(json.dumps(probe_for(ModelCard.load(folder / f"{SOURCE}.json"), "jax-w32-r3")))
    import_weights(run / "jax-w32-r3.weights.npz", run / "probe.json", folder, name="imported")
    return folder, run


def test_an_imported_network_serves_what_the_same_weights_serve_when_train_graph_wrote_them(folder, thesis_steps):
    folder, _ = folder
    world, steps = thesis_steps
    for shipped, imported in zip(served(folder, SOURCE, world, steps), served(folder, "imported", world, steps)):
        np.testing.assert_allclose(imported, shipped, atol=1e-5)


def test_the_imported_card_says_where_and_how_the_network_was_trained(folder):
    folder, _ = folder
    card = ModelCard.load(folder / "imported.json")
    assert (card.kind, card.combine, card.parameters) == ("graph", "residual", 21474)
    assert card.training["trained_with"] == "lab.train_graph_jax"
    assert card.validation["loss"] == 0.5 and card.parity_max_abs_error < 1e-4
    assert card.gridspec.normalization == ModelCard.load(folder / f"{SOURCE}.json").gridspec.normalization


def test_import_refuses_a_probe_without_that_network_and_a_name_for_several_files(folder, capsys):
    _, run = folder
    other = run / "jax-w64-r8.weights.npz"
    shutil.copy(run / "jax-w32-r3.weights.npz", other)
    assert main([str(other), "--probe", str(run / "probe.json"), "--out-dir", str(run)]) == 2
    assert "describes no network 'jax-w64-r8'" in capsys.readouterr().err
    assert main([str(other), str(other), "--probe", str(run / "probe.json"), "--name", "x"]) == 2
    assert "--name names one model" in capsys.readouterr().err
    assert main([str(run / "missing.weights.npz"), "--probe", str(run / "probe.json")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_a_padded_batch_holds_the_steps_and_padding_that_weighs_nothing_and_moves_no_body(data):
    gs = build_graph_set(data / "train.h5")
    zero, one = np.zeros(len(gs.inputs), np.float32), np.ones(len(gs.inputs), np.float32)
    steps = np.array([0, 2, 3])
    points, ends, dynamic, targets, mask = padded_batch(gs, steps, zero, one, np.zeros(2, np.float32),
                                                        np.ones(2, np.float32), bucket=256)
    f, t, e, d = gs.batch(steps)
    n = len(f)
    assert len(points) % 256 == 0 and len(points) > n and mask.sum() == n
    np.testing.assert_array_equal(points[:n], f)
    np.testing.assert_array_equal(targets[:n], t)
    np.testing.assert_array_equal(ends[:n], e)
    np.testing.assert_array_equal(dynamic[:len(d)], d)
    # Every padded point joins the last body, which is static and not one of the steps'.
    assert len(dynamic) > len(d) and dynamic[-1, 0] == 0
    assert (ends[n:] == len(dynamic) - 1).all() and (points[n:] == 0).all()


def test_concatenated_sets_batch_each_step_as_its_own_set_does(data):
    a, b = build_graph_set(data / "train.h5"), build_graph_set(data / "val.h5")
    both = concatenate([a, b])
    assert len(both) == len(a) + len(b)
    for step, (own, k) in ((0, (a, 0)), (len(a) - 1, (a, len(a) - 1)), (len(a) + 1, (b, 1))):
        for got, want in zip(both.batch([step]), own.batch([k])):
            np.testing.assert_array_equal(got, want)


def test_a_network_is_given_as_width_x_rounds_and_n_for_layer_norms():
    assert parse_config("128x8") == (128, 8, False)
    assert parse_config("64x16n") == (64, 16, True)
    for bad in ("128", "0x3", "ax3", "8x2m"):
        with pytest.raises(Exception, match="WIDTHxROUNDS|>= 1"):
            parse_config(bad)


@pytest.mark.skipif(importlib.util.find_spec("jax") is not None, reason="JAX is installed here")
def test_the_jax_trainer_says_it_needs_jax_where_jax_is_missing(data, tmp_path, capsys):
    from lab.train_graph_jax import main as train

    assert train(["--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--config", "8x2",
                  "--out", str(tmp_path / "run")]) == 2
    assert "needs JAX" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_the_jax_trainer_leaves_each_networks_weights_and_its_validation_history(data, tmp_path):
    pytest.importorskip("jax", reason="JAX is not a dependency; lab.train_graph_jax runs where it is installed")
    from lab.train_graph_jax import main as train

    out = tmp_path / "run"
    assert train(["--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--config", "8x2",
                  "--config", "8x2n", "--seconds", "3", "--val-every", "1", "--batch-steps", "4", "--point-bucket", "256",
                  "--workers", "1", "--feeders", "1", "--out", str(out)]) == 0
    probe = json.loads((out / "probe.json").read_text())
    run = probe["networks"]["jax-w8-r2"]
    assert (run["width"], run["rounds"]) == (8, 2) and run["history"] and np.isfinite(run["best_loss"])
    with np.load(out / "jax-w8-r2.weights.npz") as f:
        assert f["encode0/kernel"].shape == (14, 8) and f["round1_update1/kernel"].shape == (8, 8)
        assert "round0_norm/gain" not in f.files
    assert probe["networks"]["jax-w8-r2-ln"]["layer_norm"] is True
    with np.load(out / "jax-w8-r2-ln.weights.npz") as f:
        assert f["round1_norm/gain"].shape == (8,) and f["decode_norm/offset"].shape == (8,)


def test_a_network_with_layer_norms_is_imported_with_them_and_its_onnx_file_computes_what_tensorflow_does(tmp_path):
    from training.graph_model import GraphConfig, init_weights

    config = GraphConfig(in_channels=14, width=8, rounds=3, layer_norm=True)
    weights = init_weights(config, seed=2)
    rng = np.random.default_rng(0)
    weights = {k: v + rng.normal(0, 0.1, v.shape).astype(np.float32) for k, v in weights.items()}  # not the identity
    np.savez(tmp_path / "jax-w8-r3-ln.weights.npz", **weights)
    card = ModelCard.load(SHIPPED / f"{SOURCE}.json")
    probe = probe_for(card, "jax-w8-r3-ln")
    probe["networks"]["jax-w8-r3-ln"].update(width=8, rounds=3, layer_norm=True)
    (tmp_path / "probe.json").write_text(json.dumps(probe))
    out = tmp_path / "served"
    out.mkdir()
    imported = import_weights(tmp_path / "jax-w8-r3-ln.weights.npz", tmp_path / "probe.json", out)
    assert imported.architecture["config"]["layer_norm"] is True
    assert imported.parameters == sum(v.size for v in weights.values())
    assert imported.parity_max_abs_error < 1e-4
    recovered, _ = recover(out / "jax-w8-r3-ln.json")
    assert set(recovered) == set(weights) and "round2_norm/gain" in recovered


def test_the_jax_network_computes_what_the_tensorflow_network_does_with_and_without_layer_norms():
    pytest.importorskip("jax", reason="JAX is not a dependency; lab.train_graph_jax runs where it is installed")
    import jax
    import jax.numpy as jnp

    from training.graph_model import ContactGraphNet, GraphConfig, init_weights
    from lab.train_graph_jax import _network

    forward = _network(jax, jnp)
    rng = np.random.default_rng(1)
    points = rng.standard_normal((60, 14)).astype(np.float32)
    ends = rng.integers(0, 12, (60, 2)).astype(np.int32)
    dynamic = (rng.random((12, 1)) < 0.8).astype(np.float32)
    for norm in (False, True):
        config = GraphConfig(in_channels=14, width=8, rounds=3, layer_norm=norm)
        weights = {k: v + rng.normal(0, 0.1, v.shape).astype(np.float32)
                   for k, v in init_weights(config, seed=3).items()}
        want = ContactGraphNet(config, weights)(points, ends, dynamic).numpy()
        got = forward({k: jnp.asarray(v) for k, v in weights.items()}, points, ends, dynamic, 3)
        np.testing.assert_allclose(np.asarray(got), want, atol=1e-4)
