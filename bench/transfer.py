"""`deepcontact bench transfer`: what the particle/grid transfer costs per step.

On a settled thesis world (100 bodies, ~170 contact points, 61 x 61 grid at
0.25 m, poly6 with h = 0.5 m) it times, as medians and 90th percentiles over
many repeats:
  * P2G of the CNN input: bodies (mass, vx, vy, omega) and contact points
    (normal_x, normal_y) into a 61 x 61 x 6 grid (`world_to_grids`), the
    server's per-step input transfer; target 150 us;
  * SPH G2P of a 61 x 61 x 2 impulse grid back to the contact points (`g2p`),
    the server's per-step output transfer; target 100 us;
  * for reference, P2G of the two target channels and bilinear G2P.
"""

from __future__ import annotations

import argparse
import gc
import platform
import time

import numpy as np
import scipy

from deepcontact.io import write_json_atomic

TARGETS_US = {"p2g_inputs": 150.0, "g2p_sph": 100.0}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")
    parser.add_argument("--repeats", type=int, default=2000, help="timed repeats of each transfer (default 2000)")
    parser.add_argument("--seed", type=int, default=900, help="thesis-world seed (benchmark range 900-999; default 900)")
    parser.add_argument(
        "--settle-steps", type=int, default=200, help="steps before measuring, so the pile has settled (default 200)"
    )


def _time_us(fn, repeats: int) -> dict[str, float]:
    """Median and 90th percentile of `repeats` timed calls, in microseconds."""
    for _ in range(max(10, repeats // 20)):  # warm caches and the stencil cache
        fn()
    samples = np.empty(repeats)
    gc_was_enabled = gc.isenabled()
    gc.disable()  # a collection inside one sample says nothing about the transfer
    try:
        for i in range(repeats):
            t0 = time.perf_counter_ns()
            fn()
            samples[i] = time.perf_counter_ns() - t0
    finally:
        if gc_was_enabled:
            gc.enable()
    return {"median": float(np.median(samples)) / 1e3, "p90": float(np.percentile(samples, 90)) / 1e3}


def run(args: argparse.Namespace) -> int:
    if args.repeats < 1:
        raise SystemExit("bench transfer: --repeats must be at least 1")
    from deepcontact import features, transfer
    from deepcontact.gridspec import GridSpec
    from simclient.scene import SceneSpec, settled_world

    scene = SceneSpec.thesis()
    engine = settled_world(scene, args.seed, args.settle_steps)
    engine.collide()
    engine.solve()
    bodies, contacts = engine.bodies(), engine.contacts()
    points = np.ascontiguousarray(contacts["point"])
    spec = GridSpec.for_domain(*scene.domain, resolution=0.25, h=0.5)

    inputs, reports = features.world_to_grids(bodies, contacts, spec, return_report=True)
    target = features.targets_to_grids(contacts, spec)
    _, g2p_report = transfer.g2p(target, points, spec)
    timings = {
        "p2g_inputs": _time_us(lambda: features.world_to_grids(bodies, contacts, spec), args.repeats),
        "g2p_sph": _time_us(lambda: transfer.g2p(target, points, spec), args.repeats),
        "p2g_targets": _time_us(lambda: features.targets_to_grids(contacts, spec), args.repeats),
        "g2p_bilinear": _time_us(lambda: transfer.g2p(target, points, spec, method="bilinear"), args.repeats),
    }

    results = {
        "seed": args.seed,
        "settle_steps": args.settle_steps,
        "repeats": args.repeats,
        "bodies": reports["bodies"].n_particles,
        "contact_points": reports["contacts"].n_particles,
        "lost": {"bodies": reports["bodies"].n_lost, "contacts": reports["contacts"].n_lost, "g2p": g2p_report.n_lost},
        "grid": spec.to_dict(),
        "input_shape": list(inputs.shape),
        "target_shape": list(target.shape),
        "timings_us": timings,
        "targets_us": TARGETS_US,
        "meets_targets": {k: timings[k]["median"] <= v for k, v in TARGETS_US.items()},
        "machine": {
            "python": platform.python_version(),
            "numpy": np.__version__,
            "scipy": scipy.__version__,
            "processor": platform.processor() or platform.machine(),
        },
    }

    _print_table(results, spec)
    if args.json:
        write_json_atomic(args.json, results)
        print(f"wrote {args.json}")
    return 0


def _print_table(results: dict, spec) -> None:
    """The timings of `results` (as run() builds them), one line per transfer."""
    print(
        f"thesis world, seed {results['seed']}, after {results['settle_steps']} steps: {results['bodies']} bodies, "
        f"{results['contact_points']} contact points; grid {spec.ny} x {spec.nx}, {spec.kernel}, h = {spec.h} m"
    )
    shape_in, shape_out = "x".join(map(str, results["input_shape"])), "x".join(map(str, results["target_shape"]))
    labels = {
        "p2g_inputs": f"P2G inputs    -> {shape_in}",
        "g2p_sph": f"G2P SPH       <- {shape_out}",
        "p2g_targets": f"P2G targets   -> {shape_out}",
        "g2p_bilinear": f"G2P bilinear  <- {shape_out}",
    }
    for key, label in labels.items():
        t = results["timings_us"][key]
        goal = ""
        if key in TARGETS_US:
            goal = f"   (target {TARGETS_US[key]:.0f} us: {'met' if results['meets_targets'][key] else 'MISSED'})"
        print(f"  {label:26s} median {t['median']:8.1f} us   p90 {t['p90']:8.1f} us{goal}")
