"""`deepcontact lab route-ceiling`: how far can the face route take a world with its labels right?

    deepcontact lab route-ceiling --world simclient.zoo:pyramid --seeds 850 --steps 120

The face route reads a classifier's answer as labels (each point lets go, sticks or slides),
solves the step on them and admits the result into the friction cones (docs/models.md). Its
answer can be no better than the same solve and admission on the step's own labels. This prices,
on Box2D's own states (the engine's trial solves, the same state for every answer), Box2D's warm
start, the oracle (the step solved to convergence from Box2D's start: the best a start can be), and
the oracle's own labels (deepcontact.faces.contact_face of its impulses) solved and admitted by the
dense research route of `lab joint-route` (lab.joint_route.Problem) six ways:

    labels:oracle            its labels at contact_face's thresholds (pressing 1e-6 N s, sliding at
                             0.99 of the cone), admitted in --rounds ADMM rounds
    labels:oracle-tight      pressing 1e-12 N s, sliding at 0.99999 of the cone: the labels' own
                             reading left out
    labels:oracle-long       the first labels admitted in ten times --rounds: the admission's
                             convergence left out
    labels:oracle-bounce     the first labels, each point that closes faster than 1 m/s held at its
                             restitution's bounce (Engine.point_restitution), as Box2D's solver
                             holds it and the served route does since 2026-12-07; the three above
                             hold every point at rest, as the route did until then
    labels:oracle-bounce-long the same admitted in ten times --rounds
    labels:oracle-bounce-near the bounce's solve taken nearest Box2D's start (its unknowns' values)
                             rather than least norm: of a redundant pile's solutions, the one
                             nearest where Box2D's sweeps begin

What they share and the oracle does not is the route's choice of solution (the face's least-norm
solve, then the nearest admissible impulses that move the bodies as it does); where they stay far
above the oracle, better labels alone cannot close the gap (on the zoo's pyramids the bounce's
answers read 0.49-0.51x of Builtin's sweeps, the oracle 0.08x; on its polygons 0.07x and 0.06x:
docs/research/2026-12-07-the-zoo-pyramids-ceiling.md). A research instrument: dense algebra,
minutes a world.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bench.stats import ratio_interval
from deepcontact.faces import contact_face

ANSWERS = ("builtin", "oracle", "labels:oracle", "labels:oracle-tight", "labels:oracle-long", "labels:oracle-bounce",
           "labels:oracle-bounce-long", "labels:oracle-bounce-near")
#: (pressing N s, share of the cone read as sliding) of labels:oracle-tight
TIGHT = (1e-12, 0.99999)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION",
                        help="a world, FUNCTION(seed) in PATH.py or MODULE:FUNCTION (e.g. simclient.zoo:pyramid)")
    parser.add_argument("--seeds", default="850", help="seeds (default 850, a choosing seed)")
    parser.add_argument("--steps", type=int, default=120, help="steps per simulation (default 120)")
    parser.add_argument("--rounds", type=int, default=200, help="admission rounds (default 200; the -long answers "
                                                                "ten times as many)")


def price(spec, seed: int, rounds: int, tick=lambda: None) -> dict[str, np.ndarray]:
    """{answer: (steps,) velocity iterations} on Box2D's trajectory of (spec, seed), over the steps
    with a point on an awake body; `tick()` after each step."""
    from bench.inprocess import declared_world
    from lab.joint_route import Problem, joint_rows
    from simclient import worlds

    engine = worlds.build(spec, seed)
    physics = declared_world(spec, engine).physics
    out = {k: [] for k in ANSWERS}

    def trial(impulses: np.ndarray) -> int:
        c = np.asarray(impulses, np.float32)
        return engine.trial(np.ascontiguousarray(c[:, 0]), np.ascontiguousarray(c[:, 1]))

    for _ in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        tick()
        if len(points) == 0 or not engine.awake()[np.concatenate([points["body_a"], points["body_b"]])].any():
            engine.solve()
            continue
        mu = points["friction"].astype(np.float64)
        builtin = engine.builtin_start()
        start = np.stack(builtin, 1).astype(np.float64)
        out["builtin"].append(engine.trial(*builtin))
        oracle = engine.oracle(start=builtin).astype(np.float64)
        oracle = np.where(np.isfinite(oracle), oracle, start)  # points no awake island solves
        out["oracle"].append(trial(oracle))
        problem = Problem(bodies, points, joint_rows(engine, bodies), physics.gravity, engine.config.dt)
        face = contact_face(oracle, mu)
        contact, joint = problem.solve(face, mu)
        out["labels:oracle"].append(trial(problem.admit(contact, joint, face, mu, rounds)))
        out["labels:oracle-long"].append(trial(problem.admit(contact, joint, face, mu, 10 * rounds)))
        tight = contact_face(oracle, mu, *TIGHT)
        contact, joint = problem.solve(tight, mu)
        out["labels:oracle-tight"].append(trial(problem.admit(contact, joint, tight, mu, rounds)))
        bouncing = Problem(bodies, points, joint_rows(engine, bodies), physics.gravity, engine.config.dt,
                           engine.point_restitution(points))
        contact, joint = bouncing.solve(face, mu)
        out["labels:oracle-bounce"].append(trial(bouncing.admit(contact, joint, face, mu, rounds)))
        out["labels:oracle-bounce-long"].append(trial(bouncing.admit(contact, joint, face, mu, 10 * rounds)))
        contact, joint = bouncing.solve(face, mu, reference=start)
        out["labels:oracle-bounce-near"].append(trial(bouncing.admit(contact, joint, face, mu, rounds)))
        engine.set_warm_start(*builtin)
        engine.solve()
    return {k: np.array(v, float) for k, v in out.items()}


def table(runs: list[dict[str, np.ndarray]], cap: int) -> str:
    """The answers' mean sweeps, their ratio to Builtin's with its interval over seeds, and the
    share of steps each ends at the solver's cap."""
    lines = ["| answer | mean sweeps | / builtin | steps at the cap |", "|---|---|---|---|"]
    for name in ANSWERS:
        its = np.concatenate([r[name] for r in runs])
        ratio = ratio_interval([r[name] for r in runs], [r["builtin"] for r in runs])
        lines.append(f"| {name} | {its.mean():.1f} | {ratio.text()} | {100 * np.mean(its >= cap):.1f} % |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    if args.rounds < 1:
        print(f"deepcontact lab route-ceiling: --rounds must be >= 1, got {args.rounds}", file=sys.stderr)
        return 2
    parsed = world_and_seeds(args, "route-ceiling")
    if parsed is None:
        return 2
    spec, seeds = parsed
    from tqdm import tqdm

    bar = tqdm(total=len(seeds) * spec.steps, unit="step", file=sys.stderr)
    runs = [price(spec, s, args.rounds, bar.update) for s in seeds]
    bar.close()
    if not any(len(r["builtin"]) for r in runs):
        print(f"deepcontact lab route-ceiling: no step of {args.world} had a point on an awake body "
              f"in {args.steps} steps; give more --steps", file=sys.stderr)
        return 1
    print(f"`{args.world}`, seeds {args.seeds}, {args.steps} steps, on Box2D's own states; admission in "
          f"{args.rounds} rounds ({10 * args.rounds} for the -long answers)")
    print(table(runs, spec.solver.velocity_iterations))
    return 0
