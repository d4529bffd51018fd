"""`deepcontact train`: fit a warm-start CNN (Pressure, UNet, Peak) on recorded simulations.

    deepcontact train --model pressure --train data/train.h5 --val data/val.h5 --out runs/NAME
    deepcontact train --train a.h5 --train b.h5 --val c.h5 --val d.h5 --out runs/NAME   # several worlds
    deepcontact train --out runs/NAME --resume            # go on from the last finished epoch

Inputs are the shared transfer's grids of the channels the run names
(``deepcontact.features``, wall mass included), targets the named contact
channels (the final impulse by default; the correction to Box2D's warm start,
or the oracle's, for residual models); both normalized per channel with
statistics of the training grids, stored in the run's GridSpec
(``spec.with_normalization``) so they travel with the exported model.

The loss (``--loss``):
    points  (default) what the solver receives: the predicted grids
            denormalized and sent back to the recorded contact points with
            SPH G2P *inside the graph* (a sparse gather with the plan's
            weights, ``TransferPlan.g2p_operator``), against the point
            targets; squared errors in units of each channel's spread at the
            points, weighted ``--tangent-weight`` for the tangent channel and
            ``--new-point-weight`` for points new this step.
    grid    the thesis's: MSE of the normalized target grid.
plus the models' L2 terms. Adam, learning rate ``--lr`` (thesis §7: 1e-3),
cosine-decayed to 2 % over the run's first ``--epochs`` (``--lr-schedule``).

Several training (or validation) files may come from different worlds (box
sizes, hence grid shapes): each batch comes from one file, batches of all
files are shuffled together. Every epoch the model is scored on the
validation files: the loss, the grid MSE and the errors at the contact
points (N s, normal and tangent separately). Training stops early when the
validation loss has not improved for ``--patience`` epochs; the best epoch's
weights are what export ships.

Run directory (``--out``):

    run.json                what the run is: model config, GridSpec with normalization,
                            data files, settings, the commands that ran it
    state.json              progress (RunState): epochs done, history, best epoch, finished;
                            written last at the end of every epoch (the commit point)
    checkpoint.weights.h5   weights after the last finished epoch (``--resume`` starts here)
    optimizer.h5            Adam's state after that epoch
    best.weights.h5         weights of the best validation epoch (what export ships)
    tb/train, tb/validation TensorBoard logs
    cache/train-K, val-K    the grids of file K, computed once per run (.npy, memory-mapped)

Bad input stops the run with a message and exit status 2 (missing or empty
files, a scene or channel mismatch, non-finite data); a NaN or infinite loss
stops it with status 1 and leaves the last good checkpoint untouched.
"""

from __future__ import annotations

import argparse
import dataclasses
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
    open_dataset,
    point_baselines,
    point_errors,
    point_values,
    pooled_normalization,
    spec_for_scene,
)
from training.models import config_from_dict, config_to_dict, default_config

RUN_VERSION = 2
DEFAULTS = {"epochs": 20, "batch_size": 32, "lr": 1e-3, "patience": 5, "max_val_steps": 2000, "loss": "points",
            "lr_schedule": "cosine", "tangent_weight": 1.0, "new_point_weight": 1.0}
LOSSES = ("points", "grid")
SCHEDULES = ("cosine", "constant")
FINAL_LR_SHARE = 0.02  # where the cosine ends, as a share of --lr
VAL_BATCH = 64


class TrainError(Exception):
    """Input the run cannot go on with; the message says why."""


# --------------------------------------------------------------------------- #
# Command line
# --------------------------------------------------------------------------- #


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", choices=("pressure", "unet", "peak"), default=None,
                        help="architecture: pressure (thesis §7.2, the default; any grid), unet (a U-Net with skips; any grid) "
                             "or peak (thesis §7.1; the fixed grid it was trained on, 17.5 M weights)")
    parser.add_argument("--train", type=Path, action="append",
                        help="training data, an HDF5 file from `deepcontact generate`; repeat for several worlds")
    parser.add_argument("--val", type=Path, action="append",
                        help="validation data (other seeds than --train); repeat for several worlds")
    parser.add_argument("--out", type=Path, required=True, help="run directory, e.g. runs/pressure")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in --out from its last finished epoch (its data and model are reused)")
    parser.add_argument("--epochs", type=int, help=f"maximum epochs in all (default {DEFAULTS['epochs']})")
    parser.add_argument("--batch-size", type=int, help=f"steps per batch (default {DEFAULTS['batch_size']})")
    parser.add_argument("--lr", type=float,
                        help=f"Adam learning rate (default {DEFAULTS['lr']}; may change on --resume)")
    parser.add_argument("--lr-schedule", choices=SCHEDULES,
                        help="cosine: decay to 2%% of --lr over the first --epochs; constant: --lr throughout "
                             f"(default {DEFAULTS['lr_schedule']})")
    parser.add_argument("--loss", choices=LOSSES,
                        help="points: error at the contact points through SPH G2P in the graph; grid: MSE of the "
                             f"normalized target grid, as the thesis (default {DEFAULTS['loss']})")
    parser.add_argument("--tangent-weight", type=float,
                        help=f"points loss: weight of the tangent channel (default {DEFAULTS['tangent_weight']})")
    parser.add_argument("--new-point-weight", type=float,
                        help="points loss: weight of points new this step, against 1 for persisting ones "
                             f"(default {DEFAULTS['new_point_weight']})")
    parser.add_argument("--patience", type=int,
                        help="stop after this many epochs without a better validation loss "
                             f"(default {DEFAULTS['patience']})")
    parser.add_argument("--max-steps-per-file", type=int, metavar="N",
                        help="use at most N training steps of each file (drawn at random with --seed; "
                             "default all with contacts)")
    parser.add_argument("--max-val-steps", type=int, metavar="N",
                        help=f"use at most N steps of each validation file (default {DEFAULTS['max_val_steps']})")
    parser.add_argument("--steps-per-epoch", type=int, metavar="N",
                        help="batches per epoch (default: one pass over the training steps)")
    parser.add_argument("--seed", type=int, default=None,
                        help="seed of weights, step choice and batch order (default 0)")
    parser.add_argument("--config", metavar="JSON",
                        help="model config overrides as JSON, or @FILE: e.g. '{\"branch_filters\": [16, 16]}'")
    parser.add_argument("--inputs", help=f"input channels, comma-separated (default {','.join(DEFAULT_INPUTS)}; "
                                         "see deepcontact/channels.py)")
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


def _command(args: argparse.Namespace) -> str:
    """The command line of this invocation, rebuilt from the parsed flags."""
    words = ["deepcontact", "train"]
    for flag in ("model", "train", "val", "out", "epochs", "batch_size", "lr", "lr_schedule", "loss",
                 "tangent_weight", "new_point_weight", "patience", "max_steps_per_file", "max_val_steps",
                 "steps_per_epoch", "seed", "config", "inputs", "targets", "resolution", "support"):
        value = getattr(args, flag, None)
        for v in (value if isinstance(value, list) else [value]):
            if v is not None:
                words += [f"--{flag.replace('_', '-')}", str(v)]
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


@dataclasses.dataclass
class RunState:
    """A run's progress, saved as state.json at the end of every epoch (the commit point)."""

    epochs_done: int = 0
    best_epoch: int | None = None
    best_val_loss: float | None = None
    epochs_since_best: int = 0
    finished: bool = False
    stop_reason: str | None = None
    history: list = dataclasses.field(default_factory=list)
    train_seconds: float = 0.0

    @classmethod
    def load(cls, path: Path) -> "RunState":
        data = json.loads(path.read_text())
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})

    def record(self, entry: dict, patience: int, epochs: int, seconds: float) -> bool:
        """Add an epoch's entry; returns whether it is the best so far, and
        decides whether the run is finished (early stopping or last epoch)."""
        self.history.append(entry)
        self.epochs_done = entry["epoch"]
        self.train_seconds = round(self.train_seconds + seconds, 2)
        best = self.best_val_loss is None or entry["val_loss"] < self.best_val_loss
        if best:
            self.best_epoch, self.best_val_loss, self.epochs_since_best = entry["epoch"], entry["val_loss"], 0
        else:
            self.epochs_since_best += 1
        stop = self.epochs_since_best >= patience
        if stop or self.epochs_done >= epochs:
            self.finished, self.stop_reason = True, "early stopping" if stop else "epochs"
        return best


# --------------------------------------------------------------------------- #
# Setting a run up
# --------------------------------------------------------------------------- #


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
        if not a.train or not a.val:
            raise TrainError("--train and --val are required for a new run")
        for name, value in (("--epochs", a.epochs), ("--batch-size", a.batch_size), ("--patience", a.patience),
                            ("--max-steps-per-file", a.max_steps_per_file), ("--max-val-steps", a.max_val_steps),
                            ("--steps-per-epoch", a.steps_per_epoch)):
            if value is not None and value < 1:
                raise TrainError(f"{name} must be >= 1, got {value}")
        if a.lr is not None and not (a.lr > 0 and math.isfinite(a.lr)):
            raise TrainError(f"--lr must be a positive number, got {a.lr}")
        for name, value in (("--tangent-weight", a.tangent_weight), ("--new-point-weight", a.new_point_weight)):
            if value is not None and not (value >= 0 and math.isfinite(value)):
                raise TrainError(f"{name} must be a number >= 0, got {value}")
        kind = a.model or "pressure"
        scene = self._check_files(a.train, a.val)
        try:
            spec = spec_for_scene(scene, resolution=a.resolution or 0.25, h=a.support or 0.5,
                                  inputs=_channels(a.inputs, DEFAULT_INPUTS),
                                  targets=_channels(a.targets, DEFAULT_TARGETS))
        except ValueError as exc:
            raise TrainError(str(exc)) from None
        config = model_config(kind, spec, _overrides(a.config))
        seed = 0 if a.seed is None else a.seed
        settings = {key: getattr(a, key) if getattr(a, key) is not None else DEFAULTS[key] for key in DEFAULTS}
        settings.update(max_steps_per_file=a.max_steps_per_file, steps_per_epoch=a.steps_per_epoch, seed=seed)
        settings["decay_epochs"] = settings["epochs"]  # the cosine's length, fixed when the run starts
        self.out.mkdir(parents=True, exist_ok=True)
        self.train_sets, self.val_sets = self._grid_sets(list(a.train), list(a.val), spec, settings)
        spec = spec.with_normalization(pooled_normalization(self.train_sets, spec))
        self.run_info = {
            "version": RUN_VERSION,
            "model": config_to_dict(config),
            "gridspec": spec.to_dict(),
            "transfer": TRANSFER,
            "data": {"train": [_file_info(p, g) for p, g in zip(a.train, self.train_sets)],
                     "val": [_file_info(p, g) for p, g in zip(a.val, self.val_sets)]},
            "settings": settings,
            "point_scale": _point_scale(self.train_sets),
            "baselines": point_baselines(self.val_sets[0], spec),
            "commands": [_command(a)],
        }
        self.state = RunState()
        write_json_atomic(self.out / "run.json", self.run_info)
        self._setup(config, spec)

    @staticmethod
    def _check_files(train: list[Path], val: list[Path]) -> dict:
        """The first training file's scene; refuses files that share seeds across train and val."""
        seeds: dict[str, set] = {"train": set(), "val": set()}
        scene = None
        for role, paths in (("train", train), ("val", val)):
            for path in paths:
                ds = open_dataset(path)
                try:
                    scene = scene or ds.scene
                    seeds[role] |= {(json.dumps(ds.scene.get("box_size")), s) for s in ds.seeds}
                finally:
                    ds.close()
        overlap = sorted(s for _, s in seeds["train"] & seeds["val"])
        if overlap:
            raise TrainError(f"--train and --val share seeds {overlap[:5]} of one world: validation must use "
                             "other worlds")
        return scene

    def _grid_sets(self, train: list[Path], val: list[Path], spec: GridSpec,
                   settings: dict) -> tuple[list[GridSet], list[GridSet]]:
        bars = None if self.quiet else _bar
        out = []
        for role, paths, limit in (("train", train, settings["max_steps_per_file"]),
                                   ("val", val, settings["max_val_steps"])):
            sets = []
            for k, path in enumerate(paths):
                # Each file on its own scene's grid (same resolution, support, channels).
                scene = open_dataset(path)
                try:
                    file_spec = spec_for_scene(scene.scene, resolution=spec.resolution, h=spec.h,
                                               kernel=spec.kernel, inputs=spec.inputs, targets=spec.targets)
                finally:
                    scene.close()
                gs, _ = cached_grid_set(path, file_spec, self.out / "cache" / f"{role}-{k}", max_steps=limit,
                                        seed=settings["seed"], progress_factory=bars)
                sets.append(gs)
            out.append(sets)
        return out[0], out[1]

    # -- resumed run -------------------------------------------------------- #

    def _reopen(self) -> None:
        a = self.args
        try:
            self.run_info = json.loads((self.out / "run.json").read_text())
            self.state = RunState.load(self.out / "state.json")
        except FileNotFoundError:
            raise TrainError(
                f"{self.out}: no run to resume (no run.json/state.json; it never finished an epoch)") from None
        except json.JSONDecodeError as exc:
            raise TrainError(f"{self.out}: run files are not JSON ({exc})") from None
        if self.run_info.get("version") != RUN_VERSION:
            raise TrainError(f"{self.out}: a run of an older deepcontact (version {self.run_info.get('version')}); "
                             "start a new run")
        if not (self.out / "checkpoint.weights.h5").exists():
            raise TrainError(f"{self.out}: no checkpoint.weights.h5 to resume from")
        info, settings = self.run_info, self.run_info["settings"]
        for flag in ("model", "train", "val", "config", "inputs", "targets", "resolution", "support", "loss",
                     "tangent_weight", "new_point_weight", "lr_schedule", "max_steps_per_file", "max_val_steps",
                     "batch_size", "seed"):
            if getattr(a, flag, None) is not None:
                raise TrainError(f"--{flag.replace('_', '-')} cannot change on --resume (the run's data, model and "
                                 f"loss are fixed); start a new run in another --out")
        for flag in ("epochs", "patience", "lr", "steps_per_epoch"):
            if getattr(a, flag) is not None:
                settings[flag] = getattr(a, flag)
        st = self.state
        if st.finished:
            if st.stop_reason == "early stopping" or st.epochs_done >= settings["epochs"]:
                raise TrainError(f"{self.out}: the run already finished ({st.stop_reason}, "
                                 f"{st.epochs_done} epochs); pass a larger --epochs to train on")
            st.finished, st.stop_reason = False, None
        spec = GridSpec.from_dict(info["gridspec"])
        config = config_from_dict(info["model"])
        raw = spec.with_normalization({})
        self.train_sets, self.val_sets = self._grid_sets([Path(d["path"]) for d in info["data"]["train"]],
                                                         [Path(d["path"]) for d in info["data"]["val"]], raw, settings)
        for gs in self.train_sets + self.val_sets:
            if gs.inputs.shape[-1] != config.in_channels or gs.targets.shape[-1] != config.out_channels:
                raise TrainError(f"channel mismatch: grids have {gs.inputs.shape[-1]} inputs / "
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

        s = self.run_info["settings"]
        self.tf, self.keras = tf, keras
        self.config, self.spec = config, spec
        keras.utils.set_random_seed(s["seed"] + self.state.epochs_done)
        self.model = build_model(config)
        self.parameters = count_parameters(self.model)
        self.run_info["parameters"] = self.parameters
        self.per_epoch = self._batches_per_epoch()
        lr = s["lr"]
        if s["lr_schedule"] == "cosine":
            lr = keras.optimizers.schedules.CosineDecay(s["lr"], s["decay_epochs"] * self.per_epoch,
                                                        alpha=FINAL_LR_SHARE)
        self.optimizer = keras.optimizers.Adam(lr)
        self.optimizer.build(self.model.trainable_variables)
        self.in_mean, self.in_std = spec.normalization_arrays(spec.inputs)
        self.out_mean, self.out_std = spec.normalization_arrays(spec.targets)
        self.train_step, self.predict = _compiled_steps(tf, self.model, self.optimizer, config, self.run_info,
                                                        self.out_mean, self.out_std)

    def _batches_per_epoch(self) -> int:
        s = self.run_info["settings"]
        if s["steps_per_epoch"]:
            return s["steps_per_epoch"]
        return sum(math.ceil(len(gs) / s["batch_size"]) for gs in self.train_sets)

    def _save_checkpoint(self, best: bool) -> None:
        import h5py

        part = self.out / ".checkpoint.part.weights.h5"
        with warnings.catch_warnings():
            # Keras 3.15 calls np.array(variable) inside save_weights, which NumPy 2.4 flags; harmless.
            warnings.filterwarnings("ignore", "__array__ implementation doesn't accept a copy keyword",
                                    DeprecationWarning)
            self.model.save_weights(part)
            if best:
                best_part = self.out / ".best.part.weights.h5"
                self.model.save_weights(best_part)
                os.replace(best_part, self.out / "best.weights.h5")
        store: dict[str, Any] = {}
        self.optimizer.save_own_variables(store)
        opt_part = self.out / ".optimizer.part.h5"
        with h5py.File(opt_part, "w") as f:
            f.attrs["epoch"] = self.state.epochs_done
            for key, value in store.items():
                f.create_dataset(key, data=self.keras.ops.convert_to_numpy(value))
        os.replace(part, self.out / "checkpoint.weights.h5")
        os.replace(opt_part, self.out / "optimizer.h5")
        # Last: the epoch counts once this is written.
        write_json_atomic(self.out / "state.json", dataclasses.asdict(self.state))

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
        if self.run_info["settings"]["lr_schedule"] == "constant":
            self.optimizer.learning_rate.assign(self.run_info["settings"]["lr"])

    # -- batches ------------------------------------------------------------ #

    def _batch(self, gs: GridSet, idx: np.ndarray) -> tuple[np.ndarray, ...]:
        """Normalized grids (B, ny, nx, Cin), (B, ny, nx, Cout) and the batch's
        points: G2P nodes (P, S) into the flattened batch, weights (P, S),
        targets (P, Cout) and per-point loss weights (P,)."""
        x = (np.asarray(gs.inputs[idx]) - self.in_mean) / self.in_std
        y = (np.asarray(gs.targets[idx]) - self.out_mean) / self.out_std
        rows = np.concatenate([np.arange(gs.point_offsets[k], gs.point_offsets[k + 1]) for k in idx])
        counts = (gs.point_offsets[idx + 1] - gs.point_offsets[idx]).astype(np.int64)
        cells = int(np.prod(gs.inputs.shape[1:3]))
        shift = np.repeat(np.arange(len(idx), dtype=np.int64) * cells, counts)
        nodes = (np.asarray(gs.point_nodes[rows]) + shift[:, None]).astype(np.int32)
        new_weight = self.run_info["settings"]["new_point_weight"]
        point_w = np.where(gs.point_new[rows], new_weight, 1.0).astype(np.float32)
        return (x.astype(np.float32, copy=False), y.astype(np.float32, copy=False), nodes,
                np.asarray(gs.point_weights[rows]), gs.point_targets[rows].astype(np.float32), point_w)

    def _epoch_batches(self, epoch: int) -> list[tuple[int, np.ndarray]]:
        """(file, step indices) of every batch of an epoch: each file's steps in
        batches, all files' batches shuffled together; fixed by (seed, epoch),
        so a resumed run replays it."""
        s = self.run_info["settings"]
        rng = np.random.default_rng([s["seed"], epoch])
        bs = s["batch_size"]
        batches = []
        for f, gs in enumerate(self.train_sets):  # loop over files
            order = rng.permutation(len(gs))
            batches += [(f, np.sort(order[i:i + bs])) for i in range(0, len(order), bs)]
        picks = rng.permutation(len(batches))
        if len(picks) < self.per_epoch:  # --steps-per-epoch beyond one pass: go round again
            picks = np.concatenate([picks] * math.ceil(self.per_epoch / len(picks)))
        return [batches[i] for i in picks[:self.per_epoch]]

    # -- training ----------------------------------------------------------- #

    def fit(self) -> int:
        s, st = self.run_info["settings"], self.state
        tf = self.tf
        n = sum(len(gs) for gs in self.train_sets)
        tb_train = tf.summary.create_file_writer(str(self.out / "tb" / "train"))
        tb_val = tf.summary.create_file_writer(str(self.out / "tb" / "validation"))
        _say(f"{self.config.kind}: {self.parameters['trainable']:,} trainable parameters; {n} training steps in "
             f"{len(self.train_sets)} file(s), {sum(len(g) for g in self.val_sets)} validation steps; "
             f"{self.per_epoch} batches of {s['batch_size']} per epoch; {s['loss']} loss")
        while st.epochs_done < s["epochs"]:
            epoch = st.epochs_done + 1
            t0 = time.perf_counter()
            sums = np.zeros(3)  # loss, grid mse, loss with L2
            bar = None if self.quiet else _bar(self.per_epoch, f"epoch {epoch}/{s['epochs']}", unit="batch")
            try:
                for b, (f, idx) in enumerate(self._epoch_batches(epoch)):
                    values = np.array([float(v) for v in self.train_step(*self._batch(self.train_sets[f], idx))])
                    if not np.isfinite(values).all():
                        return self._diverged(epoch, b + 1, values)
                    sums += values
                    if bar is not None:
                        bar.update(1)
                        bar.set_postfix(loss=f"{sums[0] / (b + 1):.4f}")
                    if b % 10 == 0:
                        with tb_train.as_default(step=int(self.optimizer.iterations.numpy())):
                            self._scalar("batch/loss", values[0])
                            self._scalar("batch/grid_mse", values[1])
            finally:
                if bar is not None:
                    bar.close()
            val = self.validate()
            if not math.isfinite(val["loss"]):
                return self._diverged(epoch, self.per_epoch, np.array([val["loss"]]), where="validation")
            seconds = time.perf_counter() - t0
            means = sums / self.per_epoch
            entry = {"epoch": epoch, "train_loss": means[0], "train_grid_mse": means[1],
                     "train_loss_with_l2": means[2], "val_loss": val["loss"], "val_grid_mse": val["grid_mse"],
                     "val_contact": val["contact"], "lr": float(self._lr()), "seconds": round(seconds, 2)}
            best = st.record(entry, s["patience"], s["epochs"], seconds)
            self._save_checkpoint(best)
            self._log_epoch(tb_train, tb_val, entry)
            contact = "  ".join(f"{k.replace('impulse_', '')} {v['rmse']:.4f}" for k, v in val["contact"].items())
            _say(f"epoch {epoch}: train loss {means[0]:.4f}  val loss {val['loss']:.4f} (grid mse "
                 f"{val['grid_mse']:.4f})  contact rmse N s: {contact}  ({seconds:.0f} s)" + ("  best" if best else ""))
            if st.finished:
                break
        tb_train.close()
        tb_val.close()
        if st.best_epoch:
            best = st.history[st.best_epoch - 1]
            _say(f"done ({st.stop_reason}, {st.epochs_done} epochs, {st.train_seconds:.0f} s): "
                 f"best epoch {best['epoch']}, val loss {best['val_loss']:.4f}; "
                 f"export with: deepcontact export {self.out} --out models/{self.out.name}.onnx")
        return 0

    def _lr(self) -> float:
        lr = self.optimizer.learning_rate
        return float(lr.numpy() if hasattr(lr, "numpy") else lr)

    def _diverged(self, epoch: int, batch: int, values: np.ndarray, where: str = "training") -> int:
        last = self.state.epochs_done
        kept = (f"the last good checkpoint (epoch {last}) is kept in {self.out}; resume with a lower --lr"
                if last else "no epoch had finished, so there is no checkpoint")
        print(f"deepcontact train: the {where} loss became non-finite ({values.tolist()}) at epoch {epoch}, "
              f"batch {batch}; stopped. {kept}", file=sys.stderr)
        return 1

    def validate(self) -> dict[str, Any]:
        """The loss (as trained), grid MSE (normalized) and contact-point errors (N s)
        over all validation files."""
        spec = self.spec
        loss_sum = sq_sum = 0.0
        loss_count = count = 0
        values, truth = [], []
        for gs in self.val_sets:  # loop over files
            for start in range(0, len(gs), VAL_BATCH):
                idx = np.arange(start, min(start + VAL_BATCH, len(gs)))
                batch = self._batch(gs, idx)
                pred, loss = (v.numpy() for v in self.predict(*batch))
                y = batch[1]
                sq_sum += float(np.square(pred.astype(np.float64) - y).sum())
                count += y.size
                loss_sum += float(loss) * len(idx)
                loss_count += len(idx)
                values.append(point_values(spec.denormalize(pred, "targets"), gs, spec, start))
            truth.append(gs.point_targets)
        contact = point_errors(np.concatenate(values), np.concatenate(truth), spec.targets)
        return {"loss": loss_sum / loss_count, "grid_mse": sq_sum / count, "contact": contact}

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
            self._scalar("epoch/loss", entry["train_loss"])
            self._scalar("epoch/grid_mse", entry["train_grid_mse"])
            self._scalar("epoch/lr", entry["lr"])
        with tb_val.as_default(step=entry["epoch"]):
            self._scalar("epoch/loss", entry["val_loss"])
            self._scalar("epoch/grid_mse", entry["val_grid_mse"])
            for name, errs in entry["val_contact"].items():
                for metric in ("mse", "mae"):
                    self._scalar(f"contact/{name}_{metric}", errs[metric])
        tb_train.flush()
        tb_val.flush()


def _point_scale(train_sets: list[GridSet]) -> list[float]:
    """Spread (RMS, N s) of each target channel at the training points: the
    points loss measures errors in these units."""
    sq = sum(np.square(gs.point_targets.astype(np.float64)).sum(axis=0) for gs in train_sets)
    n = sum(len(gs.point_targets) for gs in train_sets)
    rms = np.sqrt(sq / max(n, 1))
    return [float(v) if v > 1e-12 else 1.0 for v in rms]


def _compiled_steps(tf, model, optimizer, config, run_info: dict, out_mean, out_std):
    """The compiled training step and prediction of a run: (train_step, predict).

    train_step(x, y, nodes, weights, point_y, point_w) -> (loss, grid mse, loss + L2)
    predict(x, y, nodes, weights, point_y, point_w)    -> (normalized prediction, loss)
    The points loss sends the denormalized prediction to the batch's contact
    points with SPH G2P (sum over the stencil of weight x node value).
    """
    s = run_info["settings"]
    use_points = s["loss"] == "points"
    c_out = config.out_channels
    mean, std = tf.constant(out_mean), tf.constant(out_std)
    channel_w = np.ones(c_out, np.float32)
    if c_out == 2:
        channel_w[1] = s["tangent_weight"]
    scale = tf.constant(np.asarray(run_info["point_scale"], np.float32))
    channel_w = tf.constant(channel_w)
    hw = (None, None) if not config.fixed_grid else tuple(config.grid_shape)
    sig = [tf.TensorSpec((None, *hw, config.in_channels), tf.float32),
           tf.TensorSpec((None, *hw, c_out), tf.float32),
           tf.TensorSpec((None, None), tf.int32), tf.TensorSpec((None, None), tf.float32),
           tf.TensorSpec((None, c_out), tf.float32), tf.TensorSpec((None,), tf.float32)]

    def losses(pred, y, nodes, weights, point_y, point_w):
        grid_mse = tf.reduce_mean(tf.square(pred - y))
        if not use_points:
            return grid_mse, grid_mse
        node_values = tf.reshape(pred, (-1, c_out)) * std + mean  # (B * ny * nx, C) N s
        at_points = tf.reduce_sum(tf.gather(node_values, nodes) * weights[..., None], axis=1)  # (P, C)
        err = tf.square((at_points - point_y) / scale) * channel_w * point_w[:, None]
        return tf.reduce_sum(err) / tf.maximum(tf.reduce_sum(point_w) * float(c_out), 1.0), grid_mse

    @tf.function(input_signature=sig)
    def train_step(x, y, nodes, weights, point_y, point_w):
        with tf.GradientTape() as tape:
            pred = model(x, training=True)
            loss, grid_mse = losses(pred, y, nodes, weights, point_y, point_w)
            total = loss + tf.add_n(model.losses) if model.losses else loss
        grads = tape.gradient(total, model.trainable_variables)
        optimizer.apply_gradients(zip(grads, model.trainable_variables))
        return loss, grid_mse, total

    @tf.function(input_signature=sig)
    def predict(x, y, nodes, weights, point_y, point_w):
        pred = model(x, training=False)
        return pred, losses(pred, y, nodes, weights, point_y, point_w)[0]

    return train_step, predict


def _say(text: str) -> None:
    # Epoch lines are the run's record and print even with --quiet (which only drops the bars).
    print(text, flush=True)


def _bar(total: int, desc: str, unit: str = "step"):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, leave=False, dynamic_ncols=True)
