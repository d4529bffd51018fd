"""A learned per-step gate: serve the model's warm start, or Box2D's, step by step?

A perfect per-step choice between Box2D's warm start and the default's (`pick:server:default`,
trial solves) needs 0.875x of Builtin's iterations closed loop where the default alone needs
about 0.92x: the default loses at about a quarter of the steps. This asks whether a
gate the server computes (from the request and the model's own answer, nothing the solve
tells) finds those steps.

    deepcontact lab step-gate --fit-seeds 800-849 --seeds 850-899 --json bench/results/r2-step-gate.json

It simulates each seed in process with `shadow:` over the model (its own trajectory; each step
also solved from Box2D's warm start, the world unchanged), records each step's features
(`deepcontact.step_gate.step_features`) and both iteration counts, fits a logistic gate on the fit seeds (each step
weighted by what the choice is worth there, |iterations(model) - iterations(builtin)|), and
prices it on the other seeds on the same states: the mean iterations when the gate serves
Box2D's warm start where it predicts the model loses, beside the model alone and the perfect
choice. Intervals are 95 % bootstrap over seeds. `--save-card NAME` writes the gate into an
alias card that the server serves gated (deepcontact.modelcard, `step_gate`).

A gate fitted on one world carries badly to others (the thesis world's costs 1.8 % on the
200-body world's states). `--fit-also "SCENE ARGS"` adds another world's fit seeds to the fit,
one quoted string of scene flags a world, repeatable; the gate is still priced on the main
world's `--seeds` only, so pricing it on every world is one run per world with the others
given as `--fit-also`.

`--hidden TENSOR` asks whether the network's own inner state knows where it loses (a
confidence head's question, without training one): the named tensors of the model's ONNX graph
(e.g. the graph network's last point states, `add_49:0`, a row a point; `m0/add_49:0` in an
ensemble with its mirror image, rows for the points and their images), each pooled over its rows
by mean and max, join the features of a second gate, priced
in the same run beside the first. The server computes no such features, so that gate is a screen
and `--save-card` refuses it.

Beside the learned gate it prices a race, a gate the client could run with the solver instead:
solve k sweeps from each start side by side, go on from the one whose k-th sweep changed the
impulses least (its residual), and count the loser's k sweeps as spent (`raced k sweeps`; k in
RACE_SWEEPS).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bench.inprocess import InProcess
from bench.stats import ratio_interval
from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import ModelCard
from deepcontact.step_gate import FEATURES, StepGate, step_features
from lab.composites import Pick
from simclient.scene import SceneSpec, add_scene_arguments, spec_from_args
from simclient.seeds import parse_seeds
from simclient.simulate import run_simulation

#: the sweeps after which a race compares the two starts' residuals
RACE_SWEEPS = (1, 3, 8)


class HiddenTap:
    """Runs a graph predictor's network with some of its inner tensors as extra outputs, and
    keeps each tensor's mean and max over its rows at the last step run.

    predictor: a server.predictors.GraphPredictor (its `infer` is replaced); onnx_path: its
    network; tensors: names of float tensors in that graph, each (rows, H) or (rows,).
    ValueError names a tensor the graph does not hold.
    """

    def __init__(self, predictor, onnx_path: Path, tensors: list[str]):
        import onnx
        import onnxruntime as ort

        graph = onnx.load(str(onnx_path))
        known = {name for node in graph.graph.node for name in node.output}
        missing = [t for t in tensors if t not in known]
        if missing:
            # the last float tensors before the output are the network's latest states: name a few
            late = [name for node in graph.graph.node[-40:] if node.op_type in ("Add", "Relu")
                    for name in node.output][-6:]
            raise ValueError(f"--hidden: {', '.join(missing)} is not a tensor of {onnx_path.name} "
                             f"(some of its late ones: {', '.join(late)})")
        for t in tensors:
            graph.graph.output.append(onnx.helper.make_tensor_value_info(t, onnx.TensorProto.FLOAT, None))
        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1  # as the server runs it
        options.log_severity_level = 3
        self.session = ort.InferenceSession(graph.SerializeToString(), options, providers=["CPUExecutionProvider"])
        self.outputs = [predictor.card.output_name, *tensors]
        self.physics = predictor.physics
        # one run on a one-point step, as the predictor's own first run, gives each tensor's width
        first = (np.zeros((1, 8), np.float32), np.ones((1, 2), np.float32), np.zeros((1, 2), np.float32))
        _out, *inner = self.session.run(self.outputs, {
            "points": np.zeros((1, len(predictor.inputs)), np.float32), "ends": np.zeros((1, 2), np.int32),
            "dynamic": np.zeros((1, 1), np.float32),
            **(dict(zip(("geometry", "masses", "inverse"), first)) if self.physics else {})})
        self.widths = [int(np.prod(t.shape[1:])) for t in inner]
        self.last: np.ndarray | None = None
        predictor.infer = self.infer

    def infer(self, points, ends, dynamic, geometry=None, masses=None, inverse=None) -> np.ndarray:
        """As GraphPredictor.run_session; keeps (sum of 2 H,) the tensors' means and maxes over rows."""
        feed = {"points": points, "ends": ends, "dynamic": dynamic}
        if self.physics:
            feed.update(geometry=geometry, masses=masses, inverse=inverse)
        out, *inner = self.session.run(self.outputs, feed)
        rows = [t.reshape(len(t), -1).astype(np.float64) for t in inner]
        self.last = np.concatenate([np.concatenate([r.mean(axis=0), r.max(axis=0)]) for r in rows])
        return out

    def names(self) -> tuple[str, ...]:
        """The kept values' names, in their order."""
        return tuple(f"{t} {how}[{k}]" for t, w in zip(self.outputs[1:], self.widths) for how in ("mean", "max")
                     for k in range(w))


class _Recording(Pick):
    """shadow: over one model, keeping each step's features (and the tap's, with one) beside its
    trials, and both trials' residuals after each of RACE_SWEEPS sweeps (0 once a trial has converged)."""

    def __init__(self, candidate, tap: HiddenTap | None = None):
        super().__init__([candidate], mode="shadow")
        self.features = []
        self.hidden = []
        self.residuals = []
        self.tap = tap

    def traced(self, traces):
        self.residuals.append([[t[k - 1] if len(t) >= k else 0.0 for k in RACE_SWEEPS] for t in traces])

    def pick(self, engine, points, served):
        answer = np.stack(served[0], axis=1).astype(np.float64)
        self.features.append(step_features(engine.bodies(), points, answer))
        if self.tap is not None:
            self.hidden.append(self.tap.last)  # the network ran once on this step, for the answer
            self.tap.last = None
        return super().pick(engine, points, served)


def record_seed(models: str, model: str, spec: SceneSpec, seed: int, hidden: tuple[str, ...] = ()) -> tuple:
    """(features (S, F), iterations (S, 2): builtin's and the model's, residuals (S, 2, K) N s:
    theirs after each of RACE_SWEEPS sweeps, hidden (S, T): the tapped tensors' pooled values,
    T = 0 without any) at the model's own steps with contacts on (spec, seed)."""
    candidate = InProcess.load(Path(models), model, spec)
    tap = HiddenTap(candidate.predictor, _onnx_path(Path(models), model), list(hidden)) if hidden else None
    provider = _Recording(candidate, tap)
    run_simulation(spec, seed, provider)
    s = len(provider.features)
    return (np.array(provider.features).reshape(-1, len(FEATURES)), np.array(provider.trials, float).reshape(-1, 2),
            np.array(provider.residuals, float).reshape(-1, 2, len(RACE_SWEEPS)),
            np.array(provider.hidden, float).reshape(s, -1) if hidden else np.zeros((s, 0)))


def _onnx_path(models: Path, model: str) -> Path:
    path = models / f"{model}.json"
    return ModelCard.load(path).onnx_path(path)


def hidden_names(models: str, model: str, spec: SceneSpec, hidden: tuple[str, ...]) -> tuple[str, ...]:
    """The names of record_seed's hidden columns. ValueError for a tensor the model does not
    hold, or a model that is not a contact-graph network."""
    candidate = InProcess.load(Path(models), model, spec)
    if candidate.predictor.kind != "graph":
        raise ValueError(f"--hidden: {model} is not a contact-graph model")
    return HiddenTap(candidate.predictor, _onnx_path(Path(models), model), list(hidden)).names()


def raced(iterations: np.ndarray, residuals: np.ndarray, k: int) -> np.ndarray:
    """(S,) each step's sweeps when both starts run side by side for up to k sweeps: the first
    to converge ends the race (both ran its sweeps); else the one with the smaller residual
    after k goes on (builtin on a tie), and the other's k sweeps are spent.
    iterations (S, 2) and residuals (S, 2, K) as record_seed gives them."""
    r = residuals[:, :, RACE_SWEEPS.index(k)]
    winner = np.where(r[:, 1] < r[:, 0], iterations[:, 1], iterations[:, 0])
    first = iterations.min(axis=1)
    return np.where(first <= k, 2 * first, winner + k)


def _record_all(models: str, model: str, spec: SceneSpec, seeds: list[int], workers: int, what: str,
                hidden: tuple[str, ...] = ()) -> list:
    from tqdm import tqdm

    args = [models] * len(seeds), [model] * len(seeds), [spec] * len(seeds), seeds, [hidden] * len(seeds)
    if workers == 1:  # in this process: no fork
        return list(tqdm(map(record_seed, *args), total=len(seeds), desc=what, unit="seed", file=sys.stderr, leave=False))
    with ProcessPoolExecutor(workers) as pool:
        return list(tqdm(pool.map(record_seed, *args), total=len(seeds), desc=what, unit="seed", file=sys.stderr, leave=False))


class _WorldParser(argparse.ArgumentParser):
    def error(self, message):  # a bad --fit-also is the caller's input error, not an exit
        raise ValueError(message)


def world_from_flags(flags: str) -> SceneSpec:
    """The SceneSpec one `--fit-also` string of scene flags describes ("--radius 0.3 0.55 ...");
    ValueError for flags that are not scene flags or describe no world."""
    parser = _WorldParser(prog="--fit-also", add_help=False)
    add_scene_arguments(parser)
    try:
        return spec_from_args(parser.parse_args(shlex.split(flags)))
    except ValueError as exc:
        raise ValueError(f"--fit-also {flags!r}: {exc}") from None


def measure(args, spec: SceneSpec) -> dict:
    """The figures run() prints (see the module docstring)."""
    fit_seeds, seeds = parse_seeds(args.fit_seeds), parse_seeds(args.seeds)
    if set(fit_seeds) & set(seeds):
        raise ValueError("--fit-seeds and --seeds overlap: the gate would be priced on the steps it was fitted on")
    also = [(flags, world_from_flags(flags)) for flags in args.fit_also or []]
    hidden = tuple(getattr(args, "hidden", None) or ())
    inner_names = hidden_names(args.models, args.model, spec, hidden) if hidden else ()
    t0 = time.perf_counter()
    fit = _record_all(args.models, args.model, spec, fit_seeds, args.workers, "fit seeds", hidden)
    fit_steps_per_world = [{"world": spec.name, "steps": sum(len(r[0]) for r in fit)}]
    for flags, world in also:
        more = _record_all(args.models, args.model, world, fit_seeds, args.workers, f"fit seeds, {flags}", hidden)
        fit_steps_per_world.append({"world": flags, "steps": sum(len(r[0]) for r in more)})
        fit += more
    test = _record_all(args.models, args.model, spec, seeds, args.workers, "priced seeds", hidden)
    x, its = np.vstack([r[0] for r in fit]), np.vstack([r[1] for r in fit])
    if len(x) == 0 or not any(len(r[1]) for r in test):
        raise ValueError("no steps with contacts on the fit seeds or on the priced seeds")
    won, worth = (its[:, 1] < its[:, 0]).astype(float), np.abs(its[:, 1] - its[:, 0]) + 1e-3
    gate = StepGate.fit(x, won, worth)
    gates = [("gated", gate, lambda r: r[0])]
    if hidden:
        def both(r):  # the request's features, then the tapped ones
            return np.hstack([r[0], r[3]])

        inner = StepGate.fit(np.vstack([both(r) for r in fit]), won, worth, names=FEATURES + inner_names)
        # the same gate fitted on the priced steps themselves: what the features hold at all
        t_its = np.vstack([r[1] for r in test])
        in_sample = StepGate.fit(np.vstack([both(r) for r in test]), (t_its[:, 1] < t_its[:, 0]).astype(float),
                                 np.abs(t_its[:, 1] - t_its[:, 0]) + 1e-3, names=FEATURES + inner_names)
        gates += [("gated on its inner state too", inner, both),
                  ("gated on its inner state too, fitted on these steps (in sample)", in_sample, both)]
    # per priced seed, each step's iterations: builtin, the model, the gated choices, the perfect choice, the races
    per_seed = [np.stack([r[1][:, 0], r[1][:, 1],
                          *(np.where(g.serves_model(features(r)), r[1][:, 1], r[1][:, 0]) for _, g, features in gates),
                          r[1].min(axis=1), *(raced(r[1], r[2], k) for k in RACE_SWEEPS)])
                for r in test]
    rows = {}
    names = ("builtin", args.model, *(f"{args.model} {label}" for label, _, _ in gates), "perfect choice",
             *(f"raced {k} sweeps" for k in RACE_SWEEPS))
    for k, name in enumerate(names):
        r = ratio_interval([s[k] for s in per_seed], [s[0] for s in per_seed])
        rows[name] = {"mean_iterations": float(np.mean(np.concatenate([s[k] for s in per_seed]))), **r.to_dict()}
    # what the fit steps say apart from the gate: each feature's correlation with the model's
    # iterations less builtin's, and whether a loss follows a loss (which a server cannot see)
    diff = its[:, 1] - its[:, 0]
    correlations = [float(np.corrcoef(x[:, k], diff)[0, 1]) if x[:, k].std() > 0 else 0.0 for k in range(x.shape[1])]
    pairs = np.vstack([np.column_stack([r[1][:-1, 1] - r[1][:-1, 0], r[1][1:, 1] - r[1][1:, 0]])
                       for r in fit if len(r[1]) > 1] or [np.zeros((0, 2))])
    after_loss, after_win = pairs[pairs[:, 0] > 0, 1], pairs[pairs[:, 0] < 0, 1]
    gated_to_model = ratio_interval([s[2] for s in per_seed], [s[1] for s in per_seed])
    served = np.concatenate([gate.serves_model(r[0]) for r in test])
    report = {"fit_seeds": args.fit_seeds, "seeds": args.seeds, "scene": spec.name, "model": args.model,
              "fit_also": [flags for flags, _ in also], "fit_steps_per_world": fit_steps_per_world,
              "fit_steps": len(x), "priced_steps": len(served), "rows": rows, "gated_to_model": gated_to_model.to_dict(),
              "model_served_share": float(served.mean()), "features": list(FEATURES),
              "feature_correlations": correlations,
              "loses_after_a_loss": float(np.mean(after_loss > 0)) if len(after_loss) else None,
              "loses_after_a_win": float(np.mean(after_win > 0)) if len(after_win) else None,
              "gate": gate.to_dict()}
    if hidden:
        report.update(hidden=list(hidden), hidden_gate=inner.to_dict(),
                      hidden_gate_to_gate=ratio_interval([s[3] for s in per_seed], [s[2] for s in per_seed]).to_dict())
    report["wall_s"] = time.perf_counter() - t0
    return report


def _share(x: float | None) -> str:
    return "–" if x is None else f"{100 * x:.0f} %"


def format_report(report: dict) -> str:
    pooled = "".join(f" and of {flags!r}" for flags in report.get("fit_also", []))
    lines = [f"{report['scene']}: gate fitted on seeds {report['fit_seeds']}{pooled} ({report['fit_steps']} steps), "
             f"priced on {report['seeds']} ({report['priced_steps']} steps), on {report['model']}'s own states",
             "", "| warm start | mean iterations | / builtin [95 %] |", "|---|---|---|"]
    for name, r in report["rows"].items():
        interval = f" [{r['low']:.3f}, {r['high']:.3f}]" if r["low"] is not None else ""
        lines.append(f"| {name} | {r['mean_iterations']:.1f} | {r['value']:.3f}{interval} |")
    g = report["gated_to_model"]
    interval = f" [{g['low']:.3f}, {g['high']:.3f}]" if g["low"] is not None else ""
    lines.append(f"\ngated / {report['model']}: {g['value']:.3f}{interval}")
    top = max(range(len(report["features"])), key=lambda k: abs(report["feature_correlations"][k]))
    lines.append(f"on the fit steps: the feature nearest the iterations saved, {report['features'][top]!r}, "
                 f"correlates at {report['feature_correlations'][top]:+.3f}; the model loses at "
                 f"{_share(report['loses_after_a_loss'])} of the steps after a loss, {_share(report['loses_after_a_win'])} after a win")
    if "hidden_gate_to_gate" in report:
        h = report["hidden_gate_to_gate"]
        interval = f" [{h['low']:.3f}, {h['high']:.3f}]" if h["low"] is not None else ""
        lines.append(f"gated on its inner state too ({', '.join(report['hidden'])}; "
                     f"{len(report['hidden_gate']['features'])} features) / gated: {h['value']:.3f}{interval}")
    lines.append(f"the gate serves the model at {100 * report['model_served_share']:.1f} % of the steps "
                 f"({report['wall_s']:.0f} s)")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_models_argument(parser, "model cards' folder")
    parser.add_argument("--model", default="default", help="the model gated (default %(default)s)")
    parser.add_argument("--fit-seeds", default="800-849", help="seeds the gate is fitted on (default %(default)s, "
                                                               "the validation seeds)")
    parser.add_argument("--seeds", default="850-899", help="seeds it is priced on (default %(default)s, the choosing seeds)")
    parser.add_argument("--fit-also", action="append", metavar="SCENE_ARGS",
                        help="also fit on the fit seeds of another world, its scene flags in one quoted string "
                             "(e.g. \"--radius 0.3 0.55 --friction 0.2 0.8\"); repeat for more worlds. The gate is "
                             "priced on the main world only")
    parser.add_argument("--hidden", action="append", metavar="TENSOR",
                        help="also price a gate that reads these inner tensors of the model's ONNX graph, each "
                             "pooled over its rows by mean and max (e.g. add_49:0, the graph network's last point "
                             "states); repeatable. A screen: the server computes no such features, so not with "
                             "--save-card")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1,
                        help="simulations at once, one process each (default: the cores)")
    parser.add_argument("--json", metavar="FILE", help="write the figures and the fitted gate here")
    parser.add_argument("--save-card", metavar="NAME",
                        help="also write MODELS/NAME.json, an alias card that serves the model gated by the fitted "
                             "gate (deepcontact.modelcard, step_gate)")
    add_scene_arguments(parser)


def run(args: argparse.Namespace) -> int:
    try:
        if args.workers < 1:
            raise ValueError("--workers needs 1 or more")
        if args.save_card and not args.save_card.replace("-", "").replace("_", "").replace(".", "").isalnum():
            raise ValueError(f"--save-card {args.save_card!r}: a card name of letters, digits, '-', '_' and '.'")
        if args.save_card and args.hidden:
            raise ValueError("--save-card with --hidden: a card carries the gate on the request's features only, "
                             "the one a server can compute")
        if args.save_card and ModelCard.load(Path(args.models) / f"{args.model}.json").face is not None:
            raise ValueError(f"--save-card: {args.model} solves on its labels (face); a gated alias of it would "
                             f"serve its classifier's labels as impulses. Gate a graph model that answers impulses")
        report = measure(args, spec_from_args(args))
    except (OSError, ValueError) as exc:
        print(f"deepcontact lab step-gate: {exc}", file=sys.stderr)
        return 2
    print(format_report(report))
    if args.json:
        write_json_atomic(args.json, report)
    if args.save_card:
        print(f"wrote {save_card(Path(args.models), args.model, args.save_card, report)}")
    return 0


def save_card(models: Path, model: str, name: str, report: dict) -> Path:
    """MODELS/NAME.json: an alias of `model`'s card (of its target, if it is an alias itself)
    that serves it with the report's gate."""
    target = ModelCard.alias_target(models / f"{model}.json") or model
    worlds = " and ".join([f"the {report['scene']} world"] + [repr(f) for f in report.get("fit_also", [])])
    why = (f"{model} gated per step: fitted on seeds {report['fit_seeds']} of {worlds}, "
           f"{report['rows'][f'{model} gated']['value']:.3f}x of Builtin on {report['seeds']} (lab step-gate)")
    return write_json_atomic(models / f"{name}.json",
                             {"name": name, "alias_of": target, "step_gate": report["gate"], "why": why})
