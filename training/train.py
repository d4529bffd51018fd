"""`deepcontact train`: fit a Pressure or Peak model on recorded simulations.

    deepcontact train --model pressure --train data/train.h5 --val data/val.h5 --out runs/NAME
    deepcontact train --out runs/NAME --resume            # go on from the last finished epoch

Inputs are the shared transfer's grids (``world_to_grids`` with the wall
mass), targets the final impulses splatted with ``targets_to_grids``; both
are normalized per channel with statistics of the training grids, which are
stored in the run's GridSpec (``spec.with_normalization``) and so travel with
the exported model.  Adam, learning rate 1e-3 (thesis §7), loss = grid MSE of
the normalized targets + the models' L2 terms.  After every epoch the model
is scored on the validation file: the grid MSE (normalized units, no L2),
and the loss *at the contact points*: predicted grids denormalized and sent
back with SPH G2P, against the recorded impulses, normal and tangent
separately (N s).  Training stops early when the validation grid MSE has not
improved for ``--patience`` epochs.

Run directory (``--out``):

    run.json                what the run is: model config, GridSpec with normalization,
                            data files, settings, the commands that ran it
    state.json              progress: epochs done, history, best epoch, finished;
                            written last at the end of every epoch (the commit point)
    checkpoint.weights.h5   weights after the last finished epoch (``--resume`` starts here)
    optimizer.h5            Adam's state after that epoch
    best.weights.h5         weights of the best validation epoch (what export ships)
    tb/train, tb/validation TensorBoard logs
    cache/train, cache/val  the grids, computed once per run (.npy, memory-mapped)

Bad input stops the run with a message and exit status 2 (missing or empty
files, a scene or channel mismatch, non-finite data); a NaN or infinite loss
stops it with status 1 and leaves the last good checkpoint untouched.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from deepcontact.channels import DEFAULT_INPUTS, DEFAULT_TARGETS
from deepcontact.gridspec import GridSpec
from deepcontact.io import write_json_atomic
from training.grids import (
    TRANSFER,
    GridDataError,
    GridSet,
    cached_grid_set,
    normalization_from,
    open_dataset,
    point_baselines,
    point_errors,
    point_values,
    spec_for_scene,
)
from training.models import config_from_dict, config_to_dict, default_config

RUN_VERSION = 1
DEFAULTS = {"epochs": 20, "batch_size": 32, "lr": 1e-3, "patience": 5, "max_val_steps": 2000}
VAL_BATCH = 64


class TrainError(Exception):
    """Input the run cannot go on with; the message says why."""


# --------------------------------------------------------------------------- #
# Command line
# --------------------------------------------------------------------------- #


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=("pressure", "peak"), default=None,
                        help="architecture (default pressure; thesis §7.2 / §7.1)")
    parser.add_argument("--train", type=Path, help="training data, an HDF5 file from `deepcontact generate`")
    parser.add_argument("--val", type=Path, help="validation data (other seeds than --train)")
    parser.add_argument("--out", type=Path, required=True, help="run directory, e.g. runs/pressure")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last finished epoch (its data and model are reused)")
    parser.add_argument("--epochs", type=int, help=f"maximum epochs in all (default {DEFAULTS['epochs']})")
    parser.add_argument("--batch-size", type=int, help=f"steps per batch (default {DEFAULTS['batch_size']})")
    parser.add_argument("--lr", type=float,
                        help=f"Adam learning rate (default {DEFAULTS['lr']}; may change on --resume)")
    parser.add_argument("--patience", type=int,
                        help="stop after this many epochs without a better validation loss "
                             f"(default {DEFAULTS['patience']})")
    parser.add_argument("--max-steps-per-file", type=int, metavar="N",
                        help="use at most N training steps (drawn at random with --seed; default all with contacts)")
    parser.add_argument("--max-val-steps", type=int, metavar="N",
                        help=f"use at most N validation steps (default {DEFAULTS['max_val_steps']})")
    parser.add_argument("--steps-per-epoch", type=int, metavar="N",
                        help="batches per epoch (default: one pass over the training steps)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of weights, step choice and batch order (default 0)")
    parser.add_argument("--config", metavar="JSON",
                        help="model config overrides as JSON, or @FILE: e.g. '{\"branch_filters\": [16, 16]}'")
    parser.add_argument("--inputs", help=f"input channels, comma-separated (default {','.join(DEFAULT_INPUTS)})")
    parser.add_argument("--targets", help=f"target channels, comma-separated (default {','.join(DEFAULT_TARGETS)})")
    parser.add_argument("--resolution", type=float, default=None, help="grid spacing, m (default 0.25)")
    parser.add_argument("--support", type=float, default=None, help="SPH support radius h, m (default 0.5)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    try:
        return Trainer(args).fit()
    except (TrainError, GridDataError) as exc:
        print(f"deepcontact train: {exc}", file=sys.stderr)
        return 2


# --------------------------------------------------------------------------- #
# Setting a run up
# --------------------------------------------------------------------------- #


def _command(args: argparse.Namespace) -> str:
    """The command line of this invocation, rebuilt from the parsed flags."""
    words = ["deepcontact", "train"]
    for flag in ("model", "train", "val", "out", "epochs", "batch_size", "lr", "patience", "max_steps_per_file",
                 "max_val_steps", "steps_per_epoch", "seed", "config", "inputs", "targets", "resolution",
                 "support"):
        value = getattr(args, flag, None)
        if value is not None:
            words += [f"--{flag.replace('_', '-')}", str(value)]
    words += ["--resume"] if args.resume else []
    return shlex.join(words)


def _overrides(text: str | None) -> dict[str, Any]:
    if not text:
        return {}
    if text.startswith("@"):
        try:
            text = Path(text[1:]).read_text()
        except OSError as exc:
            raise TrainError(f"--config {text}: {exc.strerror}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise TrainError(f"--config is not JSON: {exc}") from None
    if not isinstance(data, dict):
        raise TrainError("--config must be a JSON object of config fields")
    return data


def _channels(text: str | None, default: tuple[str, ...]) -> tuple[str, ...]:
    return default if not text else tuple(c.strip() for c in text.split(",") if c.strip())


def model_config(kind: str, spec: GridSpec, overrides: dict[str, Any]):
    """The model config for ``spec``'s channels (and grid, for Peak); a
    contradicting override is a channel mismatch and raises TrainError."""
    derived = {"in_channels": len(spec.inputs), "out_channels": len(spec.targets)}
    if kind == "peak":
        derived["grid_shape"] = list(spec.shape)
    for key, value in derived.items():
        if key in overrides and overrides[key] != value:
            raise TrainError(
                f"channel mismatch: the config says {key}={overrides[key]!r}, the data's grids have {value!r} "
                f"(inputs {list(spec.inputs)}, targets {list(spec.targets)}, grid {list(spec.shape)})")
    try:
        return default_config(kind, **{**overrides, **derived})
    except (TypeError, ValueError) as exc:
        raise TrainError(f"bad model config: {exc}") from None


def _file_info(path: Path, gs: GridSet) -> dict[str, Any]:
    import h5py

    with h5py.File(path, "r") as f:
        command = str(f.attrs.get("command", ""))
    return {"path": str(path), "scene": gs.meta["scene"], "seeds": gs.meta["seeds"], "steps_used": len(gs),
            "points": int(gs.point_offsets[-1]), "command": command}


class Trainer:
    """One training run: sets the run directory up (or reopens it), then :meth:`fit`."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.out = Path(args.out)
        self.quiet = args.quiet
        if args.resume:
            self._reopen()
        else:
            self._create()

    # -- new run ------------------------------------------------------------ #

    def _create(self) -> None:
        a = self.args
        if (self.out / "state.json").exists():
            raise TrainError(f"{self.out} already holds a run; pass --resume to continue it or choose another --out")
        # A run.json without state.json never finished an epoch: nothing to keep, start it afresh.
        if a.train is None or a.val is None:
            raise TrainError("--train and --val are required for a new run")
        for name, value in (("--epochs", a.epochs), ("--batch-size", a.batch_size), ("--patience", a.patience),
                            ("--max-steps-per-file", a.max_steps_per_file), ("--max-val-steps", a.max_val_steps),
                            ("--steps-per-epoch", a.steps_per_epoch)):
            if value is not None and value < 1:
                raise TrainError(f"{name} must be >= 1, got {value}")
        if a.lr is not None and not (a.lr > 0 and math.isfinite(a.lr)):
            raise TrainError(f"--lr must be a positive number, got {a.lr}")
        kind = a.model or "pressure"
        train_ds = open_dataset(a.train)
        val_ds = open_dataset(a.val)
        try:
            scene = train_ds.scene
            if val_ds.scene.get("box_size") != scene.get("box_size"):
                raise TrainError(
                    f"{a.val} is scene {val_ds.scene.get('name')!r} with box {val_ds.scene.get('box_size')}, "
                    f"{a.train} is {scene.get('name')!r} with box {scene.get('box_size')}: one grid cannot serve both")
            overlap = sorted(set(train_ds.seeds) & set(val_ds.seeds))
            if overlap:
                raise TrainError(f"--train and --val share seeds {overlap[:5]}: validation must use other worlds")
        finally:
            train_ds.close()
            val_ds.close()
        try:
            spec = spec_for_scene(scene, resolution=a.resolution or 0.25, h=a.support or 0.5,
                                  inputs=_channels(a.inputs, DEFAULT_INPUTS),
                                  targets=_channels(a.targets, DEFAULT_TARGETS))
        except ValueError as exc:
            raise TrainError(str(exc)) from None
        config = model_config(kind, spec, _overrides(a.config))
        seed = 0 if a.seed is None else a.seed
        settings = {
            "epochs": a.epochs or DEFAULTS["epochs"],
            "batch_size": a.batch_size or DEFAULTS["batch_size"],
            "lr": a.lr or DEFAULTS["lr"],
            "patience": a.patience or DEFAULTS["patience"],
            "max_steps_per_file": a.max_steps_per_file,
            "max_val_steps": a.max_val_steps or DEFAULTS["max_val_steps"],
            "steps_per_epoch": a.steps_per_epoch,
            "seed": seed,
        }
        self.out.mkdir(parents=True, exist_ok=True)
        self.train_set, self.val_set = self._grid_sets(a.train, a.val, spec, settings)
        spec = spec.with_normalization(normalization_from(self.train_set, spec))
        self.run_info = {
            "version": RUN_VERSION,
            "model": config_to_dict(config),
            "gridspec": spec.to_dict(),
            "transfer": TRANSFER,
            "data": {"train": _file_info(a.train, self.train_set), "val": _file_info(a.val, self.val_set)},
            "settings": settings,
            "baselines": point_baselines(self.val_set, spec),
            "commands": [_command(a)],
        }
        self.state = {"epochs_done": 0, "best_epoch": None, "best_val_grid_mse": None, "epochs_since_best": 0,
                      "finished": False, "stop_reason": None, "history": [], "train_seconds": 0.0}
        write_json_atomic(self.out / "run.json", self.run_info)
        self._setup(config, spec)

    def _grid_sets(self, train: Path, val: Path, spec: GridSpec, settings: dict) -> tuple[GridSet, GridSet]:
        bars = None if self.quiet else _bar
        train_set, _ = cached_grid_set(train, spec, self.out / "cache" / "train",
                                       max_steps=settings["max_steps_per_file"], seed=settings["seed"],
                                       progress_factory=bars)
        val_set, _ = cached_grid_set(val, spec, self.out / "cache" / "val", max_steps=settings["max_val_steps"],
                                     seed=settings["seed"], progress_factory=bars)
        return train_set, val_set

    # -- resumed run -------------------------------------------------------- #

    def _reopen(self) -> None:
        a = self.args
        try:
            self.run_info = json.loads((self.out / "run.json").read_text())
            self.state = json.loads((self.out / "state.json").read_text())
        except FileNotFoundError:
            raise TrainError(
                f"{self.out}: no run to resume (no run.json/state.json; it never finished an epoch)") from None
        except json.JSONDecodeError as exc:
            raise TrainError(f"{self.out}: run files are not JSON ({exc})") from None
        if not (self.out / "checkpoint.weights.h5").exists():
            raise TrainError(f"{self.out}: no checkpoint.weights.h5 to resume from")
        info, settings = self.run_info, self.run_info["settings"]
        fixed = {"model": info["model"]["kind"], "train": info["data"]["train"]["path"],
                 "val": info["data"]["val"]["path"], "max_steps_per_file": settings["max_steps_per_file"],
                 "max_val_steps": settings["max_val_steps"], "batch_size": settings["batch_size"],
                 "seed": settings["seed"]}
        for flag in ("model", "train", "val", "config", "inputs", "targets", "resolution", "support",
                     "max_steps_per_file", "max_val_steps", "batch_size", "seed"):
            given = getattr(a, flag, None)
            if given is not None and (flag not in fixed or str(given) != str(fixed[flag])):
                raise TrainError(f"--{flag.replace('_', '-')} cannot change on --resume (the run's data and model "
                                 f"are fixed); start a new run in another --out")
        if a.epochs is not None:
            settings["epochs"] = a.epochs
        if a.patience is not None:
            settings["patience"] = a.patience
        if a.lr is not None:
            settings["lr"] = a.lr
        if a.steps_per_epoch is not None:
            settings["steps_per_epoch"] = a.steps_per_epoch
        if self.state["finished"]:
            if self.state["stop_reason"] == "early stopping" or self.state["epochs_done"] >= settings["epochs"]:
                raise TrainError(f"{self.out}: the run already finished ({self.state['stop_reason']}, "
                                 f"{self.state['epochs_done']} epochs); pass a larger --epochs to train on")
            self.state["finished"], self.state["stop_reason"] = False, None
        spec = GridSpec.from_dict(info["gridspec"])
        config = config_from_dict(info["model"])
        raw = spec.with_normalization({})
        self.train_set, self.val_set = self._grid_sets(Path(info["data"]["train"]["path"]),
                                                       Path(info["data"]["val"]["path"]), raw, settings)
        for name, gs in (("train", self.train_set), ("val", self.val_set)):
            if gs.inputs.shape[-1] != config.in_channels or gs.targets.shape[-1] != config.out_channels:
                raise TrainError(f"channel mismatch: {name} grids have {gs.inputs.shape[-1]} inputs / "
                                 f"{gs.targets.shape[-1]} targets, the model takes {config.in_channels} / "
                                 f"{config.out_channels}")
        info["commands"].append(_command(a))
        write_json_atomic(self.out / "run.json", info)
        self._setup(config, spec)
        self._load_checkpoint()

    # -- model, optimizer, checkpoints -------------------------------------- #

    def _setup(self, config, spec: GridSpec) -> None:
        from training.models import build_model, count_parameters, import_tensorflow

        tf = import_tensorflow()
        import keras

        self.tf, self.keras = tf, keras
        self.config, self.spec = config, spec
        keras.utils.set_random_seed(self.run_info["settings"]["seed"] + self.state["epochs_done"])
        self.model = build_model(config)
        self.parameters = count_parameters(self.model)
        self.run_info["parameters"] = self.parameters
        self.optimizer = keras.optimizers.Adam(self.run_info["settings"]["lr"])
        self.optimizer.build(self.model.trainable_variables)
        self.in_mean, self.in_std = spec.normalization_arrays(spec.inputs)
        self.out_mean, self.out_std = spec.normalization_arrays(spec.targets)
        model, optimizer = self.model, self.optimizer
        c_in, c_out = config.in_channels, config.out_channels
        hw = (None, None) if not config.fixed_grid else tuple(config.grid_shape)
        x_sig = tf.TensorSpec((None, *hw, c_in), tf.float32)
        y_sig = tf.TensorSpec((None, *hw, c_out), tf.float32)

        @tf.function(input_signature=[x_sig, y_sig])
        def train_step(x, y):
            with tf.GradientTape() as tape:
                pred = model(x, training=True)
                mse = tf.reduce_mean(tf.square(pred - y))
                loss = mse + tf.add_n(model.losses) if model.losses else mse
            grads = tape.gradient(loss, model.trainable_variables)
            optimizer.apply_gradients(zip(grads, model.trainable_variables))
            return mse, loss

        @tf.function(input_signature=[x_sig])
        def predict(x):
            return model(x, training=False)

        self.train_step, self.predict = train_step, predict

    def _save_checkpoint(self, best: bool) -> None:
        import h5py

        part = self.out / ".checkpoint.part.weights.h5"
        with warnings.catch_warnings():
            # Keras 3.15 calls np.array(variable) inside save_weights, which NumPy 2.4 flags; harmless.
            warnings.filterwarnings("ignore", "__array__ implementation doesn't accept a copy keyword",
                                    DeprecationWarning)
            self._save_weights(part, best)
        store: dict[str, Any] = {}
        self.optimizer.save_own_variables(store)
        opt_part = self.out / ".optimizer.part.h5"
        with h5py.File(opt_part, "w") as f:
            f.attrs["epoch"] = self.state["epochs_done"]
            for key, value in store.items():
                f.create_dataset(key, data=self.keras.ops.convert_to_numpy(value))
        os.replace(part, self.out / "checkpoint.weights.h5")
        os.replace(opt_part, self.out / "optimizer.h5")
        write_json_atomic(self.out / "state.json", self.state)  # last: the epoch counts once this is written

    def _save_weights(self, part: Path, best: bool) -> None:
        self.model.save_weights(part)
        if best:
            best_part = self.out / ".best.part.weights.h5"
            self.model.save_weights(best_part)
            os.replace(best_part, self.out / "best.weights.h5")

    def _load_checkpoint(self) -> None:
        import h5py

        self.model.load_weights(self.out / "checkpoint.weights.h5")
        opt = self.out / "optimizer.h5"
        if opt.exists():
            with h5py.File(opt, "r") as f:
                store = {k: f[k][()] for k in f.keys()}
            try:
                self.optimizer.load_own_variables(store)
            except ValueError as exc:
                raise TrainError(f"{opt}: does not fit the model ({exc})") from None
        self.optimizer.learning_rate.assign(self.run_info["settings"]["lr"])

    # -- training ----------------------------------------------------------- #

    def _batch(self, gs: GridSet, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = (np.asarray(gs.inputs[idx]) - self.in_mean) / self.in_std
        y = (np.asarray(gs.targets[idx]) - self.out_mean) / self.out_std
        return x.astype(np.float32, copy=False), y.astype(np.float32, copy=False)

    def fit(self) -> int:
        s, st = self.run_info["settings"], self.state
        tf = self.tf
        n = len(self.train_set)
        bs = s["batch_size"]
        per_epoch = math.ceil(n / bs) if not s["steps_per_epoch"] else s["steps_per_epoch"]
        tb_train = tf.summary.create_file_writer(str(self.out / "tb" / "train"))
        tb_val = tf.summary.create_file_writer(str(self.out / "tb" / "validation"))
        _say(f"{self.config.kind}: {self.parameters['trainable']:,} trainable parameters; "
             f"{n} training steps, {len(self.val_set)} validation steps; {per_epoch} batches of {bs} per epoch")
        while st["epochs_done"] < s["epochs"]:
            epoch = st["epochs_done"] + 1
            t0 = time.perf_counter()
            order = self._order(epoch, per_epoch * bs, n)
            mse_sum = loss_sum = 0.0
            bar = None if self.quiet else _bar(per_epoch, f"epoch {epoch}/{s['epochs']}", unit="batch")
            try:
                for b in range(per_epoch):
                    idx = np.sort(order[b * bs:(b + 1) * bs])  # sorted: memory-mapped reads go forward
                    mse, loss = (float(v) for v in self.train_step(*self._batch(self.train_set, idx)))
                    if not (math.isfinite(mse) and math.isfinite(loss)):
                        return self._diverged(epoch, b + 1, mse, loss)
                    mse_sum += mse
                    loss_sum += loss
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(mse=f"{mse_sum / (b + 1):.4f}", loss=f"{loss_sum / (b + 1):.4f}")
                    if b % 10 == 0:
                        with tb_train.as_default(step=int(self.optimizer.iterations.numpy())):
                            self._scalar("batch/grid_mse", mse)
                            self._scalar("batch/loss_with_l2", loss)
            finally:
                if bar is not None:
                    bar.close()
            val = self.validate()
            if not math.isfinite(val["grid_mse"]):
                return self._diverged(epoch, per_epoch, val["grid_mse"], val["grid_mse"], where="validation")
            seconds = time.perf_counter() - t0
            entry = {"epoch": epoch, "train_grid_mse": mse_sum / per_epoch, "train_loss": loss_sum / per_epoch,
                     "val_grid_mse": val["grid_mse"], "val_contact": val["contact"], "seconds": round(seconds, 2)}
            st["history"].append(entry)
            st["epochs_done"] = epoch
            st["train_seconds"] = round(st["train_seconds"] + seconds, 2)
            best = st["best_val_grid_mse"] is None or val["grid_mse"] < st["best_val_grid_mse"]
            if best:
                st["best_epoch"], st["best_val_grid_mse"], st["epochs_since_best"] = epoch, val["grid_mse"], 0
            else:
                st["epochs_since_best"] += 1
            stop = st["epochs_since_best"] >= s["patience"]
            if stop or epoch >= s["epochs"]:
                st["finished"], st["stop_reason"] = True, "early stopping" if stop else "epochs"
            self._save_checkpoint(best)
            self._log_epoch(tb_train, tb_val, entry)
            contact = "  ".join(f"{k.replace('impulse_', '')} {v['rmse']:.4f}" for k, v in val["contact"].items())
            _say(f"epoch {epoch}: train mse {entry['train_grid_mse']:.4f} (loss {entry['train_loss']:.4f})  "
                 f"val mse {val['grid_mse']:.4f}  contact rmse N s: {contact}  ({seconds:.0f} s)"
                 + ("  best" if best else ""))
            if stop:
                break
        tb_train.close()
        tb_val.close()
        best = st["history"][st["best_epoch"] - 1] if st["best_epoch"] else None
        if best:
            _say(f"done ({st['stop_reason']}, {st['epochs_done']} epochs, {st['train_seconds']:.0f} s): "
                 f"best epoch {best['epoch']}, val grid mse {best['val_grid_mse']:.4f}; "
                 f"export with: deepcontact export {self.out} --out models/{self.out.name}.onnx")
        return 0

    def _order(self, epoch: int, count: int, n: int) -> np.ndarray:
        """Sample order of an epoch: fixed by (seed, epoch), so a resumed run replays it."""
        rng = np.random.default_rng([self.run_info["settings"]["seed"], epoch])
        reps = math.ceil(count / n)
        return np.concatenate([rng.permutation(n) for _ in range(reps)])[:count]

    def _diverged(self, epoch: int, batch: int, mse: float, loss: float, where: str = "training") -> int:
        last = self.state["epochs_done"]
        kept = (f"the last good checkpoint (epoch {last}) is kept in {self.out}; resume with a lower --lr"
                if last else "no epoch had finished, so there is no checkpoint")
        print(f"deepcontact train: the {where} loss became non-finite (grid mse {mse}, loss {loss}) at epoch {epoch}, "
              f"batch {batch}; stopped. {kept}", file=sys.stderr)
        return 1

    def validate(self) -> dict[str, Any]:
        """Grid MSE (normalized) and contact-point errors (N s) on the validation set."""
        gs, spec = self.val_set, self.spec
        sq_sum, count, values = 0.0, 0, []
        for start in range(0, len(gs), VAL_BATCH):
            idx = np.arange(start, min(start + VAL_BATCH, len(gs)))
            x, y = self._batch(gs, idx)
            pred = self.predict(x).numpy()
            sq_sum += float(np.square(pred.astype(np.float64) - y).sum())
            count += y.size
            values.append(point_values(spec.denormalize(pred, "targets"), gs, spec, start))
        contact = point_errors(np.concatenate(values), gs.point_targets, spec.targets)
        return {"grid_mse": sq_sum / count, "contact": contact}

    def _scalar(self, tag: str, value: float) -> None:
        """A TensorBoard scalar.  tf.summary.scalar needs the tensorboard
        package, which the pinned environment lacks; this writes the same
        record (a float tensor tagged with the "scalars" plugin)."""
        from tensorflow.core.framework import summary_pb2

        if not hasattr(self, "_scalar_meta"):
            self._scalar_meta = summary_pb2.SummaryMetadata(
                plugin_data=summary_pb2.SummaryMetadata.PluginData(plugin_name="scalars"),
                data_class=summary_pb2.DATA_CLASS_SCALAR).SerializeToString()
        self.tf.summary.write(tag, self.tf.constant(float(value), self.tf.float32), metadata=self._scalar_meta)

    def _log_epoch(self, tb_train, tb_val, entry: dict) -> None:
        with tb_train.as_default(step=entry["epoch"]):
            self._scalar("epoch/grid_mse", entry["train_grid_mse"])
            self._scalar("epoch/loss_with_l2", entry["train_loss"])
        with tb_val.as_default(step=entry["epoch"]):
            self._scalar("epoch/grid_mse", entry["val_grid_mse"])
            for name, errs in entry["val_contact"].items():
                for metric in ("mse", "mae"):
                    self._scalar(f"contact/{name}_{metric}", errs[metric])
        tb_train.flush()
        tb_val.flush()


def _say(text: str) -> None:
    # Epoch lines are the run's record and print even with --quiet (which only drops the bars).
    print(text, flush=True)


def _bar(total: int, desc: str, unit: str = "step"):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, dynamic_ncols=True)
