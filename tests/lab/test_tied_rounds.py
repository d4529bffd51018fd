"""A tied network (train-graph --tied): one sweep's weights, run as many rounds as asked."""

import json

import numpy as np
import onnxruntime as ort
import pytest

from commands import main
from lab.tied_rounds import main as tied_rounds


def _step(in_channels: int, rng) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points (30, F), ends (30, 2) among 10 bodies, dynamic (10, 1) with one static body."""
    points = rng.standard_normal((30, in_channels)).astype(np.float32)
    ends = rng.integers(0, 10, size=(30, 2)).astype(np.int32)
    dynamic = (np.arange(10) > 0).astype(np.float32)[:, None]
    return points, ends, dynamic


@pytest.mark.parametrize("recall", [False, True])
def test_a_tied_network_holds_one_rounds_weights_and_runs_any_number_of_rounds(recall):
    from training.graph_model import ContactGraphNet, GraphConfig, count_parameters, init_weights

    tied = GraphConfig(in_channels=5, width=8, rounds=4, tied=True, recall=recall)
    untied = GraphConfig(in_channels=5, width=8, rounds=4, recall=recall)
    assert not any(k.startswith("round1_") for k in init_weights(tied))
    one_round = GraphConfig(in_channels=5, width=8, rounds=1, recall=recall)
    assert count_parameters(init_weights(tied)) == count_parameters(init_weights(one_round))

    rng = np.random.default_rng(0)
    weights = {k: (0.3 * rng.standard_normal(v.shape)).astype(np.float32) for k, v in init_weights(tied).items()}
    net = ContactGraphNet(tied, weights)
    step = _step(5, rng)
    # Four tied rounds are an untied network whose four rounds all hold round 0's weights.
    copies = dict(weights) | {k.replace("round0_", f"round{r}_"): v
                              for r in range(1, 4) for k, v in weights.items() if k.startswith("round0_")}
    np.testing.assert_allclose(np.asarray(net(*step)), np.asarray(ContactGraphNet(untied, copies)(*step)),
                               rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(net(*step, rounds=2)), np.asarray(net(*step)))  # depth is a choice
    with pytest.raises(ValueError, match="untied"):
        ContactGraphNet(untied, copies)(*step, rounds=2)


def test_train_graph_trains_a_tied_network_at_several_depths_and_exports_it_deeper(data, tmp_path, capsys):
    out = tmp_path / "tied.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "3", "--tied", "--recall",
                 "--train-rounds", "2-4", "--loss", "mse", "--cache", str(tmp_path / "cache"), "--quiet"]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    config = card["architecture"]["config"]
    assert config["tied"] is True and config["recall"] is True and config["rounds"] == 3
    assert card["training"]["settings"]["train_rounds"] == [2, 3, 4]
    assert card["parity_max_abs_error"] < 1e-4

    # Its validation loss at the depth it was validated at is the card's; at other depths, others.
    depths = ["--depths", "3,6", "--val", str(data / "val.h5"), "--cache", str(tmp_path / "cache")]
    capsys.readouterr()
    assert tied_rounds([str(out.with_suffix(".json")), *depths]) == 0
    printed = [line.split()[-1] for line in capsys.readouterr().out.splitlines()]
    assert float(printed[0]) == pytest.approx(card["validation"]["loss"], rel=1e-3)
    assert float(printed[1]) != pytest.approx(float(printed[0]), rel=1e-3)

    # The same weights at six rounds, recovered from the ONNX file, checked against TensorFlow.
    assert tied_rounds([str(out.with_suffix(".json")), "--rounds", "6"]) == 0
    deeper = json.loads((tmp_path / "tied-r6.json").read_text())
    assert deeper["name"] == "tied-r6" and deeper["onnx_file"] == "tied-r6.onnx"
    assert deeper["architecture"]["config"] == config | {"rounds": 6} and deeper["parity_max_abs_error"] < 1e-4
    assert deeper["commands"][-1].startswith("python -m lab.tied_rounds")
    rng = np.random.default_rng(1)
    points, ends, dynamic = _step(card["architecture"]["config"]["in_channels"], rng)
    feed = {"points": points, "ends": ends, "dynamic": dynamic}
    three, six = (ort.InferenceSession(str(tmp_path / f), providers=["CPUExecutionProvider"]).run(None, feed)[0]
                  for f in ("tied.onnx", "tied-r6.onnx"))
    assert three.shape == six.shape and not np.allclose(three, six)


def test_tied_options_refuse_what_they_cannot_do(data, tmp_path, capsys):
    base = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
            "--out", str(tmp_path / "m.onnx"), "--quiet"]
    assert main(base + ["--train-rounds", "2-4"]) == 2
    assert "--train-rounds needs --tied" in capsys.readouterr().err
    assert main(base + ["--tied", "--train-rounds", "4-2"]) == 2
    assert "range of round counts" in capsys.readouterr().err
    # An untied model has no one sweep to repeat.
    untied = tmp_path / "untied.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(untied),
                 "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse",
                 "--cache", str(tmp_path / "cache"), "--quiet"]) == 0
    assert tied_rounds([str(untied.with_suffix(".json")), "--rounds", "4"]) == 2
    assert "only a tied graph model" in capsys.readouterr().err
    assert not (tmp_path / "untied-r4.onnx").exists()
