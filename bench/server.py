"""`deepcontact bench server`: what the server spends per step, by stage.

Starts `deepcontact serve` in its own process on loopback (in this process
the client's threads would hold the GIL inside the server's timings),
records steps of a thesis world on a benchmark seed (bodies at collide time,
contact points with their builtin warm start), streams them in lockstep through one
bidirectional stream (simclient.client) and reports medians of the server's stage timings
(decode; then those the model runs: p2g, inference, g2p for a grid model; features, inference,
g2p for a graph model; features, inference, solve, admit for the face route; total) and of
the client's round trip. The
headline is the server's time outside inference, total - inference (issue 6's
target: 300 us at the median). `decode` starts when gRPC begins parsing the
request (server.service._parse_step), so it includes parsing and gRPC's
hand-off to the handler; `total` ends when the reply is built.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from deepcontact import wire
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import unknown_model
from simclient.client import WarmStartClient

#: The reply's stage timings (Timings NAME_us), in the order a step runs them.
STAGES = ("decode", "p2g", "features", "inference", "g2p", "solve", "admit", "total")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")
    parser.add_argument("--model", default="default",
                        help="model to time (default: default, the model users are served; pressure is round 1's)")
    parser.add_argument("--seed", type=int, default=900, help="thesis-world seed (default 900)")
    parser.add_argument("--steps", type=int, default=250, help="steps recorded and sent (default 250)")
    parser.add_argument("--rounds", type=int, default=4, help="times the recorded steps are streamed (default 4)")
    parser.add_argument("--intra-op-threads", type=int, default=1,
                        help="the server's ONNX Runtime threads per inference (default 1, serve's default)")
    parser.add_argument("--bind", default="127.0.0.1:0",
                        help="where the server listens (default %(default)s, a free loopback port; unix:PATH "
                             "for a Unix socket)")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def record_steps(seed: int, steps: int):
    """[(bodies, points, friction)] of a thesis world: what a client sends each step;
    friction: (P,) float32, each point's friction coefficient (point_friction)."""
    from simclient.provider import point_friction
    from simclient.scene import SceneSpec, build_world

    engine = build_world(SceneSpec.thesis(), seed)
    mu = engine.body_friction()
    out = []
    for _ in range(steps):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        out.append((bodies, points, point_friction(mu, points).astype(np.float32)))
        engine.solve()
    return out


def time_steps(address: str, world, model: str, recorded, rounds: int) -> tuple[dict[str, list], list[float]]:
    """Send every recorded step `rounds` times; the first round warms up and is not kept.

    recorded: [(bodies, points, friction)] as record_steps gives them. Returns the server's
    stage timings per step (us; "outside_inference" is total - inference) and the
    client's round trips (s).
    """
    stages = {k: [] for k in (*STAGES, "outside_inference")}
    round_trip = []
    with WarmStartClient(address, world=world) as client:
        for r in range(rounds):
            for k, (bodies, points, friction) in enumerate(recorded):  # one request per step: what is timed
                msg = wire.encode_step(k, model, bodies, points, builtin=points["builtin"], friction=friction)
                t0 = time.perf_counter()
                reply = client.step(msg, timeout=10.0)
                rt = time.perf_counter() - t0
                if r == 0:
                    continue
                round_trip.append(rt)
                t = reply.timings
                for name in STAGES:
                    stages[name].append(getattr(t, f"{name}_us"))
                stages["outside_inference"].append(t.total_us - t.inference_us)
    return stages, round_trip


def run(args: argparse.Namespace) -> int:
    from server.process import ServerProcess
    from simclient.client import StepFailed
    from simclient.scene import SceneSpec

    if args.steps < 1 or args.rounds < 2:
        print("deepcontact bench server: --steps must be >= 1 and --rounds >= 2 (the first round warms up)",
              file=sys.stderr)
        return 2
    recorded = [s for s in record_steps(args.seed, args.steps) if len(s[1]) > 0]
    if not recorded:
        print(f"deepcontact bench server: no steps with contacts in the first {args.steps} steps of seed "
              f"{args.seed} (bodies still falling); give more --steps", file=sys.stderr)
        return 2
    try:
        server = ServerProcess(args.models, "--intra-op-threads", str(args.intra_op_threads), bind=args.bind).start()
    except (RuntimeError, TimeoutError) as exc:
        print(f"deepcontact bench server: {exc}", file=sys.stderr)
        return 2
    with WarmStartClient(server.address) as probe:
        names = [m.name for m in probe.list_models()]
    if args.model not in names:
        print(f"deepcontact bench server: {args.models}: {unknown_model(args.model, names)}",
              file=sys.stderr)
        server.stop()
        return 2
    thesis = SceneSpec.thesis()  # the worlds these steps come from
    world = wire.encode_world(*thesis.domain, thesis.walls(), thesis.physics, thesis.solver.stopping_tolerance)
    try:
        stages, round_trip = time_steps(server.address, world, args.model, recorded, args.rounds)
    except StepFailed as exc:
        print(f"deepcontact bench server: a step failed: {exc}", file=sys.stderr)
        return 1
    finally:
        server.stop()
    n_points = [len(p) for _, p, _ in recorded]
    result = {
        "model": args.model, "seed": args.seed, "steps": len(recorded), "rounds": args.rounds,
        "intra_op_threads": args.intra_op_threads, "bind": args.bind,
        "median_contact_points": statistics.median(n_points),
        "server_us_median": {k: statistics.median(v) for k, v in stages.items()},
        "server_us_p90": {k: float(np.percentile(v, 90)) for k, v in stages.items()},
        "round_trip_ms_median": 1e3 * statistics.median(round_trip),
        "round_trip_ms_p99": 1e3 * float(np.percentile(round_trip, 99)),
    }
    med = result["server_us_median"]
    print(f"{args.model} on thesis seed {args.seed}: {len(recorded)} steps with contacts "
          f"(median {result['median_contact_points']:.0f} points), {args.rounds - 1} timed rounds")
    # The stages this model runs: a stage it has not (a grid model's solve) reads 0 at every step.
    ran = [k for k in STAGES if k in ("decode", "inference", "total") or any(stages[k])]
    print("  server stage medians (us): " + ", ".join(f"{k} {med[k]:.0f}" for k in ran))
    print(f"  outside inference (total - inference): median {med['outside_inference']:.0f} us, "
          f"p90 {result['server_us_p90']['outside_inference']:.0f} us")
    print(f"  client round trip: median {result['round_trip_ms_median']:.3f} ms, p99 {result['round_trip_ms_p99']:.3f} ms")
    if args.json:
        write_json_atomic(args.json, result)
    return 0
