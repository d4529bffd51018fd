"""`deepcontact lab jointed-points`: on a world with joints, is it the points that touch a jointed
body that keep the default from Box2D's converged answer, or the rest?

    deepcontact lab jointed-points --world examples/chain.py:build --seeds 850-852

The server answers Box2D's own warm start (extrapolated along the stream) at every point that
touches a jointed body, and the model the rest (server/joints.py). This prices, by the engine's
trial solves on Box2D's own trajectory (the same states for every answer):

    builtin          Box2D's warm start
    served           the default's answer as the server gives it (bench.inprocess.InProcess's
                     call: around the joints, extrapolated along the stream)
    oracle           the step solved to convergence from Box2D's start (Engine.oracle, the joints
                     in it): the best a warm start of the contact points alone can be
    oracle@jointed   served, with the oracle's impulses at the jointed points: what a perfect
                     answer there alone would be worth
    oracle@free      the oracle at the points free of joints, served (Box2D's start) at the
                     jointed ones: what a perfect model of the rest alone would be worth
    route            the default asked about every point, the joints left out of its problem
    route:joints-warm  the same on the bodies' velocities after Box2D's warm start of its joints
                     (the step before's joint impulses, each joint's reaction at its anchors,
                     Joint.GetReactionForce and GetReactionTorque): the joints held at their
                     last impulses, the contact problem left once those are given
    route:raw        the zoo route's own solve and admission on its classifier's labels
                     (deepcontact.faces.route_compiled, the zoo card's settings), with no check
                     against Box2D's start, the joints left out
    route:joints-as-points  the same with each joint in the step's problem as two contact points
                     at its anchor, normals opposed, labelled pressing and sticking with no
                     friction bound (a rigid revolute joint's two rows), the classifier asked
                     about them too (friction 1, Box2D's start their last impulse): only on a
                     world whose joints are all rigid revolute ones (no limit, no motor)
    labels:oracle    the same route on the oracle's own labels (read at 1e-6 N s and 0.99 of the
                     cone, 200 admission rounds), the joints left out
    labels:oracle+joints-as-points  the same with the joints as points: what the route, joints in,
                     makes of right labels
    labels:oracle@jointed+joints-as-points  the oracle's labels at the jointed points, the
                     classifier's (read as the zoo card reads them) at the rest, the joints as points
    labels:builtin@jointed+joints-as-points  the same with Box2D's start read as labels at the
                     jointed points (the step before's impulses, read as the oracle's are)
    labels:repaired-K@jointed+joints-as-points  the classifier's labels everywhere, then K steps of
                     a primal-dual active-set method at the jointed points alone
                     (deepcontact.faces.repair_face on the route's admitted answer, the joints as
                     points; the free points keep the classifier's labels), K = 1, 2, 4: whether the
                     route's own solves find the jointed points' labels where the classifier does not
    ...+joints       an answer above with the joints started where it leaves them, in place of
                     their own last impulses (Engine.set_revolute_impulses; Box2D's solver applies
                     a joint's start before its sweeps as it applies the contacts'): oracle+joints
                     the oracle's converged joints; route:joints-as-points+joints,
                     labels:oracle+joints-as-points+joints the impulses of the joints' points in
                     the route's answer; served+joints:route and builtin+joints:route the served
                     answer and Box2D's start with the joints started at those of
                     route:joints-as-points: what the reply would buy if it carried the joints'
                     impulses too
    sweeps-K         Box2D's start after K of the solver's own sweeps (Engine.oracle capped at K,
                     the joints in it), K = 12, 24: what those sweeps alone are worth
    labels:sweeps-K@jointed+joints-as-points  Box2D's start after K sweeps read as labels at the
                     jointed points (as the oracle's are), the classifier's at the rest, the joints
                     as points: whether the solver's first sweeps, which carry a joint's impulse
                     a link a sweep, find the labels there

and a second table: at the jointed and at the free points, how many of the solution's labels
(the oracle's, read as above) the classifier gets right, and after each K repairs, and how many
of them a point keeps from the step before (the same contact, by its key): how far a label
there can be read off the step before.

A research instrument: the joints' impulses are read one joint at a time through pybox2d (the
patched engine exports only which bodies a joint binds), a few seconds a simulation.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

# A joint's two points (lab.joint_points): labelled pressing (N s, far past any card's `pressing`)
# and sticking, and held in a cone so wide that its impulse is bounded in no direction.
from server.revolute import JOINT_FRICTION, JOINT_LABEL

from bench.stats import ratio_interval
from deepcontact.faces import OPEN, SLIDES_MINUS, SLIDES_PLUS, contact_face, repair_face
from lab.joint_points import joint_impulses, joint_point_pairs

#: The repairs priced (labels:repaired-K@jointed+joints-as-points).
REPAIRS = (1, 2, 4)
#: Box2D's sweeps before its start is read as labels (sweeps-K, labels:sweeps-K@jointed+joints-as-points).
SWEEP_READS = (12, 24)
ANSWERS = ("builtin", "served", "oracle", "oracle@jointed", "oracle@free", "route", "route:joints-warm", "route:raw",
           "route:joints-as-points", "labels:oracle", "labels:oracle+joints-as-points",
           "labels:oracle@jointed+joints-as-points", "labels:builtin@jointed+joints-as-points",
           *(f"labels:repaired-{k}@jointed+joints-as-points" for k in REPAIRS),
           *(f"sweeps-{k}" for k in SWEEP_READS), *(f"labels:sweeps-{k}@jointed+joints-as-points" for k in SWEEP_READS),
           "oracle+joints", "route:joints-as-points+joints", "labels:oracle+joints-as-points+joints",
           "served+joints:route", "builtin+joints:route")
#: The second table's rows: labels right against the oracle's, at the jointed and the free points.
LABEL_ROWS = ("the classifier's", *(f"after {k} repair{'s' if k > 1 else ''}" for k in REPAIRS),
              "the step before's solution", *(f"Box2D's start after {k} sweeps" for k in SWEEP_READS))
#: How the oracle's impulses are read as labels (deepcontact.faces.contact_face: pressing above this
#: many N s, sliding at this share of the cone) and admitted, as lab.joint_route reads them.
ORACLE_PRESSING, ORACLE_SHARE, ORACLE_ROUNDS = 1e-6, 0.99, 200


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world with joints")
    parser.add_argument("--seeds", default="850-852", help="seeds (default 850-852, choosing seeds)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--models", default="models", help="model folder (default models/)")
    parser.add_argument("--model", default="default", help="the model priced (default: default)")


def after_joint_warm_start(engine, bodies: np.ndarray) -> np.ndarray:
    """A copy of the engine's body records (B,) with each dynamic body's velocity (m/s) and
    angular velocity (rad/s) moved by its joints' impulses of the step before (N s, each
    joint's reaction at its two anchors, equal and opposite), as Box2D's warm start of the
    joints moves them before its contact sweeps."""
    out = bodies.copy()
    row = {int(b.this): i for i, b in enumerate(engine.world.bodies)}  # creation order: the records' rows
    dv = np.zeros((len(bodies), 3))
    for joint in engine.world.joints:  # pybox2d's objects, one call each: no export of them
        force, torque = joint.GetReactionForce(1.0), float(joint.GetReactionTorque(1.0))
        for body, anchor, sign in ((joint.bodyA, joint.anchorA, -1.0), (joint.bodyB, joint.anchorB, 1.0)):
            if body.type != 2:  # static and kinematic bodies take no impulse
                continue
            r = anchor - body.worldCenter
            local = body.localCenter
            inertia = body.inertia - body.mass * (local[0] ** 2 + local[1] ** 2)  # about the centre of mass
            i = row[int(body.this)]
            dv[i, 0] += sign * force[0] / body.mass
            dv[i, 1] += sign * force[1] / body.mass
            dv[i, 2] += sign * (r[0] * force[1] - r[1] * force[0] + torque) / inertia
    out["velocity"] += dv[:, :2].astype(out["velocity"].dtype)
    out["angular_velocity"] += dv[:, 2].astype(out["angular_velocity"].dtype)
    return out


def _as_impulses(face: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(P, 2) impulses (N s) that contact_face reads as `face` (P,) at any pressing below 1 N s
    and any share up to 1: 1 N s along the normal where a point presses, mu of it along the
    tangent where it slides, its sign the way it slides."""
    out = np.zeros((len(face), 2))
    out[face != OPEN, 0] = 1.0
    out[face == SLIDES_PLUS, 1] = mu[face == SLIDES_PLUS]
    out[face == SLIDES_MINUS, 1] = -mu[face == SLIDES_MINUS]
    return out


def raw_route(zoo, bodies, points, labels, mu, world, read=None) -> np.ndarray | None:
    """The zoo route's compiled solve and admission on `labels` (P, 2) N s, read at the card's
    settings or, with read = (pressing, share, rounds), at those; None where it declines."""
    from deepcontact.faces import route_compiled

    face = zoo.settings
    pressing, share, rounds = read or (face["pressing"], face["share"], face["rounds"])
    answer = route_compiled(bodies, points, np.asarray(labels, np.float64), np.asarray(mu, np.float64), world.physics,
                            pressing, share, None if read else face["label_friction"], rounds, None, None,
                            face["relax"], face["rho"], None)
    return None if answer is None else answer.impulses


def _count(counts: dict, row: str, face: np.ndarray, reference: np.ndarray, fixed: np.ndarray,
           among: np.ndarray | None = None) -> None:
    """Add to counts[row] the (right, all) labels of `face` (P,) against `reference` (P,) at the
    jointed points (`fixed`, (P,) bool) and at the free ones, among the points `among` (all if None)."""
    among = np.ones(len(face), bool) if among is None else among
    right = face == reference
    for where, name in ((fixed & among, "jointed"), (~fixed & among, "free")):
        counts[row][name] += np.array([int(right[where].sum()), int(where.sum())])


def _kept(keys: np.ndarray, before: tuple[np.ndarray, np.ndarray] | None):
    """((P,) bool: the point, by its key (P,) uint64, was in the step before; (P,) int8 its label
    there, or -1); before: (sorted keys, their labels) of the step before, or None."""
    if before is None or len(before[0]) == 0:
        return np.zeros(len(keys), bool), np.full(len(keys), -1, np.int8)
    at = np.minimum(np.searchsorted(before[0], keys), len(before[0]) - 1)
    there = before[0][at] == keys
    return there, np.where(there, before[1][at], -1).astype(np.int8)


def price(spec, seed: int, models: str, model: str) -> tuple[dict[str, np.ndarray], float, dict]:
    """({answer: (steps,) velocity iterations} on Box2D's trajectory of (spec, seed), the share
    of the contact points that touch a jointed body, {LABEL_ROWS row: {"jointed" | "free":
    (right, all) labels}})."""
    from pathlib import Path

    from bench.inprocess import InProcess
    from server.joints import jointed_points
    from simclient import worlds

    from server.predictors import load_model

    engine = worlds.build(spec, seed)
    zoo = load_model(Path(models) / "zoo.json")
    served = InProcess.load(Path(models), model, spec)
    served.prepare(engine)
    predictor, world = served.predictor, served.world
    out = {k: [] for k in ANSWERS}
    jointed_share = []
    counts = {row: {"jointed": np.zeros(2, int), "free": np.zeros(2, int)} for row in LABEL_ROWS}
    before = None  # (sorted keys, the solution's labels) of the step before
    previous = previous_both = None  # the step before's points, for the channels that read it (new_point)
    for k in range(spec.steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points) == 0:
            engine.solve()
            continue
        builtin = np.stack(engine.builtin_start(), 1).astype(np.float32)
        friction = {"friction": points["friction"].astype(np.float32)} \
            if "point_friction" in predictor.requires else {}
        answer = np.stack(served.warm_start(engine, bodies, points, k), 1).astype(np.float32)
        fixed = jointed_points(bodies, points, engine.joints())
        as_box2d = engine.joint_state()  # the joints' own start, put back after every other one
        oracle = engine.oracle(start=(builtin[:, 0].copy(), builtin[:, 1].copy()), keep_joints=True)
        joint_starts = {"oracle+joints": engine.joint_state()}  # {answer: the joints' start, state or (J, 2) N s}
        engine.set_joint_state(as_box2d)
        oracle = np.where(np.isfinite(oracle), oracle, builtin)  # points no awake island solves
        answers_joints = {"oracle+joints": oracle}
        # The route's own state along a stream (a carried admission) is the served answer's: these
        # two are asked without it.
        route = predictor.predict(bodies, points, world, k, previous, **friction).impulses
        warm = predictor.predict(after_joint_warm_start(engine, bodies), points, world, k, previous,
                                 **friction).impulses
        mu = points["friction"].astype(np.float32)
        labels = zoo.classifier.predict(bodies, points, world, k, previous, friction=mu).impulses
        raw = raw_route(zoo, bodies, points, labels, mu, world)
        answers = {"builtin": builtin, "served": answer, "oracle": oracle,
                   "oracle@jointed": np.where(fixed[:, None], oracle, answer),
                   "oracle@free": np.where(fixed[:, None], answer, oracle),
                   "route": route, "route:joints-warm": warm, "route:raw": builtin if raw is None else raw}
        oracle_read = (ORACLE_PRESSING, ORACLE_SHARE, ORACLE_ROUNDS)
        reference = contact_face(np.asarray(oracle, np.float64), mu, ORACLE_PRESSING, ORACLE_SHARE)
        there, label_before = _kept(points["key"], before)
        _count(counts, "the step before's solution", label_before, reference, fixed, there)
        order = np.argsort(points["key"])
        before = (points["key"][order], reference[order])
        exact = raw_route(zoo, bodies, points, oracle, mu, world, oracle_read)
        answers["labels:oracle"] = builtin if exact is None else exact
        joint_points = joint_point_pairs(engine, points.dtype, only_rigid=False)
        if joint_points is not None:
            P = len(points)
            both = np.concatenate([points, joint_points])
            learned = zoo.classifier.predict(bodies, both, world, k, previous_both,
                                             friction=np.asarray(both["friction"], np.float32)).impulses.copy()
            learned[P:] = (JOINT_LABEL, 0.0)
            mu_both = np.concatenate([mu, np.full(len(joint_points), JOINT_FRICTION, np.float32)])
            joined = raw_route(zoo, bodies, both, learned, mu_both, world)
            answers["route:joints-as-points"] = builtin if joined is None else joined[:P]
            if joined is not None:
                held = joint_impulses(engine, joined[P:])
                answers_joints.update({"route:joints-as-points+joints": joined[:P], "served+joints:route": answer,
                                       "builtin+joints:route": builtin})
                joint_starts.update(dict.fromkeys(("route:joints-as-points+joints", "served+joints:route",
                                                   "builtin+joints:route"), held))
            right = np.concatenate([oracle, learned[P:]])
            joined = raw_route(zoo, bodies, both, right, mu_both, world, oracle_read)
            answers["labels:oracle+joints-as-points"] = builtin if joined is None else joined[:P]
            if joined is not None:
                answers_joints["labels:oracle+joints-as-points+joints"] = joined[:P]
                joint_starts["labels:oracle+joints-as-points+joints"] = joint_impulses(engine, joined[P:])
            # The two read alike: the classifier's labels at the free points read at the card's
            # settings, then written as impulses that the oracle's reading takes for the same face.
            mixed = np.where(fixed[:, None], oracle, _as_impulses(contact_face(
                np.asarray(learned[:P], np.float64), mu, zoo.settings["pressing"], zoo.settings["share"]), mu))
            joined = raw_route(zoo, bodies, both, np.concatenate([mixed, learned[P:]]), mu_both, world, oracle_read)
            answers["labels:oracle@jointed+joints-as-points"] = builtin if joined is None else joined[:P]
            mixed[fixed] = builtin[fixed]
            joined = raw_route(zoo, bodies, both, np.concatenate([mixed, learned[P:]]), mu_both, world, oracle_read)
            answers["labels:builtin@jointed+joints-as-points"] = builtin if joined is None else joined[:P]
            for sweeps in SWEEP_READS:
                swept = engine.oracle(max_iterations=sweeps, start=(builtin[:, 0].copy(), builtin[:, 1].copy()))
                swept = np.where(np.isfinite(swept), swept, builtin)
                answers[f"sweeps-{sweeps}"] = swept
                _count(counts, f"Box2D's start after {sweeps} sweeps",
                       contact_face(np.asarray(swept, np.float64), mu, ORACLE_PRESSING, ORACLE_SHARE), reference, fixed)
                mixed[fixed] = swept[fixed]
                joined = raw_route(zoo, bodies, both, np.concatenate([mixed, learned[P:]]), mu_both, world,
                                    oracle_read)
                answers[f"labels:sweeps-{sweeps}@jointed+joints-as-points"] = builtin if joined is None else joined[:P]
            # Repairs at the jointed points alone, from the classifier's labels: each reads the
            # labels off the route's answer on the last ones (the joints as points) and solves again.
            face = contact_face(np.asarray(learned[:P], np.float64), mu, zoo.settings["pressing"],
                                zoo.settings["share"])
            _count(counts, "the classifier's", face, reference, fixed)
            joined = raw_route(zoo, bodies, both, np.concatenate([_as_impulses(face, mu), learned[P:]]), mu_both,
                                world, oracle_read)
            for repairs in range(1, max(REPAIRS) + 1):
                if joined is not None:  # where the route declines the labels, they stay as they are
                    face[fixed] = repair_face(bodies, both, joined, mu_both, world.physics)[:P][fixed]
                    joined = raw_route(zoo, bodies, both, np.concatenate([_as_impulses(face, mu), learned[P:]]),
                                        mu_both, world, oracle_read)
                if repairs in REPAIRS:
                    answers[f"labels:repaired-{repairs}@jointed+joints-as-points"] = \
                        builtin if joined is None else joined[:P]
                    _count(counts, LABEL_ROWS[1 + REPAIRS.index(repairs)], face, reference, fixed)
        for name in ANSWERS:
            if name in joint_starts:  # started with other joints, then the joints put back
                start = joint_starts[name]
                if isinstance(start, bytes):
                    engine.set_joint_state(start)
                else:
                    engine.set_revolute_impulses(start)
                z = np.asarray(answers_joints[name], np.float32)
                out[name].append(engine.trial(np.ascontiguousarray(z[:, 0]), np.ascontiguousarray(z[:, 1])))
                engine.set_joint_state(as_box2d)
                continue
            if name not in answers:
                # A route that declined: its answer is Box2D's start, with the joints' own.
                if name in ("route:joints-as-points+joints", "served+joints:route", "builtin+joints:route",
                            "labels:oracle+joints-as-points+joints") and joint_points is not None:
                    name_as = {"served+joints:route": "served"}.get(name, "builtin")
                    out[name].append(out[name_as][-1])
                continue
            z = np.asarray(answers[name], np.float32)
            out[name].append(engine.trial(np.ascontiguousarray(z[:, 0]), np.ascontiguousarray(z[:, 1])))
        jointed_share.append(float(fixed.mean()))
        engine.set_warm_start(builtin[:, 0].copy(), builtin[:, 1].copy())
        engine.solve()
        previous = points
        previous_both = both if joint_points is not None else None
    return ({k: np.array(v, float) for k, v in out.items()},
            float(np.mean(jointed_share)) if jointed_share else 0.0, counts)


def run(args: argparse.Namespace) -> int:
    from lab.joints_price import world_and_seeds

    parsed = world_and_seeds(args, "jointed-points")
    if parsed is None:
        return 2
    spec, seeds = parsed
    from tqdm import tqdm

    try:
        runs = [price(spec, s, args.models, args.model) for s in tqdm(seeds, unit="sim", file=sys.stderr)]
    except FileNotFoundError as exc:
        print(f"deepcontact lab jointed-points: {exc}", file=sys.stderr)
        return 2
    share = float(np.mean([r[1] for r in runs]))
    print(f"`{args.world}`, seeds {args.seeds}, {args.model} on Box2D's own states: each answer's sweeps "
          f"over Box2D's; {100 * share:.1f} % of the points touch a jointed body")
    print("| answer | mean sweeps | / builtin |\n|---|---|---|")
    for name in ANSWERS:
        if any(len(r[0][name]) != len(r[0]["builtin"]) for r in runs):
            print(f"| {name} | – | – (a joint other than a rigid revolute one) |")
            continue
        ratio = ratio_interval([r[0][name] for r in runs], [r[0]["builtin"] for r in runs])
        mean = float(np.mean(np.concatenate([r[0][name] for r in runs])))
        print(f"| {name} | {mean:.1f} | {ratio.text()} |")
    print("\nThe solution's labels (read at 1e-6 N s and 0.99 of the cone): how many each reading gets right")
    print("| labels | at the jointed points | at the free points |\n|---|---|---|")
    for row in LABEL_ROWS:
        cells = []
        for where in ("jointed", "free"):
            right, total = sum(r[2][row][where] for r in runs)
            cells.append(f"{100 * right / total:.1f} % of {total:,}" if total else "–")
        print(f"| {row} | {cells[0]} | {cells[1]} |")
    return 0
