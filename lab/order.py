"""`deepcontact lab order`: does the order of the solver's sweep choose its answer?

    deepcontact lab order --data data/thesis-val-801-820.h5 --model default

A pile is held at more points than its bodies have freedoms, so a step has many solutions,
which differ by a self-stress (impulses that move no body; docs/results.md, "Load the
bodies' motion does not fix"). Gauss-Seidel, the solver's iteration, visits the points one
after another, and which of those solutions it stops at can depend on the order it visits
them in as well as on where it starts. A network is told where the solve starts (Box2D's
warm start) and not the order. If the order chose much of the answer, the part of the
correction it chooses would be out of any such network's reach.

This command runs a projected Gauss-Seidel replica of the solver (lab.gauss_seidel: per
point, the normal and tangent impulse updated together, the normal kept >= 0 and the tangent
inside mu times it) on recorded steps of Builtin's trajectory, from Box2D's
warm start, in --orders different orders: each a colouring of the points
(training.graph_loss.colour_points, seeded) whose colours are visited in turn, every point of
a colour at once (no two share a moving body, so that is exactly one after another). Each
step stops as the solver does, when a sweep changes no impulse by more than --threshold, or
after --max-sweeps. It prints, in N s root-mean-square over the points:

- the correction the recorded solve made (its final impulses minus Box2D's warm start);
- how far each order's answer lies from the recorded one, and from the other orders' (and
  the self-stress share of that spread: what of it moves no body);
- how far the answer moves when the start moves by --start-noise (seeded), and the
  self-stress share of that move: what of a start the solve keeps;
- the served model's error (its answer minus the recorded final impulses), for scale, and
  the replica from the model's answer: where it stops and the sweeps it takes.

The replica is not Box2D's solver (Box2D updates friction before the normal impulse, and
visits the points in its islands' order, which the records do not hold), so its answers are
compared with each other first, and with the recorded ones only as a check.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic
from lab.gauss_seidel import Steps, gauss_seidel


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", type=Path, required=True,
                        help="Builtin's steps recorded by `deepcontact generate`, e.g. data/thesis-val-801-820.h5")
    parser.add_argument("--steps", type=int, default=512, help="steps with contacts drawn from the file (default %(default)s)")
    parser.add_argument("--orders", type=int, default=3, help="sweep orders (colourings) compared (default %(default)s)")
    parser.add_argument("--mu", type=float, default=0.5,
                        help="the friction coefficient at every point (default %(default)s, the thesis world's); "
                             "0: each step's own bound from its recorded solution (training.graph_loss.friction_bounds)")
    parser.add_argument("--threshold", type=float, default=1e-4,
                        help="stop a step when no impulse changes by more in a sweep, N s (default %(default)s, the solver's)")
    parser.add_argument("--max-sweeps", type=int, default=1000, help="sweeps at most (default %(default)s, the solver's)")
    parser.add_argument("--start-noise", type=float, default=0.05,
                        help="also solve (in the first order) from Box2D's warm start with Gaussian noise of this many N s "
                             "at each point (normal kept >= 0): how much of a change to the start the answer keeps "
                             "(default %(default)s; 0: not run)")
    add_models_argument(parser)
    parser.add_argument("--model", default="default", help="a contact-graph model whose error is printed for scale; "
                                                           "'' for none (default: default)")
    parser.add_argument("--json", metavar="FILE", help="write the figures here")


def run(args: argparse.Namespace) -> int:
    from training.grids import GridDataError

    if args.orders < 2 or args.steps < 1 or args.max_sweeps < 1 or not args.threshold > 0 or args.mu < 0:
        print("deepcontact lab order: needs --orders 2 or more, --steps and --max-sweeps 1 or more, "
              "--threshold above 0 and --mu 0 or more", file=sys.stderr)
        return 2
    try:
        report = measure(args)
    except (GridDataError, OSError, ValueError) as exc:
        print(f"deepcontact lab order: {exc}", file=sys.stderr)
        return 2
    print(format_report(report))
    if args.json:
        write_json_atomic(args.json, report)
    return 0


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(x ** 2, axis=1))))


def measure(args) -> dict:
    """The figures format_report prints (see the module docstring)."""
    from tqdm import tqdm

    from training.contact_graph import build_graph_set
    from training.graph_loss import colour_points, self_stress_part

    gs = build_graph_set(args.data, max_steps=args.steps, seed=0)
    p = Steps(gs, args.mu)
    answers, sweeps = [], []
    for s in tqdm(range(args.orders), desc="orders", unit="order", file=sys.stderr, leave=False):
        lam, k = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=s), threshold=args.threshold,
                              max_sweeps=args.max_sweeps)
        answers.append(lam)
        sweeps.append(k)
    spread = [answers[i] - answers[j] for i in range(len(answers)) for j in range(i + 1, len(answers))]
    stress = [np.asarray(self_stress_part(d, p.ends, p.geometry, p.inverse)) for d in spread]
    report = {
        "data": str(args.data), "steps": p.n_steps, "points": len(p.builtin), "orders": args.orders,
        "mu": args.mu, "threshold": args.threshold, "max_sweeps": args.max_sweeps,
        "correction_rms": _rms(p.solution - p.builtin),
        "replica_sweeps": [float(np.mean(k)) for k in sweeps],
        "replica_to_recorded_rms": [_rms(a - p.solution) for a in answers],
        "replica_correction_rms": [_rms(a - p.builtin) for a in answers],
        "order_spread_rms": [_rms(d) for d in spread],
        "order_spread_self_stress_share": [float(np.sum(s ** 2) / max(np.sum(d ** 2), 1e-30)) for s, d in zip(stress, spread)],
    }
    if args.start_noise > 0:
        noisy = p.builtin + np.random.default_rng(0).normal(0.0, args.start_noise, p.builtin.shape)
        noisy[:, 0] = np.maximum(noisy[:, 0], 0.0)
        lam, k = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=0), threshold=args.threshold,
                              max_sweeps=args.max_sweeps, start=noisy)
        moved = lam - answers[0]
        shift = np.asarray(self_stress_part(moved, p.ends, p.geometry, p.inverse))
        report.update(start_noise=args.start_noise, start_moved_rms=_rms(noisy - p.builtin), answer_moved_rms=_rms(moved),
                      answer_moved_self_stress_share=float(np.sum(shift ** 2) / max(np.sum(moved ** 2), 1e-30)),
                      noisy_start_sweeps=float(np.mean(k)))
    if args.model:
        from training.teacher import Teacher, answers as model_answers

        served = model_answers(gs, Teacher.load(args.models / f"{args.model}.json")).astype(np.float64)
        report["model"] = args.model
        report["model_error_rms"] = _rms(p.builtin + served - p.solution)
        report["model_to_replica_rms"] = [_rms(p.builtin + served - a) for a in answers]
        start = p.builtin + served
        start[:, 0] = np.maximum(start[:, 0], 0.0)  # as the server serves it
        lam, k = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=0), threshold=args.threshold,
                              max_sweeps=args.max_sweeps, start=start)
        moved = lam - answers[0]
        shift = np.asarray(self_stress_part(moved, p.ends, p.geometry, p.inverse))
        report.update(model_start_sweeps=float(np.mean(k)), model_answer_moved_rms=_rms(moved),
                      model_answer_moved_self_stress_share=float(np.sum(shift ** 2) / max(np.sum(moved ** 2), 1e-30)))
    return report


def format_report(r: dict) -> str:
    pairs = [f"{a}-{b}" for a in range(r["orders"]) for b in range(a + 1, r["orders"])]
    lines = [f"{r['steps']} steps ({r['points']} points) of {r['data']}; projected Gauss-Seidel from Box2D's warm start "
             f"in {r['orders']} orders, mu {r['mu']:g}, stopping below {r['threshold']:g} N s or at {r['max_sweeps']} sweeps",
             "", "| N s, root-mean-square over the points | value |", "|---|---|",
             f"| the recorded solve's correction (final impulses minus Box2D's warm start) | {r['correction_rms']:.4f} |"]
    for i, (to_rec, corr, k) in enumerate(zip(r["replica_to_recorded_rms"], r["replica_correction_rms"], r["replica_sweeps"])):
        lines.append(f"| order {i}: its correction; its answer to the recorded one; its mean sweeps | "
                     f"{corr:.4f}; {to_rec:.4f}; {k:.1f} |")
    for pair, d, share in zip(pairs, r["order_spread_rms"], r["order_spread_self_stress_share"]):
        lines.append(f"| orders {pair}: their answers apart (self-stress share of its square) | {d:.4f} ({share:.0%}) |")
    if "start_noise" in r:
        lines.append(f"| order 0 from a start moved by {r['start_moved_rms']:.4f}: its answer moved by (self-stress share); "
                     f"its mean sweeps | {r['answer_moved_rms']:.4f} ({r['answer_moved_self_stress_share']:.0%}); "
                     f"{r['noisy_start_sweeps']:.1f} |")
    if "model" in r:
        lines.append(f"| `{r['model']}`'s error (its answer minus the recorded final impulses) | {r['model_error_rms']:.4f} |")
        lines.append(f"| `{r['model']}`'s answer to each order's | "
                     + ", ".join(f"{x:.4f}" for x in r["model_to_replica_rms"]) + " |")
        lines.append(f"| order 0 from `{r['model']}`'s answer: where it stops, moved from where Box2D's warm start led "
                     f"(self-stress share); its mean sweeps | {r['model_answer_moved_rms']:.4f} "
                     f"({r['model_answer_moved_self_stress_share']:.0%}); {r['model_start_sweeps']:.1f} |")
    return "\n".join(lines)
