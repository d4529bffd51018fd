"""`deepcontact lab joint-start`: closed loop, what a reply that also carried the joints' impulses
would buy on a world of rigid revolute joints.

    deepcontact lab joint-start --world examples/chain.py:build --seeds 850-869

Box2D warm-starts each joint from its own last impulse and the contact points from the served
answer; its sweeps then carry a joint's correction one link a sweep, so a chain's contacts wait
on their joints (docs/research/2026-12-07-where-jointed-worlds-lose.md: the converged contacts
with the joints' own start need 0.42x of Builtin's sweeps, with the converged joints too 0.01x).
The zoo route with each rigid revolute joint as two contact points at its anchor
(lab.joint_points) answers the joints' impulses too. This runs each seed six times, the model
called in this process as the server would answer (bench.inprocess.InProcess):

    builtin          Box2D's own warm start
    served           the model's answer at the contact points, the joints' own start
    served+joints    the same answer, and each revolute joint started at the impulses of its two
                     points in the zoo route's answer on its classifier's labels (the joints as
                     points, lab.jointed_points.raw_route; Engine.set_revolute_impulses); where the
                     route declines the step or a joint is not a rigid revolute one, the joints'
                     own start
    served+joints:checked  the same, but the joints started so only where the routes' check
                     (CHECK_SWEEPS of the solver's sweeps on a replica, server.face_route) with
                     the joints as points there says the route's answer and its joints stop
                     sooner than the served answer with the joints' own last impulses
    served+joints:halfway  the same answer, each revolute joint started halfway between its own
                     last impulse and the route's: a smaller step from Box2D's start
    served+joints:picked  the same, but where the engine's own trial solves from this state (the
                     world unchanged) say the route's joint impulses take fewer sweeps than the
                     joints' own start: a perfect check, which no server has, to bound any check

and prints each one's velocity iterations a step with contacts over Builtin's, 95 % bootstrap
over seeds, and served+joints over served. Serving it would need the joints' anchors on the
request and their impulses on the reply (the request carries only which bodies a joint binds).

A research instrument: the joints are read through pybox2d one at a time, a few seconds a simulation.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.stats import ratio_interval

RUNS = ("builtin", "served", "served+joints", "served+joints:checked", "served+joints:picked", "served+joints:halfway")
#: Sweeps of the check served+joints:checked plays from each start (the routes' check_sweeps).
CHECK_SWEEPS = 12


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world with joints")
    parser.add_argument("--seeds", default="850-852", help="seeds (default 850-852, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--models", default="models", help="model folder (default models/); its zoo card's "
                        "classifier labels the joints' route")
    parser.add_argument("--model", default="default", help="the model served at the contact points (default: default)")


def _beats_box2d(bodies, both, answer, box2d, mu, world) -> bool:
    """Whether the route's answer at the contact and the joints' points ((P + 2 J, 2) N s) stops
    in fewer of the solver's sweeps (a replica with the joints as points, up to CHECK_SWEEPS, to
    the world's stopping rule) than the served answer with the joints' own last impulses, or, in
    as many, changes the impulses less at the last: the routes' check (server.face_route), the
    joints in it."""
    from server.face_route import _sweep_change

    stop = world.tolerance if world.tolerance > 0 else 0.0
    route = _sweep_change(bodies, both, answer, mu, world.physics, CHECK_SWEEPS, None, stop)
    theirs = _sweep_change(bodies, both, box2d, mu, world.physics, CHECK_SWEEPS, None, stop)
    return route[0] < theirs[0] or (route[0] == theirs[0] and route[1] < theirs[1])


def simulate(spec, seed: int, models: str, model: str, run: str) -> np.ndarray:
    """(steps with contacts,) velocity iterations of one closed loop of (spec, seed) served as
    `run` (RUNS)."""
    from bench.inprocess import InProcess
    from lab.joint_points import joint_impulses, joint_point_pairs
    from lab.jointed_points import JOINT_FRICTION, JOINT_LABEL, raw_route
    from server.predictors import load_model
    from simclient import worlds

    engine = worlds.build(spec, seed)
    served = zoo = None
    if run != "builtin":
        served = InProcess.load(Path(models), model, spec)
        served.prepare(engine)
        zoo = load_model(Path(models) / "zoo.json")
    iterations = []
    previous = None  # the step before's points with the joints' (the classifier's new_point channel)
    for k in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if served is not None and len(points):
            normal, tangent = served.warm_start(engine, bodies, points, k)
            if run.startswith("served+joints"):
                pairs = joint_point_pairs(engine, points.dtype, only_rigid=False)
                if pairs is not None and len(pairs):
                    both = np.concatenate([points, pairs])
                    mu = np.asarray(both["friction"], np.float32)
                    labels = zoo.classifier.predict(bodies, both, served.world, k, previous, friction=mu).impulses.copy()
                    labels[len(points):] = (JOINT_LABEL, 0.0)
                    mu[len(points):] = JOINT_FRICTION
                    answer = raw_route(zoo, bodies, both, labels, mu, served.world)
                    if answer is not None and run == "served+joints:picked":
                        # The engine's own trials, both starts from the same state: the check no server has.
                        own = engine.joint_state()
                        theirs = engine.trial(normal, tangent)
                        engine.set_revolute_impulses(joint_impulses(engine, answer[len(points):]))
                        if engine.trial(normal, tangent) >= theirs:
                            engine.set_joint_state(own)
                    elif answer is not None and run == "served+joints:halfway":
                        own = joint_impulses(engine, pairs["builtin"])  # the joints' last impulses, as their points hold them
                        engine.set_revolute_impulses(0.5 * (own + joint_impulses(engine, answer[len(points):])))
                    elif answer is not None and (run != "served+joints:checked" or _beats_box2d(
                            bodies, both, answer, np.concatenate([np.stack([normal, tangent], 1), pairs["builtin"]]),
                            mu, served.world)):
                        engine.set_revolute_impulses(joint_impulses(engine, answer[len(points):]))
                    previous = both
            engine.set_warm_start(normal, tangent)
        stats = engine.solve()
        if stats.contact_points:
            iterations.append(stats.velocity_iterations)
    return np.array(iterations, float)


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    parsed = world_and_seeds(args, "joint-start")
    if parsed is None:
        return 2
    spec, seeds = parsed
    from tqdm import tqdm

    try:
        runs = {name: [simulate(spec, s, args.models, args.model, name) for s in tqdm(seeds, unit="sim", desc=name,
                                                                                       file=sys.stderr)]
                for name in RUNS}
    except FileNotFoundError as exc:
        print(f"deepcontact lab joint-start: {exc}", file=sys.stderr)
        return 2
    print(f"`{args.world}`, seeds {args.seeds}, {args.model} in process, closed loop: velocity iterations a step "
          "with contacts over Builtin's")
    print("| run | mean iterations | / builtin | / served |\n|---|---|---|---|")
    for name in RUNS:
        mean = float(np.mean(np.concatenate(runs[name]))) if any(len(r) for r in runs[name]) else float("nan")
        over = ratio_interval(runs[name], runs["builtin"]).text()
        served = ratio_interval(runs[name], runs["served"]).text() if name != "builtin" else "–"
        print(f"| {name} | {mean:.1f} | {over} | {served} |")
    return 0
