"""`deepcontact bench engine`: what the patched engine's new paths cost.

On a settled thesis world (100 bodies, ~180 contact points) it times, as
medians over many repeats:
  * export of bodies and contact points to NumPy (one call each), against the
    plain Python loop over SWIG objects that the thesis's approach needs;
  * injection of an external warm start;
  * the solve with statistics on against plain Step at the same iteration
    count (statistics off runs upstream's loop), interleaved step by step on
    two identical worlds so machine noise hits both alike.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np

from deepcontact.io import write_json_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")
    parser.add_argument("--seed", type=int, default=900, help="thesis-world seed (benchmark range 900-999; default 900)")
    parser.add_argument("--settle-steps", type=int, default=200, help="steps before measuring, so the pile has settled (default 200)")
    parser.add_argument("--repeats", type=int, default=2000, help="repeats of export and injection (default 2000)")
    parser.add_argument("--solve-steps", type=int, default=200, help="steps timed for the solve comparison (default 200)")
    parser.add_argument("--iterations", type=int, default=200, help="fixed velocity iterations for the solve comparison (default 200)")


def _median_us(fn, repeats: int) -> tuple[float, float]:
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn()
        samples.append(time.perf_counter_ns() - t0)
    samples.sort()
    return samples[len(samples) // 2] / 1e3, samples[int(len(samples) * 0.9)] / 1e3


def _swig_loop_export(world) -> tuple[np.ndarray, np.ndarray]:
    """What reading a step costs without the patch: walk the SWIG objects."""
    bodies = [(b.position[0], b.position[1], b.angle, b.linearVelocity[0], b.linearVelocity[1],
               b.angularVelocity, b.mass) for b in world.bodies]
    points = []
    for c in world.contacts:
        if not c.touching:
            continue
        wm = c.worldManifold
        m = c.manifold
        for j in range(m.pointCount):
            p = m.points[j]
            points.append((wm.points[j][0], wm.points[j][1], wm.normal[0], wm.normal[1],
                           p.normalImpulse, p.tangentImpulse))
    return np.asarray(bodies, np.float32), np.asarray(points, np.float32)


def _settled(seed: int, steps: int, **solver):
    from simclient.scene import SceneSpec, settled_world

    return settled_world(SceneSpec.thesis(), seed, steps, **solver)


def run(args: argparse.Namespace) -> int:
    engine = _settled(args.seed, args.settle_steps)
    n = engine.collide()
    results: dict = {"seed": args.seed, "settle_steps": args.settle_steps, "contact_points": n,
                     "bodies": engine.world.bodyCount}

    export_med, export_p90 = _median_us(lambda: (engine.bodies(), engine.contacts()), args.repeats)
    loop_med, loop_p90 = _median_us(lambda: _swig_loop_export(engine.world), max(50, args.repeats // 20))
    normal = np.ascontiguousarray(engine.contacts()["builtin"][:, 0])
    tangent = np.ascontiguousarray(engine.contacts()["builtin"][:, 1])
    inject_med, inject_p90 = _median_us(lambda: engine.set_warm_start(normal, tangent), args.repeats)
    engine.solve()
    results["export_us"] = {"median": export_med, "p90": export_p90}
    results["swig_loop_export_us"] = {"median": loop_med, "p90": loop_p90}
    results["inject_us"] = {"median": inject_med, "p90": inject_p90}

    # Two identical worlds, same fixed iteration count; only the loop differs.
    fixed = dict(velocity_iterations=args.iterations, velocity_threshold=-1.0)
    plain = _settled(args.seed, args.settle_steps, statistics=False, **fixed)
    tracked = _settled(args.seed, args.settle_steps, statistics=True, **fixed)
    plain_ms, tracked_ms, ratios = [], [], []
    for k in range(args.solve_steps):
        # Alternate which world goes first so cache warmth favours neither.
        if k % 2:
            sp, st = plain.step(), tracked.step()
        else:
            st, sp = tracked.step(), plain.step()
        if sp.velocity_iterations_sum != st.velocity_iterations_sum:
            print("bench engine: the two worlds diverged; the comparison is void", file=sys.stderr)
            return 1
        plain_ms.append(sp.solve_ms)
        tracked_ms.append(st.solve_ms)
        if sp.solve_ms > 0:
            ratios.append(st.solve_ms / sp.solve_ms)
    results["solve"] = {
        "velocity_iterations": args.iterations,
        "steps": args.solve_steps,
        "plain_step_ms_median": statistics.median(plain_ms),
        "instrumented_ms_median": statistics.median(tracked_ms),
        "ratio_of_medians": statistics.median(tracked_ms) / statistics.median(plain_ms),
        "median_of_ratios": statistics.median(ratios),
    }

    s = results["solve"]
    print(f"thesis world, seed {args.seed}, after {args.settle_steps} steps: "
          f"{results['bodies']} bodies, {n} contact points")
    print(f"  export (bodies + contacts)      median {export_med:8.1f} us   p90 {export_p90:8.1f} us")
    print(f"  same via SWIG objects (loop)    median {loop_med:8.1f} us   p90 {loop_p90:8.1f} us")
    print(f"  warm-start injection            median {inject_med:8.1f} us   p90 {inject_p90:8.1f} us")
    print(f"  solve, {args.iterations} iterations: plain Step {s['plain_step_ms_median']:.3f} ms, "
          f"with statistics {s['instrumented_ms_median']:.3f} ms "
          f"(ratio of medians {s['ratio_of_medians']:.3f}, median ratio {s['median_of_ratios']:.3f})")
    if args.json:
        write_json_atomic(args.json, results)
        print(f"wrote {args.json}")
    return 0
