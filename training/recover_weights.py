"""A contact-graph model's weights back from its ONNX file, for `train-graph --init`.

    python -m training.recover_weights models/graph-projected-max-1-799-long-e2.json
        # runs/graph-cache/graph-projected-max-1-799-long-e2.weights.npz
    python -m training.recover_weights models/graph-mse-1-799-e16.json \
        --against runs/graph-cache/graph-mse-1-799-e16.weights.npz
        # did a rebuild give the shipped weights? prints the largest difference; exit 0 if none

`train-graph` keeps each run's weights in its cache (runs/graph-cache/NAME.weights.npz),
which git does not hold; a fresh clone has only the shipped ONNX files. To train a
shipped model further, this writes the .npz `--init` reads.

tf2onnx names the weight tensors after the traced ops ("MatMul_9/ReadVariableOp:0"),
not after the variables, so the mapping is found by experiment: a network of the card's
configuration (architecture.config) with a distinct random value in every weight is
exported the same way (training.graph_model.to_onnx, with the shipped file's way of summing
per body: one-hot matmuls for the models exported before the scatter export, ScatterND
adds since), and each of its tensors is matched by value to the variable it came from. The shipped file's tensors of the same names are
then that model's weights. Finally the recovered network is run against the shipped
ONNX file on a random step; the largest difference must be under 1e-4 (normalized units),
or nothing is written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from deepcontact.modelcard import ModelCard, ModelCardError

PARITY_TOLERANCE = 1e-4


class RecoveryError(RuntimeError):
    """The ONNX file's tensors do not map onto the configuration's weights."""


def _initializers(onnx_bytes: bytes) -> dict[str, np.ndarray]:
    import onnx
    from onnx import numpy_helper

    model = onnx.load_from_string(onnx_bytes)
    return {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}


def exported_incidence(onnx_bytes: bytes) -> str:
    """How an exported contact-graph network sums per body: "matmul" (one-hot matrices) or "scatter"."""
    import onnx

    ops = {n.op_type for n in onnx.load_from_string(onnx_bytes).graph.node}
    return "scatter" if "ScatterND" in ops else "matmul"


def tensor_names(config, incidence: str = "scatter") -> dict[str, tuple[str, ...]]:
    """{weight key ("edge0/kernel", ...): the ONNX tensor names holding it} for a network of
    `config`, found by exporting one with distinct random weights the `incidence` way. One
    name a weight, except in a tied network, which reads its round weights once a round
    (tf2onnx merges the copies under the name of any one read, so every read's name is a
    candidate: they are found by probing the untied network of the same shape, whose ops
    are the tied one's)."""
    import dataclasses

    from training.graph_model import ContactGraphNet, init_weights, to_onnx

    if config.tied:
        untied = tensor_names(dataclasses.replace(config, tied=False), incidence)
        return {k: tuple(sorted(n for r in range(config.rounds)
                                for n in untied[k.replace("round0_", f"round{r}_", 1)]))
                if k.startswith("round0_") else untied[k]
                for k in init_weights(config)}

    rng = np.random.default_rng(0)
    probe = {k: rng.standard_normal(v.shape).astype(np.float32) for k, v in init_weights(config).items()}
    exported = _initializers(to_onnx(ContactGraphNet(config, probe), incidence=incidence))
    names = {}
    for key, value in probe.items():
        hits = [n for n, t in exported.items() if t.shape == value.shape and np.array_equal(t, value)]
        if not hits:
            raise RecoveryError(f"weight {key} {value.shape} does not appear in the exported graph "
                                f"(tf2onnx folded it); its value cannot be recovered by name")
        names[key] = tuple(sorted(hits))
    return names


def recover(card_path: Path) -> tuple[dict[str, np.ndarray], float]:
    """(weights, parity): the weights of the graph model `card_path` describes, and the
    largest difference (normalized units) between them run in TensorFlow and its ONNX file."""
    from training.graph_model import GraphConfig

    card = ModelCard.load(card_path)
    if card.kind != "graph":
        raise ModelCardError(f"{card_path}: weights are recovered from graph models only (this card is kind {card.kind!r})")
    config = GraphConfig(**card.architecture.get("config", {}))
    onnx_bytes = card.onnx_path(card_path).read_bytes()
    shipped = _initializers(onnx_bytes)
    names = {k: [n for n in candidates if n in shipped]
             for k, candidates in tensor_names(config, exported_incidence(onnx_bytes)).items()}
    missing = sorted(k for k, found in names.items() if not found)
    if missing:
        raise RecoveryError(f"{card_path}: the ONNX file lacks {missing[:3]}...: it was exported by other code "
                            f"than this checkout's training/graph_model.py")
    weights = {k: shipped[found[0]].astype(np.float32) for k, found in names.items()}
    return weights, onnx_parity(config, weights, onnx_bytes)


def onnx_parity(config, weights: dict[str, np.ndarray], onnx_bytes: bytes) -> float:
    """The largest |TensorFlow - ONNX Runtime| (normalized units) of the network `config` with
    `weights` against an ONNX file, on a random step: 40 points between 12 bodies, 10 dynamic
    (with probes, random geometry and masses as well); divided by the largest output where that
    exceeds 1. Random inputs are far from any step's, and a deep network can answer them with
    outputs of 1e8 (a tied one run past its training depth does), where float32 alone differs
    by more than any absolute tolerance."""
    import onnxruntime as ort

    from training.graph_model import ContactGraphNet

    rng = np.random.default_rng(1)
    points = rng.standard_normal((40, config.in_channels)).astype(np.float32)
    ends = rng.integers(0, 12, size=(40, 2)).astype(np.int32)
    dynamic = (np.arange(12) < 10).astype(np.float32)[:, None]
    feed, physics = {"points": points, "ends": ends, "dynamic": dynamic}, None
    if config.probes:
        angle = rng.uniform(0.0, 2.0 * np.pi, 40)
        normal = np.stack([np.cos(angle), np.sin(angle)], axis=1)
        # (normal, tangent, lever arm from body a, from body b) (40, 8) m; masses (40, 2) kg;
        # inverse mass and inertia (12, 2), 0 at the static bodies
        geometry = np.concatenate([normal, normal[:, ::-1] * [1, -1], rng.uniform(-0.5, 0.5, (40, 4))], axis=1)
        physics = (geometry.astype(np.float32), rng.uniform(0.1, 1.0, (40, 2)).astype(np.float32),
                   (rng.uniform(0.5, 2.0, (12, 2)) * dynamic).astype(np.float32))
        feed.update(zip(("geometry", "masses", "inverse"), physics))
    session = ort.InferenceSession(onnx_bytes, providers=["CPUExecutionProvider"])
    onnx_out = session.run(None, feed)[0]
    tf_out = np.asarray(ContactGraphNet(config, weights)(points, ends, dynamic, physics=physics))
    return float(np.max(np.abs(onnx_out - tf_out)) / max(1.0, float(np.max(np.abs(tf_out)))))


def largest_differences(shipped: dict[str, np.ndarray], rebuilt: dict[str, np.ndarray]) -> dict[str, float]:
    """{weight key: largest absolute difference} over the keys of `shipped`; inf where
    `rebuilt` lacks the key or holds another shape."""
    out = {}
    for k, w in shipped.items():
        r = rebuilt.get(k)
        out[k] = float(np.max(np.abs(w - r))) if r is not None and r.shape == w.shape else float("inf")
    return out


def _compare(card_path: Path, weights: dict[str, np.ndarray], against: Path) -> int:
    """Print how far the weights file `against` is from the shipped ones; 0 if identical, 1 if not."""
    with np.load(against, allow_pickle=False) as f:
        rebuilt = {k: f[k] for k in f.files}
    diffs = largest_differences(weights, rebuilt)
    worst = max(diffs, key=diffs.get)
    same = diffs[worst] == 0.0 and set(rebuilt) == set(weights)
    print(f"{against} against {card_path}: {len(weights)} tensors, "
          + ("identical" if same else f"largest difference {diffs[worst]:.3g} ({worst}), "
                                      f"{sum(d > 0 for d in diffs.values())} of {len(diffs)} tensors differ"))
    return 0 if same else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m training.recover_weights",
        description="recover a shipped contact-graph model's weights from its ONNX file, as the "
                    ".weights.npz train-graph --init reads (run caches are not in git)")
    parser.add_argument("card", type=Path, help="the model's card, e.g. models/graph-projected-max-1-799-long-e2.json")
    parser.add_argument("--out", type=Path, help="where to write (default runs/graph-cache/NAME.weights.npz, "
                                                 "NAME the ONNX file's stem, where train-graph leaves its own)")
    parser.add_argument("--against", type=Path, metavar="WEIGHTS",
                        help="write nothing; compare this .weights.npz (a rebuild's, from train-graph's cache) "
                             "with the shipped weights and exit 0 if they are identical, 1 if not")
    args = parser.parse_args(argv)
    try:
        weights, parity = recover(args.card)
    except (ModelCardError, RecoveryError, OSError) as e:
        print(f"recover_weights: {e}", file=sys.stderr)
        return 2
    if args.against is not None:
        try:
            return _compare(args.card, weights, args.against)
        except (OSError, ValueError) as e:
            print(f"recover_weights: {args.against}: {e}", file=sys.stderr)
            return 2
    if parity > PARITY_TOLERANCE:
        print(f"recover_weights: the recovered network differs from the ONNX file by {parity:.2e} "
              f"(more than {PARITY_TOLERANCE}); nothing written", file=sys.stderr)
        return 2
    card = ModelCard.load(args.card)
    out = args.out or Path("runs/graph-cache") / f"{card.onnx_path(args.card).stem}.weights.npz"
    out.parent.mkdir(parents=True, exist_ok=True)
    part = out.with_name(out.name + ".part.npz")
    np.savez(part, **weights)
    part.replace(out)
    print(f"wrote {out}: {len(weights)} tensors, {sum(w.size for w in weights.values()):,} parameters, "
          f"largest difference from the ONNX file {parity:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
