"""`deepcontact demo` (and `make demo`): the main job in one command.

Starts `deepcontact serve` with the shipped models on a Unix socket of its own, waits for its
health check, runs the thesis world on a held-out seed with no warm start, Box2D's own, the
thesis's kind of model (`pressure`) and the shipped `default` (without the guard, and as it
is shipped, with it), and prints one table:

    warm start | mean iterations | / builtin | p50 latency ms | learned route

(`/ builtin` below 1: fewer solver iterations a step than Box2D's own warm start; `learned
route`: the share of steps with contacts on which the model's own answer was the solver's
start, not a fallback's, Box2D's on a late reply or the guard's choice). The detailed
analyses (every figure of `bench iterations`, the per-warm-start statistics, each run's
fallbacks) go to the output folder, and are printed too with --detail. The server is
stopped whatever happens.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench import iterations
from deepcontact.io import write_json_atomic

#: (row, warm start, guard): what the demo runs, in its table's order.
ROWS = (
    ("none", "none", False),  # no warm start
    ("builtin", "builtin", False),  # Box2D's own
    ("server:pressure, guard off", "server:pressure", False),  # the thesis's kind of model, served blind
    ("server:default, guard off", "server:default", False),
    ("server:default", "server:default", True),  # as shipped: the guard on
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=901, help="held-out thesis seed (default 901)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")
    parser.add_argument("--out", type=Path, default=Path("demo-results"),
                        help="folder for the detailed tables and the figures (default demo-results/)")
    parser.add_argument("--detail", action="store_true", help="also print the detailed tables")


def run(args: argparse.Namespace) -> int:
    missing = [m for m in ("pressure", "default") if not (args.models / f"{m}.json").exists()]
    if missing:
        print(f"deepcontact demo: no model card {', '.join(missing)} in {args.models}/ "
              "(`make default-model` rebuilds the shipped models)", file=sys.stderr)
        return 2
    from server.process import ServerProcess
    from simclient.scene import SceneSpec

    spec = SceneSpec.thesis()
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"deepcontact demo: the thesis world, seed {args.seed}, {spec.steps} steps; a server on the shipped "
          f"models ({args.models}/) on a Unix socket of its own", file=sys.stderr)
    runs: dict[str, list[dict]] = {}
    try:
        with ServerProcess(args.models, log=args.out / "server.log", local_socket=True) as server:
            for label, name, guard in ROWS:
                runs[label] = iterations.simulate_all(spec, [name], [args.seed], target=server.address,
                                                      deadline_ms=iterations.DEFAULT_DEADLINE_MS,
                                                      guard=guard)[name]
                print(f"  {label}: done", file=sys.stderr)
    except (RuntimeError, TimeoutError, OSError) as exc:
        print(f"deepcontact demo: {exc}", file=sys.stderr)
        return 1
    table = summary_table(runs)
    detail = _write_details(args.out, runs, spec, args.seed)
    print(table)
    if args.detail:
        print(detail)
    print(f"detailed tables and figures in {args.out}/ (details.md, summary.json, fig20_contacts_iterations.png, "
          "fig21_convergence.png, fig26_mse.png)")
    return 0


def learned_share(summary: dict) -> float | None:
    """Of a server warm start's steps with contacts, the share its model's own answer started:
    not a fallback (a late reply, no server), not another card's (served_by), not the guard's
    choice of Box2D's start. None for a warm start that asks no server."""
    if not summary.get("p50_latency_ms") or not summary["steps_with_contacts"]:
        return None
    return summary["learned_route_steps"] / summary["steps_with_contacts"]


def summary_table(runs: dict[str, list[dict]]) -> str:
    """The demo's one table, from one run per row."""
    summaries = {label: iterations.pooled_summary(r) for label, r in runs.items()}
    base = summaries["builtin"]["mean_velocity_iterations"]
    lines = ["| warm start | mean iterations | / builtin | p50 latency ms | learned route |", "|---|---|---|---|---|"]
    for label, s in summaries.items():
        mean, lat, share = s["mean_velocity_iterations"], s["p50_latency_ms"], learned_share(s)
        lines.append(f"| {label} | {mean:.1f} | {mean / base:.3f} | " + (f"{lat:.2f}" if lat else "–") + " | "
                     + (f"{share:.0%}" if share is not None else "–") + " |")
    lines += ["", "Velocity iterations a step over the steps with contacts; / builtin below 1: fewer than Box2D's own "
                  "warm start. One seed is one draw: docs/results.md has 50."]
    return "\n".join(lines)


def _write_details(out: Path, runs: dict[str, list[dict]], spec, seed: int) -> str:
    """details.md (bench iterations' table, the guard's line, the fallbacks by reason), summary.json and
    the figures in `out`; returns the tables."""
    summaries = {label: iterations.pooled_summary(r) for label, r in runs.items()}
    text = (iterations.markdown_table(summaries, [seed], spec.name, iterations.ratios_to_builtin(runs))
            + iterations.guard_note(summaries, runs) + iterations.served_by_note(summaries))
    reasons = [f"- {label}: " + ", ".join(f"{n} {why}" for why, n in sorted(s["fallbacks_by_reason"].items()))
               for label, s in summaries.items() if s["fallbacks_by_reason"]]
    if reasons:
        text += "\nFallbacks to Box2D's start, by reason:\n" + "\n".join(reasons) + "\n"
    tmp = out / ".details.md.part"
    tmp.write_text(text)
    tmp.replace(out / "details.md")
    write_json_atomic(out / "summary.json", {"seed": seed, "scene": spec.name, "warm_starts": summaries})
    iterations.plot_figures(runs, spec.solver.velocity_iterations, spec.solver.velocity_threshold, out)
    return text
