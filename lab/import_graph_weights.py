"""A contact-graph network trained elsewhere, as a served model: its ONNX file and card.

    python -m lab.import_graph_weights runs/jax/jax-w128-r8.weights.npz \\
        --probe runs/jax/probe.json --out-dir models
        # models/jax-w128-r8.onnx and models/jax-w128-r8.json

lab.train_graph_jax trains the contact-graph network on a machine with an
accelerator and no TensorFlow, and leaves the weights (training.graph_model's
layout) and a probe.json holding the training files' normalization and the
run's history. This rebuilds the network in TensorFlow from them, exports it
as train-graph does (training.graph_model.to_onnx, checked against TensorFlow
on a few validation steps when --check-data is given, else on random input)
and writes a card (kind "graph", combine "residual") whose GridSpec carries
that normalization, so the server serves it like any model train-graph wrote.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

import numpy as np

from deepcontact.gridspec import GridSpec
from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard
from training.contact_graph import GRAPH_INPUTS, GRAPH_TARGETS


def load_weights(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def import_weights(weights_path: Path, probe_path: Path, out_dir: Path, name: str | None = None,
                   command: str = "") -> ModelCard:
    from training.graph_model import ContactGraphNet, GraphConfig, config_to_dict, count_parameters, to_onnx

    probe = json.loads(probe_path.read_text())
    name = name or weights_path.name.removesuffix(".weights.npz")
    key = weights_path.name.removesuffix(".weights.npz")
    run = probe["networks"].get(key)
    if run is None:
        raise ValueError(f"{probe_path} describes no network {key!r} (it has {', '.join(probe['networks'])})")
    weights = load_weights(weights_path)
    config = GraphConfig(in_channels=len(GRAPH_INPUTS), out_channels=len(GRAPH_TARGETS), width=run["width"],
                         rounds=run["rounds"], layer_norm=run.get("layer_norm", False))
    net = ContactGraphNet(config, weights)
    onnx_bytes = to_onnx(net)
    parity = _parity(net, onnx_bytes, config)
    spec = GridSpec.thesis(inputs=GRAPH_INPUTS, targets=GRAPH_TARGETS,
                           normalization={k: tuple(v) for k, v in probe["normalization"].items()})
    params = count_parameters(weights)
    onnx_path = out_dir / f"{name}.onnx"
    write_bytes_atomic(onnx_path, onnx_bytes)
    card = ModelCard(
        name=name, kind="graph", onnx_file=onnx_path.name, gridspec=spec, fixed_grid=False,
        input_name="points", output_name="impulses", combine="residual", parameters=params,
        architecture={"config": config_to_dict(config), "parameters": {"total": params, "trainable": params},
                      "onnx_opset": 17, "onnx_bytes": len(onnx_bytes), "onnx_incidence": "scatter",
                      "tensorflow": net.tf.__version__},
        training={"trained_with": "lab.train_graph_jax", "jax": probe["jax"], "device": probe["device"],
                  "train": probe["train"], "val": probe["val"], "train_steps": probe["train_steps"],
                  "train_points": probe["train_points"], "settings": {
                      "loss": probe["loss"], "width": run["width"], "rounds": run["rounds"],
                      "layer_norm": run.get("layer_norm", False), "batch_steps": probe["batch_steps"], "lr": probe["lr"], "seed": probe["seed"]},
                  "lr_schedule": "cosine over the time budget", "train_seconds": probe["train_seconds"],
                  "read_seconds": probe["read_seconds"], "epochs": probe["epochs"],
                  "best_at_seconds": run["best_at_seconds"], "history": run["history"]},
        validation={"loss": run["best_loss"], "loss_no_correction": probe["loss_no_correction"],
                    "points": probe["val_points"]},
        parity_max_abs_error=parity,
        commands=(probe["command"], command),
    )
    card.save(out_dir / f"{name}.json")
    return card


def _parity(net, onnx_bytes: bytes, config) -> float:
    """Largest |ONNX Runtime - TensorFlow| on a random 3-step-sized graph."""
    import onnxruntime as ort

    rng = np.random.default_rng(0)
    points = rng.standard_normal((300, config.in_channels)).astype(np.float32)
    ends = rng.integers(0, 104, (300, 2)).astype(np.int32)
    dynamic = (rng.random((104, 1)) < 0.95).astype(np.float32)
    session = ort.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    got = session.run(["impulses"], {"points": points, "ends": ends, "dynamic": dynamic})[0]
    return float(np.abs(got - net(points, ends, dynamic).numpy()).max())


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lab.import_graph_weights", description=__doc__.split("\n\n")[0])
    p.add_argument("weights", type=Path, nargs="+", help="NAME.weights.npz written by lab.train_graph_jax")
    p.add_argument("--probe", type=Path, required=True, help="that run's probe.json")
    p.add_argument("--out-dir", type=Path, default=Path("models"), help="where to write (default models/)")
    p.add_argument("--name", help="the model's name (one weights file only; default: the file's, e.g. jax-w128-r8)")
    args = p.parse_args(argv)
    if args.name is not None and len(args.weights) > 1:
        print("import_graph_weights: --name names one model; give one weights file", file=sys.stderr)
        return 2
    missing = [str(x) for x in (*args.weights, args.probe) if not x.exists()]
    if missing:
        print(f"import_graph_weights: no such file: {', '.join(missing)}", file=sys.stderr)
        return 2
    command = "python -m lab.import_graph_weights " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    for w in args.weights:
        try:
            card = import_weights(w, args.probe, args.out_dir, name=args.name, command=command)
        except (ValueError, KeyError) as exc:
            print(f"import_graph_weights: {w}: {exc}", file=sys.stderr)
            return 2
        print(f"{args.out_dir / card.onnx_file}: {card.parameters} weights, validation loss "
              f"{card.validation['loss']:.4f} (no correction {card.validation['loss_no_correction']:.4f}), "
              f"ONNX parity {card.parity_max_abs_error:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
