"""`deepcontact lab spread`: how far a closed loop moves when nothing that matters changes.

    deepcontact lab spread --world simclient.zoo:ragdolls --seeds 901-920 --out OUT
    deepcontact lab spread --world examples/chain.py:build --seeds 901-920 --warm-starts server:default --out OUT

A closed-loop ratio to Builtin compares two trajectories. Where a world is chaotic (a pile that
can topple either way, ragdolls falling on each other), a change far below anything the solver
can see sends the run along another trajectory, and the sweeps of the whole run change with it.
This runs Box2D's own warm start, and the same start with Gaussian noise of a few sizes far
below the stopping tolerance added at its persisting points (the lab's `jitter@SIGMA`, one draw
a size: each a different trajectory of the same physics), on the same seeds, and prints each
draw's ratio to Builtin with its 95 % bootstrap interval over seeds: the closed loop's own
spread, the ratios a warm start that changes nothing would show. Other warm starts
(`--warm-starts`) are given two ratios: to Builtin's run, as `bench iterations` prints it, and to
Builtin's expectation over its draws (each seed's steps pooled over Builtin and every draw), the
reference without the luck of one trajectory. That second ratio is for warm starts that part
from Builtin's trajectory from their first steps (a model served without the guard): one that
follows it (the guard serving Box2D's start) repeats Builtin's own draw, and against the
expectation shows only how lucky that draw was.

Ratios are over the steps with contacts (the thesis's measure, `bench iterations`' mean) and over
every step of the runs (the solver's whole work); the world's flags, seeds, server and guard are
`bench iterations`' own.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from bench import iterations
from bench.stats import Ratio, ratio_interval
from deepcontact.io import write_bytes_atomic, write_json_atomic

#: Noise sizes, N s: a hundred to a hundred thousand times below the thesis's stopping tolerance
#: (1e-4 N s), so that no draw is a warm start of its own, only another trajectory.
DEFAULT_DRAWS = "1e-9,1e-8,1e-7,3e-7,1e-6"
MEASURES = ("contact steps", "every step")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    iterations.add_arguments(parser, warm_starts="",
                             warm_starts_note="warm starts measured beside Builtin's draws, comma-separated "
                                              "(default: none, the draws alone)")
    parser.add_argument("--draws", default=DEFAULT_DRAWS,
                        help="the noise sizes of Box2D's perturbed draws, N s, comma-separated (default "
                             f"{DEFAULT_DRAWS}: far below the stopping tolerance; each size one trajectory)")


def draw_names(draws: str) -> list[str]:
    """The jitter@SIGMA warm starts of --draws; ValueError for a size that is not a positive number."""
    names = []
    for text in (d.strip() for d in draws.split(",") if d.strip()):
        try:
            sigma = float(text)
        except ValueError:
            raise ValueError(f"--draws takes noise sizes in N s, got {text!r}") from None
        if not (np.isfinite(sigma) and sigma > 0):
            raise ValueError(f"--draws takes positive noise sizes in N s, got {text!r}")
        names.append(f"jitter@{text}")
    if not names:
        raise ValueError("--draws names no noise size")
    return names


def pooled(per_draw: list[list[np.ndarray]]) -> list[np.ndarray]:
    """Each seed's steps of every draw in one array: per_draw[d][s] (steps,) iterations of draw d
    on seed s -> [s] (steps of all draws,). Its mean is the seeds' mean over the draws (every
    draw has the seed's steps where they are counted the same way)."""
    return [np.concatenate([draw[s] for draw in per_draw]) for s in range(len(per_draw[0]))]


def spread(runs: dict[str, list[dict]], draws: list[str]) -> dict:
    """{"draws": {name: {measure: Ratio}}, "others": {name: {measure: {"builtin": Ratio,
    "expected": Ratio}}}} of runs ({warm start: [run per seed]}, builtin and every draw among
    them); measures: MEASURES."""
    measure = {"contact steps": iterations.contact_step_iterations, "every step": iterations.every_step_iterations}
    out: dict = {"draws": {}, "others": {}}
    for m, of in measure.items():
        builtin = [of(r) for r in runs["builtin"]]
        expected = pooled([builtin] + [[of(r) for r in runs[d]] for d in draws])
        for name in draws:
            out["draws"].setdefault(name, {})[m] = ratio_interval([of(r) for r in runs[name]], builtin)
        for name in (n for n in runs if n != "builtin" and n not in draws):
            its = [of(r) for r in runs[name]]
            out["others"].setdefault(name, {})[m] = {"builtin": ratio_interval(its, builtin),
                                                     "expected": ratio_interval(its, expected)}
    return out


def table(result: dict, seeds: str, world: str) -> str:
    """The markdown the command prints: the draws, their range, and the other warm starts."""
    lines = [f"{world}, seeds {seeds}: Builtin's closed loop against itself perturbed far below the "
             "tolerance, and other warm starts against Builtin's run and Builtin's expectation over the draws.",
             "", "| warm start | / builtin (contact steps) | / builtin (every step) |", "|---|---|---|"]
    for name, by in result["draws"].items():
        lines.append(f"| {name} | {by['contact steps'].text()} | {by['every step'].text()} |")
    for m in MEASURES:
        values = [by[m].value for by in result["draws"].values() if by[m].value is not None]
        if values:
            lines.append(f"- the draws' spread over {m}: {min(values):.3f} to {max(values):.3f}")
    if result["others"]:
        lines += ["", "| warm start | / builtin (contact steps) | / Builtin's expectation (contact steps) | "
                  "/ builtin (every step) | / Builtin's expectation (every step) |", "|---|---|---|---|---|"]
        for name, by in result["others"].items():
            cs, ev = by["contact steps"], by["every step"]
            lines.append(f"| {name} | {cs['builtin'].text()} | {cs['expected'].text()} | {ev['builtin'].text()} | "
                         f"{ev['expected'].text()} |")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    prog = "deepcontact lab spread"
    try:
        draws = draw_names(args.draws)
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    others = [w.strip() for w in args.warm_starts.split(",") if w.strip() and w.strip() != "builtin"]
    clash = sorted(set(others) & set(draws))
    if clash:
        print(f"{prog}: {', '.join(clash)} is one of the draws; give it in --draws only", file=sys.stderr)
        return 2
    collected = iterations.collect_runs(args, ["builtin", *draws, *others])
    if isinstance(collected, int):
        return collected
    spec, seeds, runs = collected
    result = spread(runs, draws)
    world = getattr(spec, "source", None) or spec.name
    text = table(result, args.seeds, world)
    as_dict = {"world": world, "seeds": seeds, "draws": draws, "guard": not args.no_guard,
               "ratios": {group: {name: {m: (v.to_dict() if isinstance(v, Ratio) else
                                             {k: r.to_dict() for k, r in v.items()}) for m, v in by.items()}
                                  for name, by in result[group].items()} for group in ("draws", "others")}}
    write_json_atomic(args.out / "spread.json", as_dict)
    write_bytes_atomic(args.out / "spread.md", (text + "\n").encode())
    print(text)
    print(f"wrote {args.out}/spread.json and spread.md")
    return 0
