"""Rigid joints as contact points: can a classifier learn the labels at jointed bodies when each
joint sits in its graph as two points?

    python -m lab.joint_points generate --seeds 1-200 --out data/joints/chains-train-1-200.h5
    python -m lab.joint_points generate --world simclient.zoo:jointed --seeds 1-200 --out data/joints/jointed-train-1-200.h5

A rigid revolute joint holds its two bodies together at its anchor in both directions: two rows of
the step's problem, the same rows as a contact point there that presses and sticks with no bound
on its impulse. So the face route can hold such a joint as two points at the anchor, normals
opposed, labelled pressing and sticking in a cone too wide to bound them
(docs/research/2026-12-07-where-jointed-worlds-lose.md: on the chain of `examples/` the route on
the solution's labels then needs 0.434x of Builtin's sweeps, on them at the jointed points alone
0.714x). The labels at the jointed points are what the shipped classifier gets wrong. This writes
training files whose steps carry those two points of every rigid revolute joint after the step's
own contact points (`training.generate.record_simulation`'s extra_points): keys of their own, Box2D's
start the joint's last impulse on them (its reaction at the anchor, on the normal and half on the
tangent), the face they are served on (pressing, sticking) as their final impulse, friction 1.
Joints of other kinds (limited, motored, sliders, welds) are not written.

`chains(seed)` is a world for it: a heap of mixed bodies in a bin with one to three chains or
bridges of free revolute links over it, the zoo's physics drawn from the seed (simclient.zoo).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from server.revolute import JOINT_POINT_FRICTION, KEY_BASE, joints_on_b

#: The face a joint's points are served on, written as their final impulse (N s; faces.FACE_IMPULSE
#: along the normal: pressing; none along the tangent: sticking at friction JOINT_POINT_FRICTION).
SERVED_FACE = (1.0, 0.0)


def rigid_revolute(joint) -> bool:
    import Box2D

    return isinstance(joint, Box2D.b2RevoluteJoint) and not joint.limitEnabled and not joint.motorEnabled


def joint_point_pairs(engine, template_dtype: np.dtype, only_rigid: bool = True) -> np.ndarray | None:
    """Each rigid revolute joint of the engine's world as two contact records at its anchor between
    its two bodies (engine body indices), normals +x and -x; their builtin the joint's last impulse
    (N s: along the normal where it points that way, half the rest along the tangent), friction
    JOINT_POINT_FRICTION, final impulse SERVED_FACE. Joints of other kinds are left out, or, with
    only_rigid False, make it None. The records of the 2 J points, in the world's joint order."""
    row = {int(b.this): i for i, b in enumerate(engine.world.bodies)}  # creation order: the records' rows
    joints = list(engine.world.joints)  # pybox2d's objects, one call each: the patch exports no joint state
    rigid = [rigid_revolute(j) for j in joints]
    if not only_rigid and not all(rigid):
        return None
    out = np.zeros(2 * sum(rigid), template_dtype)
    k = 0
    for i, joint in enumerate(joints):
        if not rigid[i]:
            continue
        impulse = joint.GetReactionForce(1.0)
        for sign in (1.0, -1.0):
            along, across = sign * impulse[0], -sign * impulse[1]  # on the normal (sign, 0) and its tangent (0, -sign)
            out[k]["key"] = np.uint64(KEY_BASE + 2 * i + (sign < 0))
            out[k]["body_a"], out[k]["body_b"] = row[int(joint.bodyA.this)], row[int(joint.bodyB.this)]
            out[k]["point"] = tuple(joint.anchorB)
            out[k]["normal"] = (sign, 0.0)
            out[k]["builtin"] = (max(along, 0.0), across / 2)
            k += 1
    out["warm_start"] = out["builtin"]
    out["impulse"] = SERVED_FACE
    out["friction"] = JOINT_POINT_FRICTION
    return out


def joint_impulses(engine, answer: np.ndarray) -> np.ndarray:
    """The joints' impulses an answer at their points (joint_point_pairs, every joint a rigid
    revolute one) holds: answer (2 J, 2) N s (normal, tangent) of the joints' points, in their
    order; returns (J, 2) float32, N s, world frame, on each joint's body B, in the engine's
    joint order (Engine.joints, what Engine.set_revolute_impulses takes). A point's impulse
    pushes body B along its normal (sign, 0) and its tangent (0, -sign)."""
    on_b = joints_on_b(answer)
    row = {int(b.this): i for i, b in enumerate(engine.world.bodies)}
    where = {(row[int(j.bodyA.this)], row[int(j.bodyB.this)]): i for i, j in enumerate(engine.world.joints)}
    return on_b[[where[tuple(pair)] for pair in engine.joints()]].astype(np.float32)


def chains(seed: int):
    """A heap of 20-60 mixed bodies in a bin 8-16 m wide and over it 1-3 chains or bridges of
    10-40 thin links on free revolute joints (no limit, no motor), hung from a static anchor at one
    end or across the bin; the zoo's physics (gravity, time step, density, friction) from the seed.
    Returns (world, dt)."""
    from simclient import zoo

    rng, physics, world = zoo._start(seed)
    kinds, sizes = zoo._mixed(rng, int(rng.integers(20, 61)))
    width = float(rng.uniform(8.0, 16.0))
    centres = zoo._place(rng, sizes, (0.0, width), zoo._flat(0.0))
    level = float((centres[:, 1] + sizes).max()) + 0.3  # m, the first chain's height
    ground = zoo._bin(world, physics, width, level + 4.0)
    zoo._heap(world, physics, rng, kinds, sizes, centres)
    for c in range(int(rng.integers(1, 4))):
        links, bridge = int(rng.integers(10, 41)), bool(rng.random() < 0.4)
        span = width - 0.2 if bridge else float(rng.uniform(0.4, 0.9)) * width  # m
        length = span / links  # m, a link's
        thick = min(0.1, 0.2 * length)  # m, half a link's thickness
        x0 = 0.1 if bridge else float(rng.uniform(0.1, width - span - 0.1))  # m, the first joint's
        y = level + 0.6 * c
        previous = ground if bridge else world.CreateStaticBody(position=(x0, y))
        for i in range(links):
            link = world.CreateDynamicBody(position=(x0 + length * (i + 0.5), y))
            link.CreatePolygonFixture(box=(0.5 * length, thick), **physics.body(rng))
            world.CreateRevoluteJoint(bodyA=previous, bodyB=link, anchor=(x0 + length * i, y))
            previous = link
        if bridge:
            world.CreateRevoluteJoint(bodyA=previous, bodyB=ground, anchor=(x0 + span, y))
    return world, physics.dt


def simulate_seed(spec_dict: dict, seed: int) -> dict[str, np.ndarray]:
    """One task: training.generate.record_simulation of (world, seed) with every rigid revolute
    joint's two points recorded after the step's contact points."""
    from deepcontact.records import CONTACT_DTYPE
    from simclient import worlds
    from training.generate import record_simulation

    return record_simulation(worlds.spec_from_dict(spec_dict), seed,
                             extra_points=lambda engine: joint_point_pairs(engine, CONTACT_DTYPE))


def main(argv: list[str] | None = None) -> int:
    from deepcontact import dispatch
    from simclient import seeds as seed_ranges
    from simclient import worlds
    from training.dataset import Writer

    parser = argparse.ArgumentParser(prog="python -m lab.joint_points", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    gen = sub.add_parser("generate", help="record simulations with their joints as points into an HDF5 file")
    gen.add_argument("--world", default="lab.joint_points:chains", metavar="PATH.py:FUNCTION",
                     help="the world (default %(default)s)")
    gen.add_argument("--seeds", required=True, help="training seeds, e.g. 1-200")
    gen.add_argument("--steps", type=int, default=250, help="steps a simulation (default 250)")
    gen.add_argument("--workers", type=int, default=2, help="worker processes (default 2)")
    gen.add_argument("--out", required=True, type=Path, help="the HDF5 file to write")
    args = parser.parse_args(argv)
    try:
        spec = worlds.WorldSpec(args.world, steps=args.steps)
        spec.validate()
        seeds = seed_ranges.parse_seeds(args.seeds)
        if seed_ranges.outside_training(seeds):
            raise ValueError(f"seeds {args.seeds} are not all training seeds (1-899)")
        if args.out.exists():
            raise ValueError(f"{args.out} exists")
    except ValueError as exc:
        print(f"python -m lab.joint_points: {exc}", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tasks = [dispatch.Task(f"seed {s}", (worlds.spec_to_dict(spec), s)) for s in seeds]
    command = "python -m lab.joint_points " + " ".join(sys.argv[1:] if argv is None else argv)
    with Writer(args.out, scene=worlds.spec_to_dict(spec), seeds=seeds, command=command, oracle=False,
                compression="gzip") as writer, dispatch.Dispatcher(workers=args.workers, ray=None) as dispatcher:
        for arrays in dispatcher.map(simulate_seed, tasks, progress="generate"):
            writer.append(arrays["steps"], arrays["bodies"], arrays["points"], arrays["trace"], None,
                          physics=arrays["physics"])
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
