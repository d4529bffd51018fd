"""`deepcontact lab joint-start`: closed loop, what a reply that also carried the joints' impulses
would buy on a world of revolute joints.

    deepcontact lab joint-start --world examples/chain.py:build --seeds 850-869
    deepcontact lab joint-start --world simclient.zoo:ragdolls --seeds 850-854 --on-builtin

Box2D warm-starts each joint from its own last impulse and the contact points from the served
answer; its sweeps then carry a joint's correction one link a sweep, so a chain's contacts wait
on their joints (docs/research/2026-12-07-where-jointed-worlds-lose.md: the converged contacts
with the joints' own start need 0.42x of Builtin's sweeps, with the converged joints too 0.01x).
The zoo route with each rigid revolute joint as two contact points at its anchor
(lab.joint_points) answers the joints' impulses too. This runs each seed six times, the model
called in this process as the server would answer (bench.inprocess.InProcess):

    builtin          Box2D's own warm start
    served           the model's answer at the contact points alone, the joints' own start (as
                     served before the joints' start was, and what every run below builds on)
    served+revolute  as the server answers now (server.revolute): of five starts, the one its
                     copy of the step with the joints swept as Box2D sweeps them stops soonest
                     from, the joints' start too where it is the route's
    served+joints    the same answer, and each revolute joint started at the impulses of its two
                     points in the zoo route's answer on its classifier's labels (the joints as
                     points, lab.jointed_points.raw_route; Engine.set_revolute_impulses); where the
                     route declines the step or a joint is not a rigid revolute one, the joints'
                     own start
    served+joints:checked  the same, but the joints started so only where the routes' check
                     (CHECK_SWEEPS of the solver's sweeps on a replica, server.face_route) with
                     the joints as points there says the route's answer and its joints stop
                     sooner than the served answer with the joints' own last impulses
    served+joints:replica  the same, but the joints started so only where the server's copy of the
                     step with Box2D's own joint rows (deepcontact.faces.sweeps_to_stop with
                     RevoluteRows: each joint swept as b2RevoluteJoint does, before the contacts)
                     stops sooner, up to REPLICA_SWEEPS, from the served answer with the route's
                     joint impulses than with the joints' own last impulses: a check a server could
                     make, were the joints' anchors and last impulses on the request
    best:picked      the same five starts, the one the engine's own trials from this state say
                     stops soonest: the bound on any check among them
    served+joints:halfway  the same answer, each revolute joint started halfway between its own
                     last impulse and the route's: a smaller step from Box2D's start
    served+joints:picked  the same, but where the engine's own trial solves from this state (the
                     world unchanged) say the route's joint impulses take fewer sweeps than the
                     joints' own start: a perfect check, which no server has, to bound any check

and prints each one's velocity iterations a step with contacts over Builtin's, 95 % bootstrap
over seeds, and served+joints over served. With --on-builtin, builtin, served and served+revolute
are priced instead on Box2D's own trajectory: at each step the engine's trial solve from each
start (the joints' start set where the answer carries one, then put back), every run on the very
same states, so a chaotic world's closed-loop spread does not hide the difference; beside them two
oracles of the angle limits' own impulse (Engine.set_revolute_impulses with a third column), which
the reply does not carry: builtin+limits* and served+revolute+limits*, the same starts with each
active limit started at the impulse Box2D's solve of that step ends at (its limits' warm start
the limit's own last impulse otherwise; docs/research/2026-12-07-island-by-island.md, "The
limits' impulse"). Serving it would need the joints' anchors on the
request and their impulses on the reply (the request carries only which bodies a joint binds).

A research instrument: the joints are read through pybox2d one at a time, a few seconds a simulation.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.stats import ratio_interval

RUNS = ("builtin", "served", "served+revolute", "served+joints", "served+joints:checked", "served+joints:replica",
        "served+joints:picked", "served+joints:halfway", "best:picked")
#: Sweeps of the check served+joints:checked plays from each start (the routes' check_sweeps).
CHECK_SWEEPS = 12
#: The most sweeps served+joints:replica plays from each start (the zoo route's check_sweeps).
REPLICA_SWEEPS = 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world with joints")
    parser.add_argument("--seeds", default="850-852", help="seeds (default 850-852, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--models", default="models", help="model folder (default models/); its zoo card's "
                        "classifier labels the joints' route")
    parser.add_argument("--model", default="default", help="the model served at the contact points (default: default)")
    parser.add_argument("--runs", default=",".join(RUNS), help=f"which runs, comma-separated (default all: {','.join(RUNS)}); "
                        "builtin and served are always run")
    parser.add_argument("--on-builtin", action="store_true", help="price builtin, served and served+revolute (and "
                        "the limits' oracles, builtin+limits* and served+revolute+limits*) on "
                        "Box2D's own trajectory (the engine's trial solves, the same states for each) instead of "
                        "closed loop (--runs then does not apply)")


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


def _replica_prefers(bodies, points, served, own, route, world) -> bool:
    """Whether the server's copy of the step with the joints as Box2D sweeps them stops sooner
    from the served answer (P, 2) N s with the route's joint impulses `route` than with the
    joints' own last impulses: own (bodies (J, 2), arms (J, 4), impulses (J, 2)) of
    server.revolute.rows, route (J, 2) N s, both on body B in the engine's joint order (Engine.joints);
    in as many sweeps, whether its last sweep changes the contacts' impulses less."""
    from deepcontact.faces import RevoluteRows, sweeps_to_stop

    ab, arms, start = own
    starts = np.repeat(np.asarray(served, np.float64)[None], 2, 0)
    counts, changes = sweeps_to_stop(bodies, points, starts, np.asarray(points["friction"], np.float64), world.physics,
                                     world.tolerance, REPLICA_SWEEPS, None,
                                     RevoluteRows(ab, arms, np.stack([start, route])))
    return counts[1] < counts[0] or (counts[1] == counts[0] and changes[1] < changes[0])


def _best_of(engine, bodies, points, served, zoo, world, step, previous):
    """(normal, tangent) (P,) float32 N s of the start best:picked takes, the engine's revolute
    joints set to its joints' start: of server.revolute's five starts (the route here on the
    lab's joints' points, lab.joint_points), the one the engine's own trials say stops soonest."""
    from lab.joint_points import joint_impulses, joint_point_pairs
    from lab.jointed_points import JOINT_FRICTION, JOINT_LABEL, raw_route

    P = len(points)
    candidates = [(np.asarray(points["builtin"], np.float64), None), (np.asarray(served, np.float64), None)]
    pairs = joint_point_pairs(engine, points.dtype, only_rigid=False)
    if pairs is not None and len(pairs):
        both = np.concatenate([points, pairs])
        mu = np.asarray(both["friction"], np.float32)
        labels = zoo.classifier.predict(bodies, both, world, step, previous, friction=mu).impulses.copy()
        labels[P:] = (JOINT_LABEL, 0.0)
        mu[P:] = JOINT_FRICTION
        answer = raw_route(zoo, bodies, both, labels, mu, world)
        if answer is not None:
            joints = joint_impulses(engine, answer[P:])
            route = np.asarray(answer[:P], np.float64)
            candidates += [(route, None), (candidates[1][0], joints), (route, joints)]
    own = engine.joint_state()
    counts = []
    for contacts, joints in candidates:
        engine.set_joint_state(own)
        if joints is not None:
            engine.set_revolute_impulses(joints)
        counts.append(engine.trial(contacts[:, 0].astype(np.float32), contacts[:, 1].astype(np.float32)))
    engine.set_joint_state(own)
    contacts, joints = candidates[int(np.argmin(counts))]
    if joints is not None:
        engine.set_revolute_impulses(joints)
    return contacts[:, 0].astype(np.float32), contacts[:, 1].astype(np.float32)


def simulate(spec, seed: int, models: str, model: str, run: str) -> np.ndarray:
    """(steps with contacts,) velocity iterations of one closed loop of (spec, seed) served as
    `run` (RUNS)."""
    from bench.inprocess import InProcess
    from lab.joint_points import joint_impulses, joint_point_pairs
    from lab.jointed_points import JOINT_FRICTION, JOINT_LABEL, raw_route
    from server.predictors import load_model
    from server.revolute import rows
    from simclient import worlds

    engine = worlds.build(spec, seed)
    served = zoo = None
    if run != "builtin":
        served = InProcess.load(Path(models), model, spec, revolute_joints=run == "served+revolute")
        served.prepare(engine)
        zoo = load_model(Path(models) / "zoo.json")
    iterations = []
    previous = None  # the step before's points with the joints' (the classifier's new_point channel)
    for k in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if served is not None and len(points):
            normal, tangent = served.warm_start(engine, bodies, points, k)
            if run == "best:picked":
                normal, tangent = _best_of(engine, bodies, points, np.stack([normal, tangent], 1), zoo, served.world,
                                           k, previous)
            elif run.startswith("served+joints"):
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
                    elif answer is not None and run == "served+joints:replica":
                        own = rows(bodies, engine.joints(), engine.revolute())
                        theirs = joint_impulses(engine, answer[len(points):])
                        if _replica_prefers(bodies, points, np.stack([normal, tangent], 1), own, theirs, served.world):
                            engine.set_revolute_impulses(theirs)
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


#: --on-builtin's runs (module docstring).
ON_BUILTIN = ("builtin", "served", "served+revolute", "builtin+limits*", "served+revolute+limits*")


def priced(spec, seed: int, models: str, model: str) -> dict[str, np.ndarray]:
    """{run: (steps with contacts,) velocity iterations} of ON_BUILTIN, each the engine's trial
    solve from its start on Box2D's own trajectory of (spec, seed): the joints' start set where
    the answer carries one (served+revolute), then put back; the limits' oracles with each active
    limit's impulse the one Box2D's own solve of the step ends at (read off a first run of the
    same trajectory)."""
    from bench.inprocess import InProcess
    from simclient import worlds

    engine = worlds.build(spec, seed)
    ended = []  # each step's joints after Box2D's own solve: the limits' impulses it ends at
    for k in range(spec.steps):
        engine.collide()
        engine.solve()
        ended.append(engine.revolute()[:, 8].copy())
    engine = worlds.build(spec, seed)
    served = InProcess.load(Path(models), model, spec, revolute_joints=False)
    revolute = InProcess.load(Path(models), model, spec, revolute_joints=True)
    served.prepare(engine)
    revolute.prepare(engine)
    out = {name: [] for name in ON_BUILTIN}
    with_limits = lambda: np.concatenate([engine.revolute()[:, 5:7], ended[k][:, None]], 1)  # noqa: E731
    for k in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points):
            own = engine.joint_state()
            box2d = np.asarray(points["builtin"], np.float32)
            out["builtin"].append(engine.trial(box2d[:, 0].copy(), box2d[:, 1].copy()))
            engine.set_revolute_impulses(with_limits())
            out["builtin+limits*"].append(engine.trial(box2d[:, 0].copy(), box2d[:, 1].copy()))
            engine.set_joint_state(own)
            out["served"].append(engine.trial(*served.warm_start(engine, bodies, points, k)))
            start = revolute.warm_start(engine, bodies, points, k)
            out["served+revolute"].append(engine.trial(*start))
            engine.set_revolute_impulses(with_limits())  # the served joints' start, the limits' at their end
            out["served+revolute+limits*"].append(engine.trial(*start))
            engine.set_joint_state(own)  # Box2D's trajectory goes on from its own start
            engine.set_warm_start(box2d[:, 0].copy(), box2d[:, 1].copy())
        engine.solve()
    return {name: np.array(v, float) for name, v in out.items()}


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    parsed = world_and_seeds(args, "joint-start")
    if parsed is None:
        return 2
    spec, seeds = parsed
    from tqdm import tqdm

    chosen = [name.strip() for name in args.runs.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in RUNS]
    if unknown:
        print(f"deepcontact lab joint-start: unknown run {unknown[0]!r}; runs are {', '.join(RUNS)}", file=sys.stderr)
        return 2
    chosen = [name for name in RUNS if name in ("builtin", "served") or name in chosen]
    if args.on_builtin:
        return _on_builtin(args, spec, seeds)
    try:
        runs = {name: [simulate(spec, s, args.models, args.model, name) for s in tqdm(seeds, unit="sim", desc=name,
                                                                                       file=sys.stderr)]
                for name in chosen}
    except FileNotFoundError as exc:
        print(f"deepcontact lab joint-start: {exc}", file=sys.stderr)
        return 2
    print(f"`{args.world}`, seeds {args.seeds}, {args.model} in process, closed loop: velocity iterations a step "
          "with contacts over Builtin's")
    print("| run | mean iterations | / builtin | / served |\n|---|---|---|---|")
    for name in chosen:
        mean = float(np.mean(np.concatenate(runs[name]))) if any(len(r) for r in runs[name]) else float("nan")
        over = ratio_interval(runs[name], runs["builtin"]).text()
        served = ratio_interval(runs[name], runs["served"]).text() if name != "builtin" else "–"
        print(f"| {name} | {mean:.1f} | {over} | {served} |")
    return 0


def _on_builtin(args: argparse.Namespace, spec, seeds) -> int:
    from tqdm import tqdm

    try:
        per_seed = [priced(spec, s, args.models, args.model) for s in tqdm(seeds, unit="sim", desc="priced",
                                                                             file=sys.stderr)]
    except FileNotFoundError as exc:
        print(f"deepcontact lab joint-start: {exc}", file=sys.stderr)
        return 2
    runs = {name: [p[name] for p in per_seed] for name in ON_BUILTIN}
    print(f"`{args.world}`, seeds {args.seeds}, {args.model} in process, priced on Box2D's own states: velocity "
          "iterations a step with contacts over Builtin's")
    print("| run | mean iterations | / builtin | / served |\n|---|---|---|---|")
    for name, values in runs.items():
        mean = float(np.mean(np.concatenate(values))) if any(len(v) for v in values) else float("nan")
        over = ratio_interval(values, runs["builtin"]).text()
        served = ratio_interval(values, runs["served"]).text() if name != "builtin" else "–"
        print(f"| {name} | {mean:.1f} | {over} | {served} |")
    return 0
