"""A second pass: `train-graph --second-pass CARD` also trains on steps whose warm start
a first pass has moved (training/second_pass.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from deepcontact.channels import Step, channel_values
from commands import main
from deepcontact.modelcard import ModelCard
from tests.training.conftest import SMALL
from training.card_variant import card_variant
from training.contact_graph import GRAPH_INPUTS, build_graph_set, one_world
from training.grids import iter_steps, open_dataset, select_steps
from training.second_pass import SecondPassError, moved


def test_moved_steps_read_what_the_server_reads_at_the_moved_warm_start(data):
    path = data / "val.h5"
    graphs = build_graph_set(path, max_steps=10)
    correction = np.random.default_rng(0).normal(0.0, 0.5, (len(graphs.targets), 2))
    second = moved(graphs, correction)
    # The same steps from the file, their warm start moved in the records and every channel
    # computed as the server computes it; which points are new stays the file's.
    with open_dataset(path) as ds:
        steps = ds.steps
    world = one_world([step for _, step in iter_steps(path, steps, select_steps(steps, 10, 0))])
    contacts = world.contacts.copy()
    contacts["builtin"] += correction.astype(np.float32)
    there = Step(world.bodies, contacts, None, world.physics)
    expected = channel_values(GRAPH_INPUTS, there)
    new = GRAPH_INPUTS.index("new_point")
    expected[:, new] = channel_values(("new_point",), world)[:, 0]
    scale = np.abs(expected).max(axis=0) + 1.0
    assert (np.abs(second.features - expected) / scale).max() < 1e-5
    left = channel_values(("correction_normal", "correction_tangent"), there)  # recorded impulse - moved warm start
    np.testing.assert_allclose(second.targets, left, atol=1e-5)
    np.testing.assert_allclose(second.builtin, contacts["builtin"], atol=1e-6)


def test_a_correction_must_be_one_per_point(data):
    graphs = build_graph_set(data / "val.h5", max_steps=3)
    with pytest.raises(SecondPassError, match="a correction per point"):
        moved(graphs, np.zeros((len(graphs.targets) + 1, 2)))


def test_train_graph_second_pass_trains_on_the_steps_and_on_them_moved_by_its_first(data, small_graph, tmp_path):
    folder, cache = small_graph
    out = tmp_path / "both.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--cache", str(cache), "--second-pass", str(folder / "small.json"),
                 "--init", str(cache / "small.weights.npz"), *SMALL]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    own = json.loads((folder / "small.json").read_text())
    assert card["training"]["second_pass"]["name"] == "small"
    # Validated on the recorded steps and on the same steps as the second pass sees them.
    assert card["validation"]["points"] == 2 * own["validation"]["points"]
    assert card["gridspec"]["normalization"] == own["gridspec"]["normalization"]  # the recorded steps'


def test_a_first_pass_that_serves_something_else_is_refused(data, small_graph, tmp_path, capsys):
    folder, cache = small_graph
    scaled = card_variant(folder / "small.json", correction_scale=0.5)
    out = tmp_path / "both.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--cache", str(cache), "--second-pass", str(scaled), *SMALL]) == 2
    assert "scale 0.5" in capsys.readouterr().err and not out.exists()


def test_a_network_trained_for_two_passes_is_scored_as_the_server_serves_it(data, small_graph, tmp_path):
    from server.predictors import GraphPredictor, World

    folder, cache = small_graph
    out = tmp_path / "twice.onnx"
    # At a rate of 1e-12 the weights stay the small model's: the validation loss is then the
    # squared error of what the server answers with those weights run twice.
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--cache", str(cache), "--passes", "2", "--init", str(cache / "small.weights.npz"),
                 "--lr", "1e-12", *SMALL]) == 0
    card = ModelCard.load(out.with_suffix(".json"))
    assert card.passes == 2
    predictor = GraphPredictor(card, out)
    path = data / "val.h5"
    with open_dataset(path) as ds:
        steps = ds.steps
    out_mean, out_std = card.gridspec.normalization_arrays(card.gridspec.targets)
    squares = []
    for _, step in iter_steps(path, steps, select_steps(steps, None, 0)):
        world = World(((0.0, 0.0), (1.0, 1.0)), step.physics)
        served = predictor.predict(step.bodies, step.contacts, world, 0).impulses
        error = (served - step.contacts["impulse"]) / out_std  # served - (builtin + recorded correction)
        squares.append(np.square(error).sum(axis=1))
    served_loss = np.concatenate(squares).mean()
    assert card.validation["loss"] == pytest.approx(served_loss, rel=1e-3)
    once = json.loads((folder / "small.json").read_text())["validation"]["loss"]
    assert abs(served_loss - once) > 1e-3 * once  # the second pass changed the answer


def test_passes_need_a_residual_model_whose_inputs_a_pass_can_move(data, tmp_path, capsys):
    base = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
            "--out", str(tmp_path / "x.onnx"), "--cache", str(tmp_path / "cache"), *SMALL]
    assert main(base + ["--passes", "2", "--combine", "new-points"]) == 2
    assert "only with --combine residual" in capsys.readouterr().err
    assert main(base + ["--passes", "2", "--extra-inputs", "vn_builtin_asinh"]) == 2
    assert "vn_builtin_asinh would need the engine" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()
