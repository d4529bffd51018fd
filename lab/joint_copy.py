"""`deepcontact lab joint-copy`: does the server's copy of a step count the sweeps Box2D's solver
takes, with a world's joints in it and without them?

    deepcontact lab joint-copy --world examples/chain.py:build --seeds 850 --steps 150

On Box2D's own trajectory, at each step with contact points, from Box2D's own start: the engine's
trial solve (its sweeps to the stopping rule, the joints in it) against the server's copy of the
step (deepcontact.faces.sweeps_to_stop, up to the engine's cap) with the joints swept as
Box2D's solver does (RevoluteRows, server.revolute.rows and .limits: revolute joints with their
angle limits and motors, rigid welds, prismatic joints) and without them (the routes' check as it
was before 2026-12-07's joints' start). Prints, for each copy, the steps whose count lies within
3 sweeps of the engine's and the correlation of the two counts. Only worlds whose every joint is
of those kinds.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

#: A copy's count "agrees" with the engine's within this many sweeps.
WITHIN = 3


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world of revolute, rigid weld and prismatic joints")
    parser.add_argument("--seeds", default="850", help="seeds (default 850, a choosing seed)")
    parser.add_argument("--steps", type=int, default=150, help="steps per simulation (default 150)")


def counts(spec, seed: int) -> np.ndarray:
    """(steps with points, 3) int: the engine's sweeps, the copy's with the joints, without them."""
    from bench.inprocess import declared_world
    from deepcontact.faces import RevoluteRows, sweeps_to_stop
    from server.revolute import all_held, limits, rows
    from simclient import worlds

    engine = worlds.build(spec, seed)
    physics, tolerance = declared_world(spec, engine).physics, engine.config.velocity_threshold
    cap = engine.config.velocity_iterations
    out = []
    for _ in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points):
            revolute = engine.revolute()
            if not all_held(revolute):
                raise ValueError("a joint of this world is of a kind the server's copy does not hold (or it has none)")
            start = np.asarray(points["builtin"], np.float64)
            mu = np.asarray(points["friction"], np.float64)
            ab, arms, own = rows(bodies, engine.joints(), revolute)
            joined = sweeps_to_stop(bodies, points, start[None], mu, physics, tolerance, cap, None,
                                    RevoluteRows(ab, arms, own[None], limits(bodies, engine.joints(), revolute, physics.dt)))[0][0]
            alone = sweeps_to_stop(bodies, points, start[None], mu, physics, tolerance, cap)[0][0]
            normal, tangent = start[:, 0].astype(np.float32), start[:, 1].astype(np.float32)
            out.append((engine.trial(normal, tangent), int(joined), int(alone)))
            engine.set_warm_start(normal, tangent)
        engine.solve()
    return np.array(out, np.int64).reshape(-1, 3)


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    parsed = world_and_seeds(args, "joint-copy")
    if parsed is None:
        return 2
    spec, seeds = parsed
    if spec.solver.velocity_threshold <= 0:
        print("deepcontact lab joint-copy: the solver has no stopping rule to count sweeps to (--tolerance)",
              file=sys.stderr)
        return 2
    try:
        table = np.concatenate([counts(spec, s) for s in seeds])
    except ValueError as exc:
        print(f"deepcontact lab joint-copy: {exc}", file=sys.stderr)
        return 2
    if not len(table):
        print("deepcontact lab joint-copy: no steps with contact points", file=sys.stderr)
        return 2
    print(f"`{args.world}`, seeds {args.seeds}, {len(table)} steps with contact points: Box2D's start, the engine's "
          f"sweeps against the server's copy of the step")
    print(f"| the copy | within {WITHIN} sweeps of the engine's | correlation |\n|---|---|---|")
    for column, name in ((1, "with the joints' rows"), (2, "without them")):
        agree = int((abs(table[:, column] - table[:, 0]) <= WITHIN).sum())
        corr = float(np.corrcoef(table[:, 0], table[:, column])[0, 1]) if table[:, column].std() > 0 else float("nan")
        print(f"| {name} | {agree} of {len(table)} ({agree / len(table):.0%}) | {corr:.2f} |")
    return 0
