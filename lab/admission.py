"""`deepcontact lab admission`: what admitting a motion costs a step, beside Box2D's solve.

    deepcontact lab admission --seeds 850-852 --json bench/results/r2-admission/timings.json

The admitted warm starts (`oracle:near-admissible*`, `admit:W`; docs/results.md, "The limits
choose the self-stress") run in NumPy on the client. Before any of them could be served, their
cost per step has to come down below the solver work they save. On thesis piles after
--settle steps of Box2D's own warm start, for each of --steps steps this times, with
the step's exact motion (the solution from Box2D's warm start, `engine.oracle(start=...)`):

- body-space: `body_space_part`, the least-norm change that moves every body as the solution does;
- moving split: `body_space_part_of` at the moving bodies (`bodies_moving`), the rest at Box2D's;
- admit: `nearest_admissible` of Box2D's warm start plus that body-space change (ADMM);
- admit moving: the same of the moving split;
- Box2D's solve: one trial solve from Box2D's own warm start (`engine.trial`), the solver work
  a warm start has to save, timed on the same step.

Printed: per part the median and 90th percentile over all timed steps, in ms, and the median
ratio of each part to Box2D's solve on the same step. Times are wall times on this machine,
one process; set OMP_NUM_THREADS=1 for numbers comparable to the benchmarks'.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from deepcontact.io import write_json_atomic

PARTS = ("body_space", "moving_split", "admit", "admit_moving", "box2d_solve")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="850-852", help="thesis-world seeds (default %(default)s, choosing seeds)")
    parser.add_argument("--settle", type=int, default=200,
                        help="Box2D's own steps before timing, so the piles have formed (default %(default)s)")
    parser.add_argument("--steps", type=int, default=10, help="steps timed per seed (default %(default)s)")
    parser.add_argument("--json", metavar="FILE", help="write the per-step timings and the summary here")


def _timed(fn):
    """(fn(), seconds)."""
    t0 = time.perf_counter()
    out = fn()
    return out, time.perf_counter() - t0


def run(args: argparse.Namespace) -> int:
    from deepcontact.admission import nearest_admissible
    from deepcontact.kinematics import bodies_moving, body_space_part, body_space_part_of
    from simclient.scene import SceneSpec, settled_world
    from simclient.seeds import parse_seeds
    from simclient.provider import body_friction, point_friction

    if args.settle < 0 or args.steps < 1:
        raise SystemExit("lab admission: --settle must be >= 0 and --steps >= 1")
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as e:
        raise SystemExit(f"lab admission: {e}") from None
    rows = []
    for seed in seeds:
        engine = settled_world(SceneSpec.thesis(), seed, args.settle)
        friction = body_friction(engine)
        for _ in range(args.steps):  # steps, not points
            engine.collide()
            bodies, points = engine.bodies(), engine.contacts()
            builtin_pair = (np.ascontiguousarray(points["builtin"][:, 0]), np.ascontiguousarray(points["builtin"][:, 1]))
            if len(points):
                builtin = points["builtin"].astype(np.float64)
                exact = engine.oracle(start=builtin_pair).astype(np.float64)
                change = np.where(np.isnan(exact), builtin, exact) - builtin
                mu = point_friction(friction, points)
                moves, t_body = _timed(lambda: body_space_part(bodies, points, change))
                moving, t_split = _timed(lambda: body_space_part_of(bodies, points, change, bodies_moving(bodies)))
                _, t_admit = _timed(lambda: nearest_admissible(bodies, points, builtin + moves, mu))
                _, t_moving = _timed(lambda: nearest_admissible(bodies, points, builtin + moving, mu))
                _, t_solve = _timed(lambda: engine.trial(*builtin_pair))
                rows.append({"seed": seed, "step": engine.step_index, "contact_points": int(len(points)),
                             "body_space": t_body, "moving_split": t_split, "admit": t_admit,
                             "admit_moving": t_moving, "box2d_solve": t_solve})
            engine.set_warm_start(*builtin_pair)
            engine.solve()
        print(f"seed {seed}: {args.steps} steps timed", flush=True)
    if not rows:
        raise SystemExit("lab admission: no timed step had contact points")

    ms = {p: np.array([r[p] for r in rows]) * 1e3 for p in PARTS}
    summary = {p: {"median_ms": float(np.median(ms[p])), "p90_ms": float(np.percentile(ms[p], 90)),
                   "median_ratio_to_box2d_solve": float(np.median(ms[p] / ms["box2d_solve"]))} for p in PARTS}
    points = [r["contact_points"] for r in rows]
    print(f"\n{len(rows)} steps, {min(points)}-{max(points)} contact points (seeds {args.seeds}, after {args.settle} steps)\n")
    print("| part | median ms | p90 ms | / Box2D's solve (median) |")
    print("|---|---|---|---|")
    for p in PARTS:
        s = summary[p]
        print(f"| {p.replace('_', ' ')} | {s['median_ms']:.2f} | {s['p90_ms']:.2f} | {s['median_ratio_to_box2d_solve']:.1f} |")
    if args.json:
        write_json_atomic(args.json, {"seeds": args.seeds, "settle": args.settle, "steps": args.steps,
                                      "summary": summary, "per_step": rows,
                                      "machine": {"python": platform.python_version(), "numpy": np.__version__,
                                                  "processor": platform.processor() or platform.machine()}})
        print(f"wrote {args.json}")
    return 0

