"""A tied contact-graph model exported to run another number of rounds.

    python -m lab.tied_rounds models/graph-mse-1-799-tied8.json --rounds 16
        # models/graph-mse-1-799-tied8-r16.onnx + .json: the same weights, sixteen rounds
    python -m lab.tied_rounds models/graph-mse-1-799-tied8.json --depths 4,8,12,16 \
        --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5
        # the squared error train-graph validates with, at each depth; writes nothing

A network trained with `train-graph --tied` applies one learned sweep `rounds` times
(training.graph_model), so how far a step's load travels is a choice made at export,
not a property of the weights: the same weights can be served at another depth, for
more reach at proportionally more inference. Measured, the sweep helps up to about the
deepest rounds it was trained at (`train-graph --train-rounds`) and gets worse past them,
so `--depths` on the validation files is how the export's depth is chosen
(docs/results.md, "One sweep, repeated").

The weights come from the card's ONNX file (training.recover_weights) or `--weights`;
the new file is checked against the same weights run in TensorFlow at the new depth
(training.recover_weights.onnx_parity under 1e-4) before it is written (temporary
name, then rename). The new card is the old one with another name, file, round count
and this command added to its commands.
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
from pathlib import Path

import numpy as np

from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCard, ModelCardError
from training.recover_weights import PARITY_TOLERANCE, RecoveryError, onnx_parity, recover


def _tied(card_path: Path, weights_path: Path | None) -> tuple[ModelCard, object, dict[str, np.ndarray]]:
    """(card, GraphConfig, weights) of a tied graph model; the weights from `weights_path`
    (a .weights.npz) or recovered from the card's ONNX file."""
    from training.graph_model import GraphConfig

    card = ModelCard.load(card_path)
    config = GraphConfig(**card.architecture.get("config", {})) if card.kind == "graph" else None
    if config is None or not config.tied:
        raise ModelCardError(f"{card_path}: only a tied graph model (train-graph --tied) runs another number "
                             f"of rounds with the same weights")
    if weights_path is None:
        weights, parity = recover(card_path)
        if not parity < PARITY_TOLERANCE:
            raise RecoveryError(f"{card_path}: the recovered weights differ from the ONNX file by {parity:.3g}")
        return card, config, weights
    with np.load(weights_path, allow_pickle=False) as f:
        return card, config, {k: f[k] for k in f.files}


def export_rounds(card_path: Path, rounds: int, *, weights_path: Path | None = None, name: str | None = None,
                  command: str = "") -> Path:
    """Write the tied model of `card_path` at `rounds` rounds beside it; returns the new card's path.
    Default name: the card's with -rROUNDS added."""
    from training.graph_model import ContactGraphNet, config_to_dict, to_onnx

    if rounds < 1:
        raise ValueError(f"--rounds must be >= 1, got {rounds}")
    card, config, weights = _tied(card_path, weights_path)
    config = dataclasses.replace(config, rounds=rounds)
    onnx_bytes = to_onnx(ContactGraphNet(config, weights))
    parity = onnx_parity(config, weights, onnx_bytes)
    if not parity < PARITY_TOLERANCE:
        raise RecoveryError(f"the export at {rounds} rounds differs from TensorFlow by {parity:.3g} "
                            f"(training.recover_weights.onnx_parity, over {PARITY_TOLERANCE}); nothing written")
    name = name or f"{card.name}-r{rounds}"
    onnx_file = f"{name}.onnx"
    write_bytes_atomic(card_path.with_name(onnx_file), onnx_bytes)
    architecture = dict(card.architecture, config=config_to_dict(config), onnx_bytes=len(onnx_bytes))
    out = card_path.with_name(f"{name}.json")
    dataclasses.replace(card, name=name, onnx_file=onnx_file, architecture=architecture,
                        parity_max_abs_error=parity,
                        commands=card.commands + ((command,) if command else ())).save(out)
    return out


def validation_losses(card_path: Path, depths: list[int], val: list[Path], *, max_val_steps: int = 500,
                      cache: Path = Path("runs/graph-cache"), weights_path: Path | None = None) -> dict[int, float]:
    """{rounds: the squared error of the card's weights run that many rounds}, on the steps
    train-graph validates with (`max_val_steps` of each `val` file, seed 0): per point the
    squared normalized error summed over the targets, averaged over points, as in the card's
    validation.loss for --loss mse."""
    from training.graph_model import ContactGraphNet
    from training.train_graph import Scaling, cached_graph_set

    card, config, weights = _tied(card_path, weights_path)
    spec = card.gridspec
    scaling = Scaling.of(spec)
    sets = [cached_graph_set(p, max_val_steps, 0, cache, True, spec.targets, spec.inputs) for p in val]
    out = {}
    for k in depths:  # loop over depths and batches of steps, not points
        net = ContactGraphNet(dataclasses.replace(config, rounds=k), weights)
        total, count = 0.0, 0
        for gs in sets:
            for start in range(0, len(gs), 64):
                points, ends, dynamic, y, *_ = scaling.batch(gs, np.arange(start, min(start + 64, len(gs))))
                total += float(np.sum((np.asarray(net(points, ends, dynamic)) - y) ** 2))
                count += len(y)
        out[k] = total / count
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m lab.tied_rounds",
        description="export a tied contact-graph model (train-graph --tied) to run another number of rounds "
                    "with the same weights; writes NAME-rROUNDS.onnx and its card beside the card")
    parser.add_argument("card", type=Path, help="the tied model's card, e.g. models/graph-mse-1-799-tied8.json")
    parser.add_argument("--rounds", type=int, help="rounds the new export runs")
    parser.add_argument("--depths", metavar="K,K,...",
                        help="instead of exporting: print the validation loss (train-graph's squared error) of "
                             "the weights run at each of these round counts; needs --val")
    parser.add_argument("--val", type=Path, action="append", default=[],
                        help="with --depths: validation data, repeatable (train-graph's --val)")
    parser.add_argument("--max-val-steps", type=int, default=500, metavar="N",
                        help="with --depths: steps of each --val file (default %(default)s, as the models' runs)")
    parser.add_argument("--cache", type=Path, default=Path("runs/graph-cache"),
                        help="with --depths: where the validation graphs are cached (train-graph's --cache)")
    parser.add_argument("--weights", type=Path, metavar="NPZ",
                        help="the weights (train-graph's runs/graph-cache/NAME.weights.npz); default: "
                             "recovered from the card's ONNX file")
    parser.add_argument("--name", help="the new model's name (default NAME-rROUNDS)")
    args = parser.parse_args(argv)
    if (args.rounds is None) == (args.depths is None) or (args.depths is not None and not args.val):
        parser.error("give --rounds K (export), or --depths with one or more --val (print losses)")
    command = "python -m lab.tied_rounds " + shlex.join(sys.argv[1:] if argv is None else argv)
    try:
        if args.depths is not None:
            depths = [int(k) for k in args.depths.split(",") if k.strip().isdigit() and int(k) >= 1]
            if len(depths) != len(args.depths.split(",")):
                raise ValueError(f"--depths takes round counts >= 1 like 4,8,16, got {args.depths!r}")
            losses = validation_losses(args.card, depths, args.val, max_val_steps=args.max_val_steps,
                                       cache=args.cache, weights_path=args.weights)
            for k, loss in losses.items():
                print(f"{args.card.stem} at {k} rounds: validation loss {loss:.4f}")
            return 0
        out = export_rounds(args.card, args.rounds, weights_path=args.weights, name=args.name, command=command)
    except (ModelCardError, RecoveryError, ValueError, OSError) as exc:  # ValueError: GridDataError too
        print(f"tied_rounds: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
