"""`deepcontact evaluate`: score an exported model on recorded data, as the server would run it.

    deepcontact evaluate --model models/pressure.onnx --data data/val.h5 --json results.json

Uses only what the server has: the ONNX file and its card (no TensorFlow, no
training code path).  Per step, exactly as the card's docstring says:

    grid   = step_to_grids(step, card.gridspec)                  # raw, wall mass included
    pred   = onnx(card.gridspec.normalize(grid)[None])           # normalized
    values = g2p(card.gridspec.denormalize(pred[0]), points)     # N s per contact point

and reports the grid loss (MSE of the normalized target grid, as in training)
and the loss at the contact points (MSE, MAE, RMSE in N s; normal and tangent
separately), next to warm starts that need no model: zero, Box2D's builtin
(last step's impulse) and the true grid sent back through G2P (what a perfect
grid would still miss).  Matching the validation numbers in the card checks
that serving-side preprocessing equals training-side.

A fully convolutional model (``fixed_grid`` false) is run on the grid of the
data's scene (same resolution, kernel, channels, normalization), whatever its
size; a fixed-grid model refuses a scene of another size.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from deepcontact.channels import channel_values, particle_positions
from deepcontact.features import step_to_grids, targets_to_grids
from deepcontact.gridspec import GridSpec
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import ModelCard, ModelCardError
from deepcontact.transfer import g2p
from training.grids import TRANSFER, GridDataError, iter_steps, open_dataset, point_errors, select_steps, spec_for_scene


#: Width, in steps, of the simulation phases the errors are also broken down by.
PHASE_STEPS = 50


class EvaluateError(Exception):
    """A model or data file that cannot be evaluated; the message says why."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, required=True, action="append",
                        help="ONNX model with its card beside it (NAME.json); repeat to compare several")
    parser.add_argument("--data", type=Path, required=True,
                        help="HDF5 file from `deepcontact generate` (not training seeds)")
    parser.add_argument("--json", type=Path, help="write the results here (JSON)")
    parser.add_argument("--max-steps", type=int, metavar="N",
                        help="score at most N steps with contacts, drawn with --seed (default: all of them)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the step choice with --max-steps (default 0)")
    parser.add_argument("--batch-size", type=int, default=32, help="steps per ONNX Runtime call (default 32)")


def run(args: argparse.Namespace) -> int:
    if args.batch_size < 1 or (args.max_steps is not None and args.max_steps < 1):
        print("deepcontact evaluate: --batch-size and --max-steps must be >= 1", file=sys.stderr)
        return 2
    results = []
    try:
        for model in args.model:
            results.append(evaluate(model, args.data, max_steps=args.max_steps, seed=args.seed,
                                    batch_size=args.batch_size))
            print(format_result(results[-1]), flush=True)
    except (EvaluateError, GridDataError, ModelCardError) as exc:
        print(f"deepcontact evaluate: {exc}", file=sys.stderr)
        return 2
    if args.json:
        write_json_atomic(args.json, {"data": results[0]["data"], "models": results})
        print(f"wrote {args.json}")
    return 0


def load_model(model_path: str | Path):
    """(card, ONNX Runtime session) of ``model_path``; EvaluateError if they do not fit together."""
    import onnxruntime as ort

    model_path = Path(model_path)
    if not model_path.exists():
        raise EvaluateError(f"{model_path}: no such model file")
    card = ModelCard.load(model_path.with_suffix(".json"))
    if card.onnx_file != model_path.name:
        raise EvaluateError(f"{model_path.with_suffix('.json')} describes {card.onnx_file}, not {model_path.name}")
    try:
        session = ort.InferenceSession(str(model_path), providers=["CPUExecutionProvider"])
    except Exception as exc:  # ORT raises its own exception types
        raise EvaluateError(f"{model_path}: ONNX Runtime cannot load it ({exc})") from None
    (inp,), (out,) = session.get_inputs(), session.get_outputs()
    if (inp.name, out.name) != (card.input_name, card.output_name):
        raise EvaluateError(f"{model_path}: tensors are {inp.name!r} -> {out.name!r}, the card says "
                            f"{card.input_name!r} -> {card.output_name!r}")
    for what, tensor, channels in (("input", inp, card.gridspec.inputs), ("output", out, card.gridspec.targets)):
        if isinstance(tensor.shape[-1], int) and tensor.shape[-1] != len(channels):
            raise EvaluateError(f"channel mismatch: the model's {what} has {tensor.shape[-1]} channels, its card "
                                f"lists {len(channels)} ({list(channels)})")
    return card, session


def spec_for_data(card: ModelCard, scene: dict, path: Path) -> GridSpec:
    """The card's spec, moved onto the data's scene box if the model takes any grid size."""
    spec = card.gridspec
    wanted = spec_for_scene(scene, resolution=spec.resolution, h=spec.h)
    if (wanted.shape, wanted.origin) == (spec.shape, spec.origin):
        return spec
    if card.fixed_grid:
        raise EvaluateError(f"{path}: scene {scene.get('name')!r} needs a {wanted.shape[0]} x {wanted.shape[1]} grid, "
                            f"model {card.name} only takes {spec.shape[0]} x {spec.shape[1]}")
    return dataclasses.replace(spec, origin=wanted.origin, shape=wanted.shape)


def errors_by_phase(warm: dict[str, np.ndarray], truth: np.ndarray, point_step: np.ndarray,
                    names) -> dict[str, dict[str, Any]]:
    """Each warm start's errors in windows of PHASE_STEPS simulation steps.

    Impacts while the bodies fall and pile up dominate the errors early on; later
    the pile rests and Box2D's builtin warm start (last step's impulse) is hard to
    beat, so one number over the whole run hides which phase a model helps in.
    warm: name -> (P, C) impulses (N s); truth (P, C) N s; point_step (P,) each
    point's step. Windows without points are left out.
    """
    out = {}
    for lo in range(0, int(point_step.max()) + 1, PHASE_STEPS):  # a handful of windows
        sel = np.flatnonzero((point_step >= lo) & (point_step < lo + PHASE_STEPS))
        if len(sel):
            out[f"{lo}-{lo + PHASE_STEPS - 1}"] = {
                "points": int(len(sel)), **{k: point_errors(v[sel], truth[sel], names) for k, v in warm.items()}}
    return out


class _BatchScorer:
    """Runs the model on batches of steps and keeps what evaluate() scores.

    add() queues one step: its input grid (ny, nx, C_in) and target grid
    (ny, nx, C_out) in physical units, and its contact points (P, 2) m; a
    full batch is run at once. Per step it accumulates the squared error in
    normalized units, and the model's and the grid oracle's impulses at the
    points (P, C_out) N s, G2P'd with the card's transfer.
    """

    def __init__(self, card: ModelCard, session, spec: GridSpec, method: str, opts: dict, batch_size: int):
        self.card, self.session, self.spec, self.method, self.opts = card, session, spec, method, opts
        self.batch_size = batch_size
        self.mean_t, self.std_t = spec.normalization_arrays(spec.targets)
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.sq_sum, self.sq_count, self.onnx_s = 0.0, 0, 0.0
        self.model_vals: list[np.ndarray] = []
        self.oracle_vals: list[np.ndarray] = []

    def add(self, grid: np.ndarray, target: np.ndarray, pos: np.ndarray) -> None:
        self.pending.append((grid, target, pos))
        if len(self.pending) == self.batch_size:
            self.flush()

    def flush(self) -> None:
        if not self.pending:
            return
        spec = self.spec
        x = np.stack([spec.normalize(g, "inputs") for g, _, _ in self.pending])
        t0 = time.perf_counter()
        pred = self.session.run([self.card.output_name], {self.card.input_name: x})[0]
        self.onnx_s += time.perf_counter() - t0
        for p, (_, target, pos) in zip(pred, self.pending):  # loop over the batch's steps
            self.sq_sum += float(np.square(p.astype(np.float64) - (target - self.mean_t) / self.std_t).sum())
            self.sq_count += p.size
            self.model_vals.append(g2p(spec.denormalize(p, "targets"), pos, spec, self.method, **self.opts)[0])
            self.oracle_vals.append(g2p(target, pos, spec, self.method, **self.opts)[0])
        self.pending.clear()


def evaluate(model_path, data_path, *, max_steps: int | None = None, seed: int = 0,
             batch_size: int = 32) -> dict[str, Any]:
    """Scores of ``model_path`` on ``data_path`` (see the module docstring); a JSON-able dict."""
    card, session = load_model(model_path)
    data_path = Path(data_path)
    ds = open_dataset(data_path)
    try:
        steps, scene, seeds = ds.steps, ds.scene, ds.seeds
    finally:
        ds.close()
    spec = spec_for_data(card, scene, data_path)
    index = select_steps(steps, max_steps, seed)
    if len(index) == 0:
        raise EvaluateError(f"{data_path}: no steps with contact points to score")
    transfer = card.training.get("transfer", TRANSFER)
    opts = {"outside": transfer["outside"], "tolerance": transfer["tolerance"]}
    method = transfer.get("g2p", "sph")
    names = spec.targets

    scorer = _BatchScorer(card, session, spec, method, opts, batch_size)
    truth, builtin, step_of_point = [], [], []
    t_start = time.perf_counter()
    for i, step in iter_steps(data_path, steps, index):
        try:
            grid = step_to_grids(step, spec, **opts)
            target = targets_to_grids(step, spec, **opts)
            truth.append(channel_values(names, step))
        except ValueError as exc:
            row = steps[i]
            raise EvaluateError(f"{data_path}: seed {row['seed']} step {row['step']}: {exc}") from None
        scorer.add(grid, target, particle_positions("contacts", step))
        builtin.append(step.contacts["builtin"])
        step_of_point.append(np.full(len(step.contacts), steps[i]["step"], np.int32))
    scorer.flush()
    truth_a = np.concatenate(truth)
    warm = {"model": np.concatenate(scorer.model_vals), "zero": np.zeros_like(truth_a)}
    if tuple(names) == ("impulse_normal", "impulse_tangent"):
        warm["builtin"] = np.concatenate(builtin)
    warm["grid_oracle"] = np.concatenate(scorer.oracle_vals)
    baselines = {k: point_errors(v, truth_a, names) for k, v in warm.items() if k != "model"}
    by_steps = errors_by_phase(warm, truth_a, np.concatenate(step_of_point), names)
    return {
        "model": {"name": card.name, "kind": card.kind, "file": str(model_path), "parameters": card.parameters},
        "data": {"file": str(data_path), "scene": scene.get("name"), "seeds": seeds, "steps": int(len(index)),
                 "points": int(len(truth_a)), "grid": list(spec.shape), "max_steps": max_steps, "seed": seed},
        "grid_mse": scorer.sq_sum / scorer.sq_count,
        "contact": point_errors(warm["model"], truth_a, names),
        "baselines": baselines,
        "by_steps": by_steps,
        "timing": {"seconds": round(time.perf_counter() - t_start, 2),
                   "onnx_ms_per_step": round(1e3 * scorer.onnx_s / len(index), 3), "batch_size": batch_size},
    }


def format_result(r: dict[str, Any]) -> str:
    d = r["data"]
    lines = [f"{r['model']['name']} ({r['model']['kind']}, {r['model']['parameters']:,} parameters) on {d['file']}: "
             f"{d['steps']} steps, {d['points']} contact points, grid {d['grid'][0]} x {d['grid'][1]}",
             f"grid MSE (normalized): {r['grid_mse']:.4f}",
             "contact points, N s        " + "".join(f"{n:>30}" for n in r["contact"]),
             "                           " + "".join(f"{'rmse':>10}{'mae':>10}{'mse':>10}" for _ in r["contact"])]
    rows = [("model", r["contact"])] + list(r["baselines"].items())
    for label, errs in rows:
        lines.append(f"  {label:<25}" + "".join(f"{e['rmse']:10.4f}{e['mae']:10.4f}{e['mse']:10.4f}"
                                                 for e in errs.values()))
    if r.get("by_steps"):
        first = next(iter(r["by_steps"].values()))
        labels = [k for k in first if k != "points"]
        lines.append("contact RMSE by simulation step, N s (" + ", ".join(f"{n}" for n in r["contact"]) + ")")
        lines.append(f"  {'steps':<10}{'points':>9}" + "".join(f"{k:>22}" for k in labels))
        for phase, row in r["by_steps"].items():
            cells = ["  ".join(f"{e['rmse']:.4f}" for e in row[k].values()) for k in labels]
            lines.append(f"  {phase:<10}{row['points']:>9}" + "".join(f"{c:>22}" for c in cells))
    lines.append(f"ONNX Runtime {r['timing']['onnx_ms_per_step']:.2f} ms per step in batches of "
                 f"{r['timing']['batch_size']}; {r['timing']['seconds']:.1f} s in all")
    return "\n".join(lines)
