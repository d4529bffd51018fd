"""`deepcontact export`: a finished training run -> ONNX model + model card.

    deepcontact export runs/NAME --out models/NAME.onnx      # also writes models/NAME.json

Loads the run's best weights (``best.weights.h5``, the epoch with the lowest
validation grid loss), converts the model with tf2onnx (opset 17) and writes
the card (:class:`deepcontact.modelcard.ModelCard`): the GridSpec with the
training normalization, ``fixed_grid``, architecture and parameter count,
training data, validation losses, the TensorFlow / ONNX Runtime parity error
and the commands that made the model.  Both files are written under a
temporary name and renamed.

The ONNX graph takes "grids" (batch, ny, nx, Cin) float32 and returns
"impulses" (batch, ny, nx, Cout) float32, both normalized; the batch
dimension is dynamic, and so are ny and nx for fully convolutional models
(Pressure).  ``tf2onnx.convert.from_keras`` does not work with Keras 3 here,
so the model is wrapped in a ``tf.function`` with an input signature and
converted with ``from_function``.

A run that has not finished (no ``state.json`` saying so, or no best
weights) is refused with exit status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import numpy as np

from deepcontact.envelope import Envelope
from deepcontact.gridspec import GridSpec
from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import COMBINE, ModelCard

OPSET = 17
PARITY_SEED = 0


class ExportError(Exception):
    """A run directory that cannot be exported; the message says why."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_dir", type=Path, help="a finished run of `deepcontact train`, e.g. runs/pressure")
    parser.add_argument("--out", type=Path, required=True,
                        help="ONNX file to write, e.g. models/pressure.onnx (the card goes beside it as .json)")
    parser.add_argument("--name", help="model name in the card (default: the --out file's stem)")
    parser.add_argument("--combine", choices=COMBINE,
                        help="how the served warm start uses the model's output (default: residual for runs whose "
                             "targets are correction_* channels, replace otherwise; see deepcontact.modelcard)")


def run(args: argparse.Namespace) -> int:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    try:
        card, onnx_path, card_path = export_run(args.run_dir, args.out, name=args.name,
                                                command=_command(args), combine=args.combine)
    except ExportError as exc:
        print(f"deepcontact export: {exc}", file=sys.stderr)
        return 2
    size = onnx_path.stat().st_size
    print(f"wrote {onnx_path} ({size / 1e3:.1f} kB, {card.parameters:,} parameters) and {card_path}; "
          f"TF vs ONNX Runtime max abs error {card.parity_max_abs_error:.2e}")
    return 0


def _command(args: argparse.Namespace) -> str:
    words = ["deepcontact", "export", str(args.run_dir), "--out", str(args.out)]
    return shlex.join(words + (["--name", args.name] if args.name else []))


def load_finished_run(run_dir: str | os.PathLike) -> tuple[dict, dict]:
    """(run.json, state.json) of a finished run; ExportError otherwise."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise ExportError(f"{run_dir}: no such run directory")
    try:
        info = json.loads((run_dir / "run.json").read_text())
        state = json.loads((run_dir / "state.json").read_text())
    except FileNotFoundError:
        raise ExportError(f"{run_dir}: no finished checkpoint (no run.json/state.json: training never finished "
                          f"an epoch)") from None
    except json.JSONDecodeError as exc:
        raise ExportError(f"{run_dir}: run files are not JSON ({exc})") from None
    if not state.get("finished"):
        raise ExportError(
            f"{run_dir}: training has not finished ({state.get('epochs_done', 0)} of {info['settings']['epochs']} "
            f"epochs done); finish it with `deepcontact train --out {run_dir} --resume`")
    if not (run_dir / "best.weights.h5").exists():
        raise ExportError(f"{run_dir}: no finished checkpoint (best.weights.h5 is missing)")
    return info, state


def export_run(run_dir: str | os.PathLike, out: str | os.PathLike, *, name: str | None = None,
               command: str | None = None, combine: str | None = None) -> tuple[ModelCard, Path, Path]:
    """Export the best weights of a finished run to ``out`` (.onnx) and its card (.json).

    Returns (card, onnx path, card path).
    """
    from training.models import build_model, config_from_dict, count_parameters, import_tensorflow

    run_dir, out = Path(run_dir), Path(out)
    if out.suffix != ".onnx":
        raise ExportError(f"--out must name a .onnx file, got {out}")
    info, state = load_finished_run(run_dir)
    config = config_from_dict(info["model"])
    spec = GridSpec.from_dict(info["gridspec"])
    tf = import_tensorflow()
    model = build_model(config)
    model.load_weights(run_dir / "best.weights.h5")
    proto = to_onnx(model, config)
    data = proto.SerializeToString()
    parity = parity_error(model, data, config, spec)

    write_bytes_atomic(out, data)
    params = count_parameters(model)
    train, val = info["data"]["train"], info["data"]["val"]
    commands = list(dict.fromkeys(d["command"] for d in train + val if d.get("command"))) + list(info["commands"])
    card = ModelCard(
        name=name or out.stem,
        kind=config.kind,
        onnx_file=out.name,
        gridspec=spec,
        fixed_grid=bool(config.fixed_grid),
        combine=combine or ("residual" if all("correction_" in t for t in spec.targets) else "replace"),
        parameters=params["total"],
        architecture={"config": info["model"], "parameters": params, "onnx_opset": OPSET,
                      "onnx_bytes": len(data), "tensorflow": tf.__version__},
        training=_training_record(info, state),
        validation=_validation_record(info, state),
        parity_max_abs_error=parity,
        commands=tuple(commands + ([command] if command else [])),
        trained_on=Envelope.from_scenes([d["scene"] for d in train]).to_dict() if all("scene" in d for d in train)
        else None,
    )
    card_path = out.with_suffix(".json")
    card.save(card_path)
    os.chmod(card_path, 0o644)  # the temporary file it was renamed from was private; a card is not
    return card, out, card_path


def _training_record(info: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    """The card's training section: the run's data, settings, transfer and epochs."""
    train, val = info["data"]["train"], info["data"]["val"]
    return {
        "scene": train[0]["scene"],
        "train": [_data_summary(d) for d in train],
        "val": [_data_summary(d) for d in val],
        "settings": info["settings"],
        "transfer": info["transfer"],
        "epochs_run": state["epochs_done"],
        "best_epoch": state["best_epoch"],
        "stop_reason": state["stop_reason"],
        "train_seconds": state["train_seconds"],
        "history": [[h["epoch"], round(h["train_loss"], 6), round(h["val_loss"], 6)] for h in state["history"]],
    }


def _validation_record(info: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    """The card's validation section: the best epoch's losses and the run's baselines."""
    best = state["history"][state["best_epoch"] - 1]
    val = info["data"]["val"]
    return {"epoch": best["epoch"], "steps": sum(d["steps_used"] for d in val),
            "points": sum(d["points"] for d in val), "loss": best["val_loss"],
            "grid_mse": best["val_grid_mse"], "contact": best["val_contact"],
            "baselines": info.get("baselines", {})}


def _data_summary(d: dict[str, Any]) -> dict[str, Any]:
    return {"path": d["path"], "seeds": seed_ranges(d["seeds"]), "steps_used": d["steps_used"],
            "points": d["points"]}


def seed_ranges(seeds: list[int]) -> str:
    """[1, 2, 3, 7] -> "1-3,7" (the form `deepcontact generate --seeds` takes)."""
    seeds = sorted(seeds)
    parts, i = [], 0
    while i < len(seeds):
        j = i
        while j + 1 < len(seeds) and seeds[j + 1] == seeds[j] + 1:
            j += 1
        parts.append(str(seeds[i]) if i == j else f"{seeds[i]}-{seeds[j]}")
        i = j + 1
    return ",".join(parts)


def to_onnx(model, config):
    """The Keras model as an ONNX ModelProto: input "grids", output "impulses", NHWC,
    dynamic batch (and dynamic ny, nx unless the config has a fixed grid)."""
    from training.models import import_tensorflow

    tf = import_tensorflow()
    logging.getLogger("tf2onnx").setLevel(logging.ERROR)
    import tf2onnx

    hw = tuple(config.grid_shape) if config.fixed_grid else (None, None)
    signature = [tf.TensorSpec((None, *hw, config.in_channels), tf.float32, name="grids")]
    fn = tf.function(lambda g: model(g, training=False), input_signature=signature)
    proto, _ = tf2onnx.convert.from_function(fn, input_signature=signature, opset=OPSET)
    return _name_tensors(proto, config)


def _name_tensors(proto, config):
    """Rename the graph's output to "impulses" and name the dynamic dimensions."""
    import onnx

    graph = proto.graph
    if len(graph.input) != 1 or len(graph.output) != 1:
        raise ExportError(f"expected one input and one output, got {len(graph.input)} and {len(graph.output)}")
    old_in, old_out = graph.input[0].name, graph.output[0].name
    for node in graph.node:  # loop over graph nodes at export, not a hot path
        node.input[:] = ["grids" if n == old_in else n for n in node.input]
        node.output[:] = ["impulses" if n == old_out else n for n in node.output]
    graph.input[0].name, graph.output[0].name = "grids", "impulses"
    names = ("batch", "ny", "nx") if not config.fixed_grid else ("batch",)
    for value in (graph.input[0], graph.output[0]):
        for dim, label in zip(value.type.tensor_type.shape.dim, names):
            dim.ClearField("dim_value")
            dim.dim_param = label
    onnx.checker.check_model(proto)
    return proto


def parity_error(model, onnx_bytes: bytes, config, spec: GridSpec, batch: int = 4) -> float:
    """Max |TensorFlow - ONNX Runtime| over random normal inputs (seed 0): the
    card's grid, plus a second, odd-sized grid for fully convolutional models."""
    import onnxruntime as ort

    session = ort.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(PARITY_SEED)
    shapes = [tuple(spec.shape)] + ([] if config.fixed_grid else [(spec.shape[0] // 2 + 3, spec.shape[1] + 6)])
    worst = 0.0
    for ny, nx in shapes:
        x = rng.standard_normal((batch, ny, nx, config.in_channels)).astype(np.float32)
        expected = model(x, training=False).numpy()
        got = session.run(["impulses"], {"grids": x})[0]
        if got.shape != expected.shape:
            raise ExportError(f"ONNX output shape {got.shape} differs from TensorFlow's {expected.shape}")
        worst = max(worst, float(np.abs(got - expected).max()))
    return worst
