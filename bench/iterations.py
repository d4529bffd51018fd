"""`deepcontact bench iterations`: every warm start on the same held-out worlds.

    deepcontact bench iterations --seeds 901-910 \\
        --warm-starts none,builtin,copy,copy2,copy0,extrapolate,server:random,server:bad,server:grid-identity,server:pressure \\
        --out bench/results/iterations

Runs each warm start on each seed (benchmark seeds: never used in training),
starting `deepcontact serve --models MODELS` itself when a `server:` warm start
is listed and no `--server` is given. One task per (warm start, seed)
simulation: in this process one after the other (the default), on
`--workers N` processes, or on Ray (`--ray [ADDRESS]`, deepcontact.dispatch);
a `server:` task opens its own stream to the server. Results are gathered in
(warm start, seed) order, so the iteration figures are the same on every
backend (latencies are not). Every ratio to builtin (mean, median and 90th
percentile of the iterations per step) comes with its 95 % bootstrap interval
over seeds (bench.stats); a warm start beats builtin where the whole interval
lies below 1. Writes DIR/summary.json ({"warm_starts": {NAME: summary},
"ratios_to_builtin": ..., "per_seed_mean_iterations": ...}), DIR/results.md
(the table) and the thesis's figures as PNG (builtin black, other baselines
grey and dashed, learned models coloured):
    fig20_contacts_iterations.png   contacts and iterations per step (Fig. 20)
    fig21_convergence.png           steps still iterating after k iterations,
                                    and the median residual per iteration (Fig. 21-25)
    fig26_mse.png                   warm-start MSE per step, normal and tangent (Fig. 26, 28)
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from bench.figures import save_figure
from bench.stats import STATS, Ratio, ratio_interval
from deepcontact import dispatch, tls
from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic
from simclient import seeds as seed_ranges
from simclient import warmstarts, worlds
from simclient.guard import Guard
from simclient.simulate import DEFAULT_DEADLINE_MS, run_simulation, tls_files
from simclient.stepping import StepRecord, summarize
from simclient.warmstarts import composite_parts, make_provider

DEFAULT_WARM_STARTS = ("none,builtin,copy,copy2,copy0,extrapolate,"
                       "server:random,server:bad,server:grid-identity,server:pressure")
# Summary fields that are wall-clock measurements: the only ones that differ between runs.
TIMING_FIELDS = ("p50_latency_ms", "p99_latency_ms", "median_client_us", "total_solve_ms", "guard_trial_ms")


def add_arguments(parser: argparse.ArgumentParser, warm_starts: str = DEFAULT_WARM_STARTS,
                  warm_starts_note: str | None = None) -> None:
    """The command's flags; warm_starts: --warm-starts' default, warm_starts_note: its help's
    first words where another command gives the flag another meaning."""
    worlds.add_world_arguments(parser)
    parser.add_argument("--seeds", default="901-910", help="benchmark seeds (default 901-910)")
    parser.add_argument("--warm-starts", default=warm_starts, help=warm_starts_help(warm_starts_note))
    parser.add_argument("--server", metavar="HOST:PORT",
                        help="use this server instead of starting one (any gRPC target: dns:///name:port balances "
                             "over replicas, unix:PATH dials a Unix socket); server: warm starts with --ray ADDRESS need it, as the cluster's "
                             "workers cannot reach the one started here, on a Unix socket of this machine")
    add_models_argument(parser, "models for the server started here")
    tls.add_client_arguments(parser)
    parser.add_argument("--deadline-ms", type=float, default=DEFAULT_DEADLINE_MS,
                        help=f"per-step deadline for server replies (default {DEFAULT_DEADLINE_MS:g})")
    parser.add_argument("--no-guard", action="store_true",
                        help="serve each server: warm start's answer on every step; by default a guard serves it only "
                             "while it beats Box2D's own start on the simulation's steps (trial solves, under 5 %% "
                             "of Box2D's sweeps; docs/worlds.md)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    dispatch.add_arguments(parser, workers_default="1, this process")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def warm_starts_help(note: str | None = None) -> str:
    """--warm-starts' help: the names registered when the parser is built (simclient.warmstarts)."""
    text = (f"{note or f'comma-separated (default {DEFAULT_WARM_STARTS})'}; each one of {warmstarts.usage()}; "
            "server:* stands for every model the server serves")
    if any(r.composite for r in warmstarts.registered()):
        text += (" (in a composite too, e.g. price:server:*); a composite prints a same-state table of its trial "
                 "solves and one of the steps that end at the solver's cap (each start's sweeps to Builtin's "
                 "accuracy there)")
    return text


def _prog(args: argparse.Namespace) -> str:
    """How this command's messages name it: `deepcontact bench iterations` or the group that runs it."""
    return " ".join(("deepcontact", *getattr(args, "_words", ("bench", "iterations"))))


def _read_arguments(args: argparse.Namespace, names: list[str] | None = None):
    """(spec, seeds, names, providers) of the command line (names: these warm starts instead of
    --warm-starts), or ValueError saying what is wrong; warns on stderr of seeds that models
    were fitted or stopped on."""
    spec = worlds.spec_from_args(args)
    seeds = seed_ranges.parse_seeds(args.seeds)
    if isinstance(spec, worlds.WorldSpec):  # a function that raises or returns no world: said before any work
        worlds.build_user_world(spec.source, seeds[0])
    if names is None:
        names = [w.strip() for w in args.warm_starts.split(",") if w.strip()]
    providers = {name: make_provider(name) for name in names}
    dispatch.check_arguments(args)
    tls.client_credentials(*tls_files(args))  # unreadable or mismatched files: said before anything runs
    if args.server is None and any(tls_files(args)):
        raise ValueError("--tls-ca/--tls-cert/--tls-key dial a server of yours (--server); the one started here "
                         "serves plaintext on a Unix socket")
    if any(p.uses_server for p in providers.values()) and args.server is None and args.ray not in (None, "local"):
        raise ValueError("server: warm starts on a Ray cluster need --server, an address its workers can reach "
                         "(e.g. dns:///server:50051)")
    # Choosing seeds (850-899) are held out from training and meant for comparing variants: no warning.
    seen = [s for s in seeds if seed_ranges.describe(s) in ("training", "validation")]
    if seen:
        print(f"warning: seeds {seed_ranges.as_ranges(seen)} are training or validation seeds (1-849): models were "
              "fitted or stopped on them, so results there are not held out (choose on 850-899, report on 900-999)",
              file=sys.stderr)
    return spec, seeds, names, providers


def run(args: argparse.Namespace) -> int:
    collected = collect_runs(args)
    if isinstance(collected, int):
        return collected
    spec, seeds, runs = collected
    table = _write_results(args.out, runs, spec, seeds, args.deadline_ms, guard=not args.no_guard)
    plot_figures(runs, spec.solver.velocity_iterations, spec.solver.velocity_threshold, args.out)
    print(table)
    print(f"wrote {args.out}/summary.json, results.md and figures")
    return 0


def collect_runs(args: argparse.Namespace, names: list[str] | None = None):
    """(spec, seeds, {warm start: [run_simulation result per seed]}) of the command line, with
    a server of this machine's started and stopped around them where a `server:` warm start
    needs one and none is given; or the exit status (2: bad arguments, a server that is away or
    refuses; 1: a simulation failed), said on stderr, with nothing written. names: the warm
    starts to run instead of --warm-starts (`deepcontact lab spread` adds its own)."""
    try:
        spec, seeds, names, providers = _read_arguments(args, names)
    except ValueError as exc:
        print(f"{_prog(args)}: {exc}", file=sys.stderr)
        return 2
    remote = [p for p in providers.values() if p.uses_server]
    args.out.mkdir(parents=True, exist_ok=True)

    server_proc = None
    target = args.server
    if remote and target is None:
        from server.process import ServerProcess

        try:
            # only this machine's tasks dial it: a Unix socket (no port to find, nothing other hosts can reach)
            server_proc = ServerProcess(args.models, log=args.out / "server.log", local_socket=True).start()
        except (RuntimeError, TimeoutError) as exc:
            print(f"{_prog(args)}: {exc}", file=sys.stderr)
            return 2
        target = server_proc.address
    try:
        from simclient.client import Refused
        from simclient.simulate import connect, declare_world

        if any(STAR in _candidates(n) for n in names):
            try:
                names = expand_served(names, target, tls.client_credentials(*tls_files(args)))
            except (ValueError, ConnectionError) as exc:
                print(f"{_prog(args)}: {exc}", file=sys.stderr)
                return 2
            remote = [p for p in (make_provider(n) for n in names) if p.uses_server]
        for provider in remote:
            # Fail before any work if the server is away, lacks a model or refuses one for this
            # world (every seed's world has the scene's domain); each task connects on its own.
            try:
                client = connect(target, "+".join(provider.models), connect_timeout=10.0, allow_fallback=False,
                                 tls=tls_files(args))
                try:
                    declare_world(client, worlds.world_message(spec, worlds.build(spec, seeds[0])), provider.models)
                finally:
                    client.close()
            except Refused as exc:
                print(f"{_prog(args)}: the server refuses {provider.name} for this world: {exc}",
                      file=sys.stderr)
                return 2
            except (ValueError, ConnectionError) as exc:
                print(f"{_prog(args)}: {exc}", file=sys.stderr)
                return 2
        runs = simulate_all(spec, names, seeds, target=target, deadline_ms=args.deadline_ms,
                            workers=args.workers, ray=args.ray, quiet=args.quiet, guard=not args.no_guard,
                            tls=tls_files(args))
    except dispatch.DispatchError as exc:
        print(f"{_prog(args)}: {exc}; no results written", file=sys.stderr)
        return 1
    finally:
        if server_proc is not None:
            server_proc.stop()
    return spec, seeds, runs


STAR = "server:*"


def expand_served(names: list[str], target: str, credentials=None) -> list[str]:
    """`server:*` as every model the server at `target` serves (not its built-in providers such
    as zero or grid-identity), in natural order (NAME-e2 before NAME-e10): a top-level entry
    becomes one entry per model, one inside a composite (HEAD:W1+W2+..., e.g. price:server:*) one
    candidate per model.
    Raises ConnectionError when the server is away, ValueError when it serves no model."""
    import re

    from simclient.client import WarmStartClient

    client = WarmStartClient(target, credentials=credentials)
    try:
        if not client.wait_ready(10.0):
            raise ConnectionError(f"no warm-start server at {target} to list for {STAR}")
        served = [m.name for m in client.list_models() if m.kind != "provider"]
    finally:
        client.close()
    if not served:
        raise ValueError(f"{STAR}: the server at {target} serves no model (only providers)")
    served.sort(key=lambda n: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", n)])
    every = [f"server:{m}" for m in served]
    out = []
    for name in names:
        if name == STAR:
            out += every
        elif STAR in _candidates(name):
            head = composite_parts(name)[0]
            out.append(f"{head}:" + "+".join(c for part in _candidates(name) for c in (every if part == STAR else [part])))
        else:
            out.append(name)
    return out


def _candidates(name: str) -> list[str]:
    """The warm starts a warm-start name stands for: a composite's candidates (HEAD:W1+W2+...), else itself."""
    parts = composite_parts(name)
    return [name] if parts is None else parts[1]


def guard_note(summaries: dict[str, dict], runs: dict[str, list[dict]]) -> str:
    """A line per guarded warm start: the steps it served the learned start on and Box2D's, its
    probes and switches, and what its trial solves cost against Builtin's own sweeps on the same
    seeds (the guard keeps them under 5 %); "" when no warm start ran under a guard."""
    builtin = runs.get("builtin")
    reference = sum(int(np.sum(contact_step_iterations(r))) for r in builtin) if builtin else 0
    lines = []
    for name, s in summaries.items():
        if not s.get("guard_probes") and not s.get("guarded_steps") and not s.get("learned_steps"):
            continue
        cost = (f", trial sweeps {s['guard_trial_iterations'] / reference:.1%} of Builtin's"
                if reference else f", {s['guard_trial_iterations']:,} trial sweeps")
        heard = s.get("familiar_steps", 0) + s.get("unfamiliar_steps", 0)
        word = (f"; the server called {s['familiar_steps']:,} of the {heard:,} steps it answered familiar"
                + (f" (otherwise: {s['unfamiliar']})" if s.get("unfamiliar") else "")) if heard else ""
        lines.append(f"- {name}: the learned start on {s['learned_steps']:,} steps, Box2D's on "
                     f"{s['guarded_steps']:,}; {s['guard_probes']:,} probes, {s['guard_switches']:,} switches{cost}"
                     f"{word}")
    return ("\nGuard (the learned start served only while it beats Box2D's; --no-guard turns it off):\n"
            + "\n".join(lines) + "\n") if lines else ""


def served_by_note(summaries: dict[str, dict]) -> str:
    """A line per warm start whose server answered some steps with another card's answer (a face
    card's fallback: the step too large, its labels missed, or its route past the deadline;
    docs/server.md, Deadlines), or "" when none did."""
    lines = [f"- {name}: {sum(by.values()):,} of {s['steps_with_contacts']:,} steps with contacts answered by "
             + ", ".join(f"{card} ({n:,})" for card, n in sorted(by.items()))
             + (f"; the revolute joints started by the answer on {s['joints_started_steps']:,}"
                if s.get("joints_started_steps") else "")
             for name, s in summaries.items() if (by := s.get("served_by"))]
    return "\nAnswered by another card than the model's route:\n" + "\n".join(lines) + "\n" if lines else ""


def _write_results(out: Path, runs: dict[str, list[dict]], spec, seeds: list[int], deadline_ms: float,
                   guard: bool = False) -> str:
    """summary.json and results.md in ``out``, each written whole or not at all; returns the table.

    runs: {warm start: [run_simulation result per seed, in seed order]}.
    """
    summaries = {name: pooled_summary(r) for name, r in runs.items()}
    ratios = ratios_to_builtin(runs)
    cap = spec.solver.velocity_iterations
    picks = {name: p for name, r in runs.items()
             if (p := pick_summary(name, r, runs.get("builtin"), cap=cap)) is not None}
    write_json_atomic(out / "summary.json", {
        "seeds": seeds, "scene": spec.name, "scene_spec": worlds.spec_to_dict(spec), "deadline_ms": deadline_ms,
        "guard": guard,
        "command": "deepcontact " + " ".join(sys.argv[1:]), "warm_starts": summaries,
        "ratios_to_builtin": {name: {k: r.to_dict() for k, r in rs.items()} for name, rs in ratios.items()},
        "per_seed_mean_iterations": {name: [_seed_mean(r) for r in rs] for name, rs in runs.items()},
        "picks": picks})
    table = (markdown_table(summaries, seeds, spec.name, ratios) + guard_note(summaries, runs) + pick_table(picks)
             + served_by_note(summaries))
    tmp = out / ".results.md.part"
    tmp.write_text(table)
    tmp.replace(out / "results.md")
    return table


def simulate_all(spec, names: list[str], seeds: list[int], *, target: str | None, deadline_ms: float,
                 workers: int | None = None, ray: str | None = None, quiet: bool = True,
                 guard: bool = False, tls=(None, None, None)) -> dict[str, list[dict]]:
    """Every (warm start, seed) simulation, one task each (deepcontact.dispatch).

    Returns {warm start: [run_simulation result per seed, in seed order]}.
    target: the server for `server:` warm starts; guard: each `server:` warm start under a
    guard (simclient.guard); tls: (ca, cert, key) PEM files to dial the server with. Each task
    carries the modules that registered warm starts here (warmstarts.extensions, e.g. lab's), so
    that a worker started afresh knows the same names. Raises DispatchError.
    """
    pairs = [(name, seed) for name in names for seed in seeds]
    extensions = warmstarts.extensions()
    tasks = [dispatch.Task(f"{name} seed {seed}", (worlds.spec_to_dict(spec), name, seed, target, deadline_ms, guard,
                                                   tuple(tls), extensions))
             for name, seed in pairs]
    runs: dict[str, list[dict]] = {name: [] for name in names}
    with dispatch.Dispatcher(workers=workers, ray=ray) as dispatcher:
        results = dispatcher.map(simulate_one, tasks, progress=None if quiet else "iterations")
        for (name, _), text in zip(pairs, results):
            runs[name].append(json.loads(text))
    return runs


def simulate_one(spec_dict: dict, name: str, seed: int, target: str | None, deadline_ms: float,
                 guard: bool = False, tls=(None, None, None), extensions=()) -> str:
    """One task: warm start `name` on (scene, seed); the run_simulation result as JSON text.

    A `server:` warm start opens its own client to `target` for this simulation; `extensions`
    are imported first (the modules that registered warm starts where the task was made).
    """
    from simclient.simulate import connect

    warmstarts.load_extensions(extensions)
    provider = make_provider(name)  # a fresh provider per world: some keep state across steps
    client = None
    if provider.uses_server:
        client = connect(target, "+".join(provider.models), connect_timeout=10.0, allow_fallback=False,
                         tls=tuple(tls))
    try:
        result = run_simulation(worlds.spec_from_dict(spec_dict), seed, provider, client=client,
                                deadline_ms=deadline_ms, guard=Guard() if guard else None)
    finally:
        if client is not None:
            client.close()
    return json.dumps(result)


def pooled_summary(results: list[dict]) -> dict:
    """The summary over all steps of all seeds of one warm start."""
    records = []
    for r in results:
        cols = r["per_step"]
        n = len(cols["velocity_iterations"])
        records += [StepRecord(**{k: cols[k][i] for k in cols}) for i in range(n)]
    return summarize(records)


def contact_step_iterations(run: dict) -> np.ndarray:
    """(steps with contacts,) velocity iterations of one simulation."""
    cols = run["per_step"]
    return np.array([i for i, n in zip(cols["velocity_iterations"], cols["contact_points"]) if n > 0], np.int64)


def _seed_mean(run: dict) -> float | None:
    its = contact_step_iterations(run)
    return float(its.mean()) if len(its) else None


def every_step_iterations(run: dict) -> np.ndarray:
    """(steps,) velocity iterations of every step of one simulation, with contacts or not (a
    step whose bodies are all asleep solves nothing: 0)."""
    return np.asarray(run["per_step"]["velocity_iterations"], np.int64)


def ratios_to_builtin(runs: dict[str, list[dict]]) -> dict[str, dict[str, Ratio]]:
    """{warm start: {"mean"|"median"|"p90"|"every_step": Ratio}}: each warm start's statistic
    over Builtin's on the same seeds, with the paired bootstrap interval over seeds
    (bench.stats); empty without a builtin run. The first three are over the steps with
    contacts (the thesis's measure); every_step is the mean over every step of the runs, the
    solver's whole work: with Box2D's sleeping on, a run whose bodies fall asleep sooner has
    fewer steps with contacts, its costly settling steps a larger share of them, and the two
    measures part (a pile of polygons that slept at step 100 where Builtin's never did: 2.29x
    Builtin's mean over the steps with contacts for 0.96x of its iterations in all)."""
    if "builtin" not in runs:
        return {}
    reference = [contact_step_iterations(r) for r in runs["builtin"]]
    every = [every_step_iterations(r) for r in runs["builtin"]]
    return {name: {**{stat: ratio_interval([contact_step_iterations(r) for r in rs], reference, stat) for stat in STATS},
                   "every_step": ratio_interval([every_step_iterations(r) for r in rs], every, "mean")}
            for name, rs in runs.items()}


def pick_summary(name: str, results: list[dict], builtin: list[dict] | None = None,
                 cap: int | None = None) -> dict | None:
    """What the trial solves of a composite warm start (e.g. `pick:`, `shadow:`, `price:`) saw, or
    None for another warm start.

    Every candidate (builtin, then the others) was solved from the same state at
    every step with contacts (the picked trajectory's): per candidate, its mean
    iterations there, that over builtin's with its bootstrap interval over seeds,
    and the share of steps where it was picked (builtin on ties), beat builtin
    and lost to it. With two or more models, also `over_first`: each candidate's
    iterations over the first model's on the same states, with the interval
    paired by seed, so two models are compared directly rather than through
    their two intervals to builtin (which share most of their noise). A model that fell back at a step is priced as builtin there
    (the table's fallbacks column counts such steps).
    With `builtin` (its own runs on the same seeds), also `trajectory`: builtin's
    mean on this trajectory over its mean on its own, paired by seed. A
    closed-loop ratio is the candidate's same-state ratio times that.
    With `cap` (the solver's most velocity iterations a step), also `at_cap`
    (cap_summary): how much of it is in steps that end at the cap.
    """
    if not any(r.get("trials") for r in results):
        return None
    provider = make_provider(name)
    if not provider.picks:
        return None
    candidates = provider.labels
    width = len(candidates)
    per_seed = [np.array([t for t in r.get("trials", []) if len(t) == width], float).reshape(-1, width)
                for r in results]  # (steps, candidates) iterations per seed
    reach = [np.array([t for t in r.get("reach", []) if len(t) == width], float).reshape(-1, width)
             for r in results]  # the same steps: sweeps to Builtin's accuracy (the composite's `reach`)
    if any(len(q) != len(s) for q, s in zip(reach, per_seed)):
        reach = None  # results written before the trials traced their residuals
    a = np.concatenate(per_seed)
    best = a.argmin(axis=1)
    return {"candidates": candidates, "serves": provider.serves, "steps": len(a),
            "mean_iterations": a.mean(axis=0).tolist(),
            "over_builtin": [ratio_interval([s[:, i] for s in per_seed], [s[:, 0] for s in per_seed]).to_dict()
                             for i in range(width)],
            "over_first": ([ratio_interval([s[:, i] for s in per_seed], [s[:, 1] for s in per_seed]).to_dict()
                            for i in range(width)] if width > 2 else None),
            "picked": [float((best == i).mean()) for i in range(width)],
            "better_than_builtin": (a < a[:, :1]).mean(axis=0).tolist(),
            "worse_than_builtin": (a > a[:, :1]).mean(axis=0).tolist(),
            "trajectory": (ratio_interval([s[:, 0] for s in per_seed], [contact_step_iterations(b) for b in builtin]).to_dict()
                           if builtin is not None and len(builtin) == len(per_seed) else None),
            "at_cap": cap_summary(per_seed, cap, reach) if cap else None,
            "notes": _mean_notes(provider.note_labels, results)}


def _mean_notes(labels: list[str], results: list[dict]) -> dict[str, float] | None:
    """Each of a composite's per-step notes (Composite.note_labels) averaged over every seed's steps, or None."""
    rows = [t for r in results for t in r.get("notes", []) if len(t) == len(labels)]
    if not labels or not rows:
        return None
    return dict(zip(labels, np.mean(np.array(rows, float), axis=0).tolist()))


def cap_summary(per_seed: list[np.ndarray], cap: int, reach: list[np.ndarray] | None = None) -> dict:
    """Where the solver's cap on velocity iterations bounds what a warm start can show.

    A step that ends at the cap is unconverged: a better start shows there only if it
    brings the step under the cap. per_seed: (steps, candidates) iterations per seed,
    builtin first. Returns the cap, Builtin's share of steps and of iterations at it,
    and per candidate: its share of steps at the cap, the share of Builtin's capped
    steps it ends under the cap, and its iterations over Builtin's on the steps
    Builtin ends under the cap and on those it ends at it (intervals over seeds).
    With `reach` (the same shape: each trial's sweeps to Builtin's accuracy,
    the composite's `reach`), also `reach_at`: those sweeps over Builtin's
    own on the steps Builtin ends at the cap, and `reach_all`: the same over all
    steps, its iterations counted where Builtin converges: what a start is worth
    once the capped steps are counted by accuracy rather than by the cap."""
    a = np.concatenate(per_seed)
    capped = a[:, 0] >= cap
    width = a.shape[1]

    def over_builtin(where, values=per_seed) -> list[dict]:
        parts = [v[where(s[:, 0])] for v, s in zip(values, per_seed)]
        return [ratio_interval([q[:, i] for q in parts], [q[:, 0] for q in parts]).to_dict() for i in range(width)]

    out = {"cap": int(cap), "builtin_steps": float(capped.mean()) if len(a) else 0.0,
           "builtin_iterations": float(a[capped, 0].sum() / max(a[:, 0].sum(), 1)),
           "steps": (a >= cap).mean(axis=0).tolist(),
           "freed": ((a[capped] < cap).mean(axis=0) if capped.any() else np.zeros(width)).tolist(),
           "over_builtin_under": over_builtin(lambda b: b < cap),
           "over_builtin_at": over_builtin(lambda b: b >= cap)}
    if reach is not None:
        out["reach_at"] = over_builtin(lambda b: b >= cap, reach)
        out["reach_all"] = over_builtin(lambda b: b >= 0, reach)
    return out


def pick_table(picks: dict) -> str:
    """The trial solves of each composite warm start (`pick:`, `shadow:`, `price:`, ...) as markdown ('' without one)."""
    lines = []
    for name, p in picks.items():
        whose = p.get("serves", "the picked")  # whose trajectory the steps are (Composite.serves)
        lines += ["", f"`{name}`: every candidate solved from the same state at each of {p['steps']} steps "
                      f"({whose} trajectory):", "",
                  "| candidate | mean iterations | / builtin | / first model | picked | better than builtin | worse |",
                  "|---|---|---|---|---|---|---|"]
        for i, c in enumerate(p["candidates"]):
            r = Ratio(**p["over_builtin"][i])
            ratio = "1" if i == 0 else r.text() + (" ✓" if r.below_one() else "")
            first = p.get("over_first")
            paired = "–" if not first or i == 0 else "1" if i == 1 else Ratio(**first[i]).text()
            lines.append(f"| {c} | {p['mean_iterations'][i]:.1f} | {ratio} | {paired} | {p['picked'][i]:.0%} | "
                         f"{p['better_than_builtin'][i]:.0%} | {p['worse_than_builtin'][i]:.0%} |")
        if p.get("trajectory"):
            lines += ["", f"Builtin on this trajectory / builtin on its own: {Ratio(**p['trajectory']).text()} "
                          "(paired by seed; the closed-loop ratio is a candidate's same-state ratio times this)."]
        if p.get("notes"):
            lines += ["", "Per step, mean: " + "; ".join(f"{k} {v:.1f}" for k, v in p["notes"].items()) + "."]
        if p.get("at_cap"):
            lines += cap_table(p["candidates"], p["at_cap"])
    return "\n".join(lines) + ("\n" if lines else "")


def cap_table(candidates: list[str], c: dict) -> list[str]:
    """Markdown lines for cap_summary's figures, one row per candidate."""
    lines = ["", f"At the cap ({c['cap']} iterations): Builtin ends {c['builtin_steps']:.1%} of these steps there, "
                 f"{c['builtin_iterations']:.1%} of its iterations; a start shows there only by ending under it.", "",
             "| candidate | steps at the cap | of Builtin's capped steps, under the cap "
             "| / builtin where Builtin ends under the cap | / builtin where Builtin ends at it |"
             + (" sweeps to Builtin's accuracy where it ends at the cap, / builtin's | all steps, the capped ones so |"
                if "reach_at" in c else ""),
             "|---|---|---|---|---|" + ("---|---|" if "reach_at" in c else "")]
    for i, name in enumerate(candidates):
        keys = ("over_builtin_under", "over_builtin_at") + (("reach_at", "reach_all") if "reach_at" in c else ())
        cells = ["1" if i == 0 else Ratio(**c[k][i]).text() for k in keys]
        lines.append(f"| {name} | {c['steps'][i]:.1%} | {c['freed'][i]:.1%} | " + " | ".join(cells) + " |")
    return lines


def markdown_table(summaries: dict, seeds: list[int], scene: str, ratios: dict | None = None) -> str:
    ratios = ratios or {}
    if len(seeds) == 1:
        seed_text = f"seed {seeds[0]} (1 world)"
    elif seeds == list(range(seeds[0], seeds[-1] + 1)):
        seed_text = f"seeds {seeds[0]}-{seeds[-1]} ({len(seeds)} worlds)"
    else:
        seed_text = f"seeds {', '.join(map(str, seeds))} ({len(seeds)} worlds)"
    lines = [f"Scene `{scene}`, {seed_text}; velocity iterations over steps with contacts (the last column: "
             "over every step, the solver's whole work, which parts from it where bodies fall asleep). "
             "Ratios to builtin with their 95 % bootstrap interval over seeds; ✓: the whole interval lies below 1.",
             "",
             "| warm start | mean | / builtin | median | median / builtin | p90 | p90 / builtin | MSE normal "
             "| MSE tangent | p50 latency ms | p99 latency ms | fallbacks | every step / builtin |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def f(x, fmt):
        return "–" if x is None else format(x, fmt)

    def r(name, stat):
        ratio = ratios.get(name, {}).get(stat)
        if ratio is None or name == "builtin":
            return "1" if name == "builtin" and ratio is not None else "–"
        return ratio.text() + (" ✓" if ratio.below_one() else "")

    for name, s in summaries.items():
        lines.append(f"| {name} | {f(s['mean_velocity_iterations'], '.1f')} | {r(name, 'mean')} | "
                     f"{f(s['median_velocity_iterations'], '.0f')} | {r(name, 'median')} | "
                     f"{f(s['p90_velocity_iterations'], '.0f')} | {r(name, 'p90')} | "
                     f"{f(s['mse_normal'], '.3g')} | {f(s['mse_tangent'], '.3g')} | {f(s['p50_latency_ms'], '.2f')} | "
                     f"{f(s['p99_latency_ms'], '.2f')} | {s['fallback_steps']} | {r(name, 'every_step')} |")
    if not any(s["steps_with_contacts"] for s in summaries.values()):
        lines += ["", "No steps with contacts: nothing to warm-start, nothing to compare."]
    return "\n".join(lines) + "\n"


# Baselines (the engine's own, oracles, fixed providers) in greys and broken lines, learned
# models in colours and full lines; no two series share both.
_BASELINE_GREYS = ("0.35", "0.55", "0.7", "0.2", "0.45", "0.62")
_BASELINE_DASHES = ("--", ":", "-.", (0, (5, 1, 1, 1)), (0, (8, 2)))  # 5 against 6 greys: 30 looks
_LEARNED_DASHES = ("-", (0, (6, 2)), (0, (3, 1, 1, 1, 1, 1)))


def series_styles(names: list[str]) -> dict[str, dict]:
    """Matplotlib line styles per warm start: builtin black and thick (the bar to
    beat), other baselines grey and dashed, learned models (server: models
    other than the providers) coloured and solid; every series distinct."""
    import matplotlib

    providers = {"server:zero", "server:random", "server:bad", "server:grid-identity"}
    colours = matplotlib.colormaps["tab10"].colors + matplotlib.colormaps["Dark2"].colors
    styles, learned, baseline = {}, 0, 0
    for name in names:
        if name == "builtin":
            styles[name] = {"color": "black", "ls": "-", "lw": 1.8}
        elif name.startswith("server:") and name not in providers:
            styles[name] = {"color": colours[learned % len(colours)],
                            "ls": _LEARNED_DASHES[learned // len(colours) % len(_LEARNED_DASHES)], "lw": 1.3}
            learned += 1
        else:
            styles[name] = {"color": _BASELINE_GREYS[baseline % len(_BASELINE_GREYS)],
                            "ls": _BASELINE_DASHES[baseline % len(_BASELINE_DASHES)], "lw": 1.1}
            baseline += 1
    return styles


def legend_label(name: str, width: int = 60) -> str:
    """A warm start's name as a figure's legend shows it: a composite that prices several
    (shadow:W1+W2+..., price:...) by its mode, its first warm start and how many more, since its
    line is one trajectory and the full name (hundreds of characters) would cover the plot;
    any other name past `width` characters cut with an ellipsis. Tables keep the full names."""
    parts = composite_parts(name)
    if parts is not None and len(parts[1]) > 1:
        head, (first, *more) = parts
        name = f"{head}:{first} (+{len(more)} more)"
    return name if len(name) <= width else name[:width - 1] + "\u2026"


def plot_figures(runs: dict[str, list[dict]], max_iterations: int, threshold: float, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def per_step(name, key):
        a = np.array([[np.nan if v is None else v for v in r["per_step"][key]] for r in runs[name]], float)
        with warnings.catch_warnings():  # a step no seed has a value for stays NaN: a gap in the line
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmean(a, axis=0)

    style = series_styles(list(runs))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for name in runs:
        ax1.plot(per_step(name, "contact_points"), label=legend_label(name), **style[name])
        ax2.plot(per_step(name, "velocity_iterations"), label=legend_label(name), **style[name])
    ax1.set(xlabel="step", ylabel="contact points", title="(a) contact points per step (mean over seeds)")
    ax2.set(xlabel="step", ylabel="velocity iterations", title="(b) iterations per step (mean over seeds)")
    ax2.legend(fontsize=7)
    save_figure(fig, out / "fig20_contacts_iterations.png")

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    k = np.arange(max_iterations + 1)
    for name in runs:
        its = np.array([i for r in runs[name] for i, n in zip(r["per_step"]["velocity_iterations"],
                                                               r["per_step"]["contact_points"]) if n > 0])
        ax1.plot(k, (its[None, :] > k[:, None]).sum(axis=1) / len(runs[name]), label=legend_label(name), **style[name])
        traces = [t for r in runs[name] for t, n in zip(r["per_step"]["residual_trace"], r["per_step"]["contact_points"])
                  if n > 0 and len(t)]
        if traces:  # none in a run without contacts: the panel stays empty
            # Finished steps repeat their last residual (thesis §8.2.1), so the median stays defined.
            padded = np.array([np.pad(t, (0, max_iterations - len(t)), mode="edge") for t in traces])
            median = np.median(padded, axis=0)
            ax2.plot(np.arange(1, max_iterations + 1), median, label=legend_label(name), **style[name])
            if median.max() > 0:  # the first steps of a short run may converge to no change at all
                ax2.set_yscale("log")
    ax1.set(xlabel="iteration k", ylabel="steps still iterating (per simulation)",
            title="(a) steps needing more than k iterations")
    ax2.axhline(threshold, color="k", ls=":", lw=0.8)
    ax2.set(xlabel="iteration", ylabel="median max |impulse change| (N s)", title="(b) median residual per iteration")
    (ax2 if ax2.get_legend_handles_labels()[0] else ax1).legend(fontsize=7)
    save_figure(fig, out / "fig21_convergence.png")

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for ax, key in ((ax1, "mse_normal"), (ax2, "mse_tangent")):
        curves = {name: per_step(name, key) for name in runs}
        for name, curve in curves.items():
            ax.plot(curve, label=legend_label(name), **style[name])
        if any(np.nanmax(c, initial=0.0) > 0 for c in curves.values()):  # a short run may have no error at all
            ax.set_yscale("log")
    ax1.set(xlabel="step", ylabel="MSE (N s)^2", title="(a) warm start vs final impulse, normal")
    ax2.set(xlabel="step", ylabel="MSE (N s)^2", title="(b) tangent")
    ax2.legend(fontsize=7)
    save_figure(fig, out / "fig26_mse.png")


