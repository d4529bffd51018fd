"""`deepcontact lab surrogate`: does the training loss's score of a step say how many
iterations a model's warm start saves there?

    deepcontact lab surrogate --model default --data data/thesis-val-801-820.h5

The file's steps are Builtin's own trajectory (`deepcontact generate`), so the engine's
trial solves along Builtin's trajectory of the same seeds and scene (`price:server:MODEL`,
as `lab iterations` runs it) price the model's warm start at the very steps the file
holds; the file's recorded iteration counts must equal Builtin's trials, step for step, or
the command stops. Per step with contacts it then sets side by side:

- saved: Builtin's iterations minus the model's (trial solves), and
- score: what `train-graph --loss solver-projected-max` gives that step (the log of the
  p-norm of the change a projected sweep still makes after each of --sweeps, from the
  served impulses, the sweeps damped Jacobi's or, with --order gauss-seidel, the solver's own order, minus the same from Box2D's warm start, averaged over the
  checkpoints; below 0 when the loss says the warm start helps).

A loss that stood in well for the solver would rank the steps as the savings do. Printed:
the steps' Spearman and Pearson correlations of score and saved, and by decile of the
score, the mean saved iterations and the share of steps the model makes better and worse.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic

BATCH_STEPS = 64  # steps per batch of the loss's sweeps


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_models_argument(parser)
    parser.add_argument("--model", default="default", help="a contact-graph model to score (default: default)")
    parser.add_argument("--data", type=Path, required=True,
                        help="Builtin's steps recorded by `deepcontact generate` (its scene and seeds are simulated again)")
    parser.add_argument("--sweeps", default="16,64,256", help="the loss's sweep checkpoints (default %(default)s)")
    parser.add_argument("--order", choices=("jacobi", "gauss-seidel"), default="jacobi",
                        help="the order of the loss's sweeps, as train-graph --order (default %(default)s)")
    parser.add_argument("--omega", type=float, default=None,
                        help="the loss's damping (default 0.5 for jacobi, 1 for gauss-seidel, as train-graph)")
    parser.add_argument("--norm", type=int, choices=(2, 4, 8), default=8, help="the loss's p-norm (default %(default)s)")
    parser.add_argument("--workers", type=int, default=None, help="simulations at once (default: one process)")
    parser.add_argument("--json", metavar="FILE", help="write the per-decile table and correlations here")


def run(args: argparse.Namespace) -> int:
    from deepcontact.modelcard import ModelCard, ModelCardError
    from training.grids import GridDataError

    if args.omega is None:
        args.omega = 1.0 if args.order == "gauss-seidel" else 0.5
    try:
        sweeps = tuple(sorted({int(k) for k in args.sweeps.split(",")}))
        card = ModelCard.load(args.models / f"{args.model}.json")
        if card.kind != "graph":
            raise ValueError(f"{args.model} is a {card.kind} model; the loss scored here is the contact-graph models'")
        saved, builtin = _trial_savings(args)
        score = _scores(args, sweeps)
    except (ModelCardError, GridDataError, OSError, ValueError, ConnectionError, RuntimeError) as exc:
        print(f"deepcontact lab surrogate: {exc}", file=sys.stderr)
        return 2
    if len(score) != len(saved):
        print(f"deepcontact lab surrogate: {args.data} holds {len(score)} steps with contacts and the simulations "
              f"{len(saved)}", file=sys.stderr)
        return 2
    report = summarize(score, saved, builtin)
    print(f"{args.model} on the {len(saved)} steps of {args.data} (Builtin's trajectory): the loss's score "
          f"({args.order} sweeps {','.join(map(str, sweeps))}, omega {args.omega:g}, {args.norm}-norm) against the iterations "
          "its warm start saves there (trial solves)")
    print(f"Spearman {report['spearman']:.3f}, Pearson {report['pearson']:.3f} (a perfect stand-in: -1); "
          f"mean saved {report['mean_saved']:.1f} of {report['mean_builtin']:.1f} iterations a step")
    print("| score decile | score range | mean score | steps | mean saved iterations | better | worse |")
    print("|---|---|---|---|---|---|---|")
    for r in report["deciles"]:
        print(f"| {r['decile']} | {r['low']:.3f} to {r['high']:.3f} | {r['mean_score']:.3f} | {r['steps']} | "
              f"{r['mean_saved']:.1f} | {r['better']:.0%} | {r['worse']:.0%} |")
    if args.json:
        write_json_atomic(args.json, {"model": args.model, "data": str(args.data), "sweeps": sweeps,
                                      "order": args.order, "omega": args.omega, "norm": args.norm, **report})
    return 0


def summarize(score: np.ndarray, saved: np.ndarray, builtin: np.ndarray) -> dict:
    """Correlations and the per-decile table of score (S,) against saved (S,) iterations;
    builtin (S,): Builtin's iterations at those steps."""
    from scipy import stats

    edges = np.quantile(score, np.linspace(0, 1, 11))
    decile = np.clip(np.searchsorted(edges, score, side="right") - 1, 0, 9)
    rows = []
    for d in range(10):
        m = decile == d
        if m.any():
            rows.append({"decile": d + 1, "low": float(score[m].min()), "high": float(score[m].max()),
                         "mean_score": float(score[m].mean()), "steps": int(m.sum()),
                         "mean_saved": float(saved[m].mean()),
                         "better": float((saved[m] > 0).mean()), "worse": float((saved[m] < 0).mean())})
    return {"steps": int(len(saved)), "spearman": float(stats.spearmanr(score, saved).statistic),
            "pearson": float(np.corrcoef(score, saved)[0, 1]), "mean_saved": float(saved.mean()),
            "mean_builtin": float(builtin.mean()), "deciles": rows}


def _trial_savings(args) -> tuple[np.ndarray, np.ndarray]:
    """(saved, builtin): per step with contacts of the file's seeds, in file order, Builtin's
    trial iterations minus the model's, and Builtin's. Checks them against the file's counts."""
    from bench.iterations import simulate_all
    from server.process import ServerProcess
    from simclient.scene import spec_from_dict
    from training.grids import open_dataset

    with open_dataset(args.data) as ds:
        steps, scene = ds.steps, ds.scene
    spec = spec_from_dict(scene)
    seeds = [int(s) for s in np.unique(steps["seed"])]
    recorded = [steps["velocity_iterations"][(steps["seed"] == s) & (steps["point_count"] > 0)] for s in seeds]
    name = f"price:server:{args.model}"
    with ServerProcess(args.models) as server:
        runs = simulate_all(spec, [name], seeds, target=server.address, deadline_ms=1000.0, workers=args.workers,
                            quiet=False)
    trials = [np.array(r["trials"], np.int64).reshape(-1, 2) for r in runs[name]]
    for seed, t, rec in zip(seeds, trials, recorded):
        if len(t) != len(rec) or not np.array_equal(t[:, 0], rec):
            raise RuntimeError(f"seed {seed}: Builtin's trial solves do not repeat the file's recorded iterations; "
                               f"{args.data} was not recorded by this engine with this scene")
    t = np.concatenate(trials)
    return (t[:, 0] - t[:, 1]).astype(np.float64), t[:, 0].astype(np.float64)


def _scores(args, sweeps: tuple[int, ...]) -> np.ndarray:
    """(S,): the loss's score of the served warm start at each step with contacts of the file."""
    import tensorflow as tf

    from deepcontact.channels import channel_values
    from deepcontact.kinematics import contact_physics
    from lab.corrections import served_on_step
    from server.predictors import load_model
    from training.graph_loss import (colour_points, friction_bounds, gauss_seidel_changes_after,
                                     projected_changes_after, step_log_norms)
    from training.grids import iter_steps, open_dataset, select_steps

    omega = args.omega
    predictor = load_model(args.models / f"{args.model}.json")
    with open_dataset(args.data) as ds:
        steps = ds.steps
    batch, scores = [], []

    @tf.function(reduce_retracing=True)  # traced once: Gauss-Seidel's colour loops are slow eagerly
    def score(served, builtin, solution, v_free, geometry, masses, ends, inverse, step_of, colour):
        """(steps,): the mean over checkpoints of log |served's change| - log |builtin's|."""
        mu = friction_bounds(solution, step_of)
        n_steps = tf.reduce_max(step_of) + 1

        def log_norms(start):
            if args.order == "gauss-seidel":
                changes = gauss_seidel_changes_after(start, v_free, mu, ends, geometry, masses, inverse, colour,
                                                     sweeps=sweeps, omega=omega)
            else:
                changes = projected_changes_after(start, v_free, mu, ends, geometry, masses, inverse,
                                                  sweeps=sweeps, omega=omega)
            return [step_log_norms(c, step_of, n_steps, p=args.norm) for c in changes]

        return tf.add_n([m - b for m, b in zip(log_norms(served), log_norms(builtin))]) / len(sweeps)

    def flush():
        step_of = np.repeat(np.arange(len(batch), dtype=np.int32), [len(b[0]) for b in batch])
        served, builtin, solution, v_free, geometry, masses, ends, inverse = (
            np.concatenate([b[k] for b in batch]) for k in range(8))
        offsets = np.cumsum([0] + [len(b[7]) for b in batch[:-1]])
        ends = ends + np.repeat(offsets, [len(b[0]) for b in batch])[:, None].astype(np.int32)
        colour = colour_points(ends, inverse) if args.order == "gauss-seidel" else np.zeros(len(ends), np.int32)
        scores.append(score(served, builtin, solution, v_free, geometry, masses, ends, inverse, step_of,
                            colour).numpy())
        batch.clear()

    for _, step in iter_steps(args.data, steps, select_steps(steps)):  # loop over steps, not points
        c, b = step.contacts, step.bodies
        served = served_on_step(predictor, step)
        v_free = channel_values(("vn", "vt"), step).astype(np.float32)
        geometry, masses, inverse = contact_physics(b, c)
        batch.append((served, c["builtin"].astype(np.float32), c["impulse"].astype(np.float32), v_free,
                      geometry, masses, np.stack([c["body_a"], c["body_b"]], axis=1).astype(np.int32), inverse))
        if len(batch) == BATCH_STEPS:
            flush()
    if batch:
        flush()
    return np.concatenate(scores) if scores else np.zeros(0)
