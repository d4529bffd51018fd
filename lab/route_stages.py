"""`deepcontact lab route-stages`: where a served model's step goes, on any world, by its size.

    deepcontact lab route-stages --world examples/pyramid.py:build --seed 850 --steps 120

`deepcontact bench server` times the server's stages on the thesis world's steps; a user's world
can hold steps five times larger, where one stage may outgrow the 10 ms deadline alone. This runs
the model in the simulation's process (bench.inprocess.InProcess: the predictor the server
loads, no gRPC) along its own trajectory of one seed and prints each stage's median time (ms)
over every step with points and over the steps of at least --large points; then, of the
compiled route's solves (deepcontact.faces.route_compiled), how many ran in the bodies' space
(no point slides) and how many by the dual, and each way's median solve time. With
--deadline-ms each step is due what the server leaves a request of that budget (less its
margin, server.service.DEADLINE_MARGIN_S), so a face route answers as it would served (fewer
admission rounds, held labels, Box2D's start where it would not end in time), and what answered
each step is counted.

    deepcontact lab route-stages --world simclient.zoo:pyramid --seed 850 --deadline-ms 10
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", default="examples/pyramid.py:build", metavar="PATH.py:FUNCTION",
                        help="a world of your own, FUNCTION(seed) in PATH.py or MODULE:FUNCTION "
                             "(default examples/pyramid.py:build, Box2D's Pyramid)")
    parser.add_argument("--seed", type=int, default=850, help="the world's seed (default 850, a choosing seed)")
    parser.add_argument("--steps", type=int, default=120, help="steps simulated (default 120)")
    parser.add_argument("--models", default="models", metavar="DIR", help="model folder (default models/)")
    parser.add_argument("--model", default="default", help="the model to time (default: default)")
    parser.add_argument("--large", type=int, default=500, metavar="P",
                        help="the steps of at least P points are also summarized alone (default 500)")
    parser.add_argument("--deadline-ms", type=float, default=None, metavar="MS",
                        help="give each step what the server leaves a request of this budget (less "
                             "server.service.DEADLINE_MARGIN_S) and count what answered each step "
                             "(default: no deadline, every step answered in full)")


def stage_medians(sizes: np.ndarray, stages: list[dict[str, float]], large: int) -> dict[str, tuple[float, float]]:
    """{stage: (median ms over every step, median ms over steps of >= large points, NaN where
    none)}, with "total" their sum a step. sizes: (S,) points a step; stages: S dicts of s."""
    names = sorted({k for s in stages for k in s})
    table = {k: np.array([s.get(k, 0.0) for s in stages]) * 1e3 for k in names}
    table["total"] = sum(table.values()) if names else np.zeros(len(stages))
    big = sizes >= large
    return {k: (float(np.median(v)), float(np.median(v[big])) if big.any() else float("nan")) for k, v in table.items()}


def solve_ways(solves: list[tuple[int, float, bool]], large: int) -> dict[str, tuple[int, int, float, float]]:
    """{"bodies" | "dual": (solves, solves of >= large points, median solve ms, median ms over the
    large ones; NaN where none)}. solves: (points, solve seconds, in the bodies' space) each."""
    out = {}
    for way, flag in (("bodies", True), ("dual", False)):
        rows = [(n, s) for n, s, b in solves if b == flag]
        ms = np.array([s for _, s in rows]) * 1e3
        big = np.array([n >= large for n, _ in rows], bool)
        out[way] = (len(rows), int(big.sum()), float(np.median(ms)) if len(ms) else float("nan"),
                    float(np.median(ms[big])) if big.any() else float("nan"))
    return out


def answered_by(sizes: np.ndarray, served_by: list, large: int) -> dict[str, tuple[int, int]]:
    """{what answered: (steps, steps of >= large points)}; served_by: per step, None where the
    model's own answer was served (named "the model")."""
    out: dict[str, tuple[int, int]] = {}
    for n, who in zip(sizes, served_by):
        every, big = out.get(who or "the model", (0, 0))
        out[who or "the model"] = (every + 1, big + int(n >= large))
    return dict(sorted(out.items(), key=lambda kv: -kv[1][0]))


def run(args: argparse.Namespace) -> int:
    import server.face_route
    from bench.inprocess import InProcess
    from server.service import DEADLINE_MARGIN_S
    from simclient.simulate import run_simulation
    from simclient.worlds import WorldSpec

    try:
        if args.steps < 1 or args.large < 1:
            raise ValueError(f"--steps and --large must be >= 1, got {args.steps} and {args.large}")
        if args.deadline_ms is not None and not args.deadline_ms > 1e3 * DEADLINE_MARGIN_S:
            raise ValueError(f"--deadline-ms must exceed the server's margin of {1e3 * DEADLINE_MARGIN_S:g} ms, "
                             f"got {args.deadline_ms:g}")
        spec = WorldSpec(args.world, steps=args.steps)
        spec.validate()
        provider = InProcess.load(Path(args.models), args.model, spec)
        if args.deadline_ms is not None:
            provider.budget_ms = args.deadline_ms - 1e3 * DEADLINE_MARGIN_S
    except (ValueError, FileNotFoundError) as exc:
        print(f"deepcontact lab route-stages: {exc}", file=sys.stderr)
        return 2
    sizes: list[int] = []  # points of each step the model answered, beside provider.stages

    class Sized(type(provider)):
        def warm_start(self, engine, bodies, points, step):
            if len(points):
                sizes.append(len(points))
            return super().warm_start(engine, bodies, points, step)

    provider.__class__ = Sized
    solves: list[tuple[int, float, bool]] = []  # each compiled route's (points, solve s, in the bodies' space)
    compiled = server.face_route.route_compiled

    def recorded(bodies, points, *rest, **named):
        answer = compiled(bodies, points, *rest, **named)
        if answer is not None:
            solves.append((len(points), answer.solve_seconds, answer.in_bodies))
        return answer

    server.face_route.route_compiled = recorded  # the route's own call, read on its way back
    try:
        run_simulation(spec, args.seed, provider)
    finally:
        server.face_route.route_compiled = compiled
    n = np.array(sizes)
    if len(n) == 0:
        print(f"deepcontact lab route-stages: no step of {args.world} seed {args.seed} had contact points",
              file=sys.stderr)
        return 1
    medians = stage_medians(n, provider.stages, args.large)
    big = int((n >= args.large).sum())
    budget = "" if args.deadline_ms is None else \
        f", each step due {args.deadline_ms - 1e3 * DEADLINE_MARGIN_S:g} ms after its call (a {args.deadline_ms:g} ms request's)"
    print(f"`{args.world}` seed {args.seed}, {args.model} in process{budget}: {len(n)} steps with points (median "
          f"{int(np.median(n))}), {big} of at least {args.large} (median {int(np.median(n[n >= args.large])) if big else 0})")
    print(f"| stage | median ms, every step | median ms, {args.large} points and more |\n|---|---|---|")
    for name, (every, large) in medians.items():
        print(f"| {name} | {every:.2f} | {large:.2f} |")
    if args.deadline_ms is not None:
        print(f"\n| answered by | steps | of at least {args.large} points |\n|---|---|---|")
        for who, (every, large) in answered_by(n, provider.served_by, args.large).items():
            print(f"| {who} | {every} | {large} |")
    if solves:
        print(f"\nThe compiled route's {len(solves)} solves: in the bodies' space where it answers (deepcontact/face_kernels.h, face_body_solve), elsewhere by the dual.")
        print(f"| way | solves | of at least {args.large} points | median solve ms | median ms, {args.large} points and more |"
              "\n|---|---|---|---|---|")
        for way, (count, big_count, every, large) in solve_ways(solves, args.large).items():
            print(f"| {way} | {count} | {big_count} | {every:.2f} | {large:.2f} |")
    return 0
