"""`deepcontact train`: a tiny run end to end, resuming, and the ways it refuses bad input."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from deepcontact.gridspec import GridSpec
from training import train as train_command
from training.dataset import Writer

# A model small enough to train in a second or two on 61 x 61 grids.
TINY = json.dumps({"stem_filters": 4, "scales": 2, "branch_filters": [4], "head_filters": [4], "l2": 0.0001})


def deepcontact_train(*argv) -> int:
    """`deepcontact train ARGV...` (built from the module, as the CLI does)."""
    parser = argparse.ArgumentParser(prog="deepcontact train")
    train_command.add_arguments(parser)
    return train_command.run(parser.parse_args([str(a) for a in argv]))


def tiny_run(data, out, *extra) -> int:
    return deepcontact_train("--train", data / "train.h5", "--val", data / "val.h5", "--out", out,
                             "--config", TINY, "--batch-size", 8, "--quiet", *extra)


def test_a_tiny_run_writes_checkpoint_and_logs_then_resumes(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert tiny_run(data, out, "--epochs", 1) == 0
    for name in ("run.json", "state.json", "checkpoint.weights.h5", "best.weights.h5", "optimizer.h5",
                 "cache/train-0/inputs.npy", "cache/val-0/point_targets.npy", "cache/val-0/point_weights.npy"):
        assert (out / name).exists(), name
    assert list((out / "tb" / "train").iterdir()) and list((out / "tb" / "validation").iterdir())
    state = json.loads((out / "state.json").read_text())
    assert state["epochs_done"] == 1 and state["finished"] and state["stop_reason"] == "epochs"
    epoch = state["history"][0]
    assert np.isfinite(epoch["val_grid_mse"])
    # The loss at the contact points, normal and tangent separately, N s.
    assert set(epoch["val_contact"]) == {"impulse_normal", "impulse_tangent"}
    assert all(np.isfinite(v["mse"]) for v in epoch["val_contact"].values())
    # The normalization is the training set's, stored in the run's GridSpec.
    run = json.loads((out / "run.json").read_text())
    spec = GridSpec.from_dict(run["gridspec"])
    assert set(spec.normalization) == set(spec.inputs) | set(spec.targets)
    inputs = np.load(out / "cache" / "train-0" / "inputs.npy", mmap_mode="r")
    assert spec.normalization["vx"][0] == pytest.approx(float(inputs[..., 1].mean(dtype=np.float64)), abs=1e-6)
    assert "epoch 1:" in capsys.readouterr().out

    cache_written = (out / "cache" / "train-0" / "meta.json").stat().st_mtime_ns
    assert deepcontact_train("--out", out, "--resume", "--epochs", 2, "--quiet") == 0
    state = json.loads((out / "state.json").read_text())
    assert state["epochs_done"] == 2 and [h["epoch"] for h in state["history"]] == [1, 2]
    assert (out / "cache" / "train-0" / "meta.json").stat().st_mtime_ns == cache_written  # grids reused
    assert json.loads((out / "run.json").read_text())["commands"][-1].endswith("--resume")

    # Finished: resuming without more epochs, or starting over in the same directory, is refused.
    assert deepcontact_train("--out", out, "--resume", "--quiet") == 2
    assert "already finished" in capsys.readouterr().err
    assert tiny_run(data, out, "--epochs", 1) == 2
    assert "--resume" in capsys.readouterr().err


def test_resuming_gives_the_weights_of_an_uninterrupted_run(data, tmp_path):
    # Seeds fix the weights and the batch order per epoch; Adam's state is checkpointed too.
    # (A constant rate: the cosine's length is the first invocation's --epochs.)
    assert tiny_run(data, tmp_path / "straight", "--epochs", 2, "--lr-schedule", "constant") == 0
    assert tiny_run(data, tmp_path / "resumed", "--epochs", 1, "--lr-schedule", "constant") == 0
    assert deepcontact_train("--out", tmp_path / "resumed", "--resume", "--epochs", 2, "--quiet") == 0
    straight = json.loads((tmp_path / "straight" / "state.json").read_text())["history"]
    resumed = json.loads((tmp_path / "resumed" / "state.json").read_text())["history"]
    assert [h["val_grid_mse"] for h in straight] == [h["val_grid_mse"] for h in resumed]
    assert (tmp_path / "straight" / "checkpoint.weights.h5").read_bytes() == \
        (tmp_path / "resumed" / "checkpoint.weights.h5").read_bytes()


def test_a_nan_loss_stops_and_keeps_the_last_good_checkpoint(data, tmp_path, capsys):
    out = tmp_path / "run"
    assert tiny_run(data, out, "--epochs", 1) == 0
    before = (out / "checkpoint.weights.h5").read_bytes()
    # An absurd learning rate sends the weights to infinity within a few batches.
    assert deepcontact_train("--out", out, "--resume", "--epochs", 3, "--lr", "1e38", "--steps-per-epoch", 4,
                             "--quiet") == 1
    err = capsys.readouterr().err
    assert "non-finite" in err and "epoch 1" in err
    assert (out / "checkpoint.weights.h5").read_bytes() == before
    assert json.loads((out / "state.json").read_text())["epochs_done"] == 1


def test_missing_and_empty_data_files_stop_with_a_clear_message(data, tmp_path, capsys):
    assert deepcontact_train("--train", tmp_path / "none.h5", "--val", data / "val.h5", "--out", tmp_path / "a") == 2
    assert "no such data file" in capsys.readouterr().err
    empty = tmp_path / "empty.h5"
    with Writer(empty, scene={}, seeds=[], command="test"):
        pass
    assert deepcontact_train("--train", empty, "--val", data / "val.h5", "--out", tmp_path / "b") == 2
    assert "holds no steps" in capsys.readouterr().err
    assert not (tmp_path / "a" / "state.json").exists() and not (tmp_path / "b" / "state.json").exists()


def test_a_channel_mismatch_between_data_and_model_config_is_refused(data, tmp_path, capsys):
    assert deepcontact_train("--train", data / "train.h5", "--val", data / "val.h5", "--out", tmp_path / "r",
                             "--config", '{"in_channels": 7}') == 2
    err = capsys.readouterr().err
    assert "channel mismatch" in err and "in_channels=7" in err


def test_validation_must_use_other_seeds(data, tmp_path, capsys):
    assert deepcontact_train("--train", data / "train.h5", "--val", data / "train.h5", "--out", tmp_path / "r") == 2
    assert "share seeds" in capsys.readouterr().err


def test_resume_without_a_run_is_refused(tmp_path, capsys):
    assert deepcontact_train("--out", tmp_path / "nothing", "--resume") == 2
    assert "no run to resume" in capsys.readouterr().err


def test_the_points_loss_is_the_error_the_solver_receives_at_the_contact_points(data, tmp_path):
    # Train with the points loss, then recompute its validation value by hand:
    # the model's grid through the transfer's own G2P, against the recorded impulses.
    from deepcontact.transfer import g2p
    from training.models import build_model, config_from_dict

    out = tmp_path / "run"
    assert tiny_run(data, out, "--epochs", 1, "--loss", "points", "--tangent-weight", 0.5) == 0
    run = json.loads((out / "run.json").read_text())
    state = json.loads((out / "state.json").read_text())
    spec = GridSpec.from_dict(run["gridspec"])
    model = build_model(config_from_dict(run["model"]))
    model.load_weights(out / "best.weights.h5")
    cache = out / "cache" / "val-0"
    inputs = np.load(cache / "inputs.npy")
    offsets, positions = np.load(cache / "point_offsets.npy"), np.load(cache / "point_positions.npy")
    truth = np.load(cache / "point_targets.npy")
    pred = spec.denormalize(model(spec.normalize(inputs), training=False).numpy(), "targets")
    at_points = np.concatenate([g2p(p, positions[a:b], spec, outside="drop")[0]
                                for p, a, b in zip(pred, offsets[:-1], offsets[1:])])
    err = np.square((at_points - truth) / np.asarray(run["point_scale"])) * [1.0, 0.5]
    assert state["history"][0]["val_loss"] == pytest.approx(err.sum() / (2 * len(truth)), rel=1e-3)


def test_training_on_worlds_of_several_box_sizes(data, tmp_path):
    from commands import main

    wide = tmp_path / "wide.h5"
    assert main(["generate", "--steps", "20", "--seeds", "4", "--box-size", "20", "10", "--bodies", "40",
                 "--out", str(wide), "--quiet"]) == 0
    out = tmp_path / "run"
    assert deepcontact_train("--train", data / "train.h5", "--train", wide, "--val", data / "val.h5",
                             "--out", out, "--config", TINY, "--batch-size", 8, "--epochs", 1, "--quiet") == 0
    assert np.load(out / "cache" / "train-1" / "inputs.npy", mmap_mode="r").shape[1:3] == (41, 81)
    run = json.loads((out / "run.json").read_text())
    assert [d["scene"]["box_size"] for d in run["data"]["train"]] == [[15.0, 15.0], [20.0, 10.0]]
    # The loss cannot change on resume: it is part of what the run is.
    assert deepcontact_train("--out", out, "--resume", "--epochs", 2, "--loss", "grid", "--quiet") == 2


def test_a_residual_model_of_the_oracle_with_velocity_and_temporal_inputs(data, tmp_path):
    out = tmp_path / "run"
    inputs = "mass,vx,vy,omega,normal_x,normal_y,builtin_normal,builtin_tangent,vn_builtin,separation,new_point," \
             "previous_builtin_normal"
    assert deepcontact_train("--train", data / "train-oracle.h5", "--val", data / "val-oracle.h5", "--out", out,
                             "--model", "unet", "--config", '{"widths": [4, 8], "convs": 1}', "--inputs", inputs,
                             "--targets", "oracle_correction_normal,oracle_correction_tangent",
                             "--new-point-weight", 2, "--batch-size", 8, "--epochs", 1, "--quiet") == 0
    spec = GridSpec.from_dict(json.loads((out / "run.json").read_text())["gridspec"])
    assert spec.inputs == tuple(inputs.split(",")) and spec.targets[0] == "oracle_correction_normal"
    grids = np.load(out / "cache" / "train-0" / "inputs.npy", mmap_mode="r")
    assert np.abs(grids[..., 8]).max() > 0 and np.abs(grids[..., 11]).max() > 0  # velocities, last step's impulses
    # Without the oracle in the data, oracle targets are refused with the reason.
    assert deepcontact_train("--train", data / "train.h5", "--val", data / "val.h5", "--out", tmp_path / "no",
                             "--targets", "oracle_correction_normal,oracle_correction_tangent", "--quiet") == 2
