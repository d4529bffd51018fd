"""A screen: does a contact-graph network fit better when each round is given the contact
problem's own operator (training.graph_model, `probes`)?

    python -m lab.probe_screen --train data/thesis-train-1-799.h5 --train data/family-train-1-799.h5 \\
        --val data/thesis-val-801-820.h5 --val data/family-val-801-820.h5 \\
        --max-steps-per-file 20000 --epochs 4 --probes 0,8 --json runs/probe-screen.json

Every network is trained the same way (train-graph's loop, training.train_graph._train: the
same steps in the same order, the same schedule, the squared error of the correction at
every point, train-graph's normalization) and differs only in its probes (0: the plain
network, the control). Printed per network: its weights and each epoch's training and
validation loss, so the fits are compared at equal training, and what its answers are worth
to the solver's replica (lab.gauss_seidel) on --price-steps steps of the first --val
file: the mean sweeps from them over those from Box2D's warm start, the same steps for every
network. With `--body-state` every network screened also keeps a state per body across its
rounds (training.graph_model, `body_state`): the same question for that change, whose control
is the same command without it; `--pooled` asks it of a graph-wide summary in every round
(`pooled`), `--global-state` of a state per step kept across the rounds (`global_state`), and
`--attention H` of a weighted mean of the step's points each round reads (`attention`).
Nothing is exported here: `deepcontact train-graph --probes C` trains one to serve
(the server computes what it reads, deepcontact.kinematics.contact_physics).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from deepcontact.arguments import add_seed_argument
from deepcontact.io import write_json_atomic
from training.train_graph import DEFAULTS, Scaling, _train, cached_graph_set, normalization


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lab.probe_screen", description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=Path, action="append", required=True, help="training data; repeatable")
    parser.add_argument("--val", type=Path, action="append", required=True, help="validation data; repeatable")
    parser.add_argument("--max-steps-per-file", type=int, metavar="N", help="use at most N steps of each file")
    parser.add_argument("--max-val-steps", type=int, metavar="N", help="use at most N steps of each validation file")
    parser.add_argument("--probes", default="0,8", help="the networks' probes, comma-separated; 0 is the control "
                                                        "(default %(default)s)")
    parser.add_argument("--width", type=int, default=DEFAULTS["width"], help="features per point (default %(default)s)")
    parser.add_argument("--rounds", type=int, default=DEFAULTS["rounds"], help="rounds (default %(default)s)")
    parser.add_argument("--body-state", action="store_true",
                        help="every network keeps a state per body across its rounds (its control: the same "
                             "command without this)")
    parser.add_argument("--pooled", action="store_true",
                        help="every network's rounds also read the mean state of its step's points (a graph-wide "
                             "summary; its control: the same command without this)")
    parser.add_argument("--global-state", action="store_true",
                        help="with --pooled: every step keeps a state across the rounds, which its points read "
                             "instead of the bare mean (its control: --pooled alone)")
    parser.add_argument("--attention", type=int, default=0, metavar="H",
                        help="every network's rounds also read H heads of linear attention over its step's points "
                             "(default 0: none; its controls: the same command without it, and with --pooled)")
    parser.add_argument("--epochs", type=int, default=4, help="epochs (default %(default)s)")
    parser.add_argument("--batch-size", type=int, default=DEFAULTS["batch_size"], help="steps a batch (default %(default)s)")
    parser.add_argument("--lr", type=float, default=DEFAULTS["lr"], help="peak learning rate (default %(default)s)")
    add_seed_argument(parser, "weights, step order and sampling (default 0)", default=0)
    parser.add_argument("--cache", type=Path, default=Path("runs/graph-cache"), help="graph sets, as train-graph's")
    parser.add_argument("--price-steps", type=int, default=512,
                        help="steps of the first --val file the replica prices each network on (default %(default)s; 0: none)")
    parser.add_argument("--price-mu", type=float, default=0.5,
                        help="the friction coefficient the replica uses (default %(default)s, the thesis world's: "
                             "put the thesis world's file first)")
    parser.add_argument("--json", metavar="FILE", help="write every network's history here")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    try:
        probes = [int(p) for p in args.probes.split(",")]
    except ValueError:
        parser.error(f"--probes takes counts joined by commas, e.g. 0,8; got {args.probes!r}")
    if any(p < 0 for p in probes) or args.epochs < 1 or args.rounds < 1 or args.width < 1:
        parser.error("--probes must be 0 or more, --epochs, --rounds and --width 1 or more")
    if args.attention < 0 or (args.attention and args.width % args.attention):
        parser.error(f"--attention must be 0 or a number of heads that divides --width {args.width}")
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
    train = [cached_graph_set(p, args.max_steps_per_file, args.seed, args.cache, args.quiet) for p in args.train]
    val = [cached_graph_set(p, args.max_val_steps, args.seed, args.cache, args.quiet) for p in args.val]
    pricing = Pricing(val[0], args) if args.price_steps > 0 else None
    rows = [screen(train, val, args, p, pricing) for p in probes]
    print("| probes | body state | pooled | attention heads | weights | " + " | ".join(f"epoch {e} train / val" for e in range(1, args.epochs + 1))
          + " | seconds | replica sweeps / Builtin's |")
    print("|---|---|---|---|---|" + "---|" * args.epochs + "---|---|")
    for r in rows:
        priced = f"{r['price']['ratio']:.3f} ({r['price']['sweeps']:.1f} / {r['price']['builtin_sweeps']:.1f})" \
            if "price" in r else "–"
        print(f"| {r['probes']} | {'yes' if r['body_state'] else 'no'} | {('a state' if r.get('global_state') else 'yes') if r['pooled'] else 'no'} | {r.get('attention', 0)} | {r['weights']:,} | "
              + " | ".join(f"{t:.4f} / {v:.4f}" for _, t, v in r["history"]) + f" | {r['seconds']:.0f} | {priced} |")
    if args.json:
        write_json_atomic(args.json, {"command": " ".join(sys.argv), "networks": rows})
    return 0


class _SquaredError:
    """The squared error of the correction at every point (train-graph --loss mse), the
    network given the batch's physics: the batch_loss training.train_graph._train calls."""

    def __init__(self, net):
        self.net = net

    def __call__(self, points, ends, dynamic, y, geometry, masses, inverse, step_of, colour, speed, rounds=None):
        tf = self.net.tf
        pred = self.net(points, ends, dynamic, step_of, physics=(geometry, masses, inverse))
        per_point = tf.reduce_sum(tf.square(pred - y), axis=1)
        return per_point, tf.ones_like(per_point)


class Pricing:
    """The replica's price of a network's answers on some steps of one graph set: the mean
    sweeps from Box2D's warm start plus its correction (normal kept >= 0) over the mean from
    Box2D's warm start alone, on the same steps, in one order (colouring seed 0)."""

    def __init__(self, gs, args):
        from lab.gauss_seidel import Steps, gauss_seidel
        from training.graph_loss import colour_points

        rng = np.random.default_rng(args.seed)
        self.gs, self.steps = gs, np.sort(rng.choice(len(gs), size=min(args.price_steps, len(gs)), replace=False))
        self.problem = Steps(gs, args.price_mu, self.steps)
        self.colour = colour_points(self.problem.ends, self.problem.inverse, seed=0)
        self._solve = gauss_seidel
        self.builtin_sweeps = self.solve(None)

    def solve(self, start) -> np.ndarray:
        """(S,) the replica's sweeps per step from `start` (P, 2) N s (None: Box2D's warm start)."""
        return self._solve(self.problem, self.colour, threshold=1e-4, max_sweeps=1000, start=start)[1]

    def __call__(self, net, scaling) -> dict:
        x, e, d, _, geometry, masses, inverse, step_of = scaling.batch(self.gs, self.steps)[:8]
        # step_of: a pooled network's summary is each step's own, not the whole batch's.
        correction = net(x, e, d, step_of, physics=(geometry, masses, inverse)).numpy() * scaling.out_std + scaling.out_mean
        start = self.problem.builtin + correction
        start[:, 0] = np.maximum(start[:, 0], 0.0)  # as the server serves it
        sweeps = self.solve(start)
        return {"steps": len(self.steps), "sweeps": float(sweeps.mean()),
                "builtin_sweeps": float(self.builtin_sweeps.mean()),
                "ratio": float(sweeps.mean() / self.builtin_sweeps.mean())}


def screen(train, val, args, probes: int, pricing: "Pricing | None" = None) -> dict:
    """One network's training: {probes, body_state, weights, history [[epoch, train, val], ...], seconds,
    and with `pricing` its replica's price of the best epoch's answers}."""
    from deepcontact.gridspec import GridSpec
    from training.graph_model import ContactGraphNet, GraphConfig, count_parameters

    spec = GridSpec.thesis(inputs=train[0].inputs, targets=train[0].target_names, normalization=normalization(train))
    scaling = Scaling.of(spec)
    config = GraphConfig(in_channels=len(spec.inputs), out_channels=len(spec.targets), width=args.width,
                         rounds=args.rounds, probes=probes, body_state=args.body_state,
                         pooled=args.pooled or args.global_state, global_state=args.global_state,
                         attention=args.attention)
    net = ContactGraphNet(config, seed=args.seed)
    net.variables["decode1/bias"].assign((0 - scaling.out_mean) / scaling.out_std)  # as train-graph starts
    net.tf.random.set_seed(args.seed)
    loop = argparse.Namespace(lr=args.lr, seed=args.seed, batch_size=args.batch_size, epochs=args.epochs,
                              patience=args.epochs, quiet=args.quiet)
    print(f"probes {probes}{', body state' if args.body_state else ''}{', pooled' if args.pooled else ''}{', a state per step' if args.global_state else ''}{f', {args.attention} attention heads' if args.attention else ''}:", flush=True)
    t0 = time.perf_counter()
    fitted, _ = _train(net, train, val, loop, scaling, _SquaredError(net))
    row = {"probes": probes, "body_state": args.body_state, "pooled": args.pooled or args.global_state,
           "global_state": args.global_state, "attention": args.attention, "weights": count_parameters(net.weights()), "history": fitted.history,
           "seconds": time.perf_counter() - t0}
    if pricing is not None:
        row["price"] = pricing(ContactGraphNet(config, fitted.weights), scaling)
    return row


if __name__ == "__main__":
    sys.exit(main())
