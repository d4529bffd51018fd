"""`deepcontact bench walltime`: does a learned warm start make the whole step faster?

    deepcontact bench walltime --sizes thesis,100,400,1600 --seeds 901-903 --out bench/results/walltime
    deepcontact bench walltime --world bench/stack_wall.py:build --tolerance 1e-6 --out bench/results/wall

For each world size (or a user's world, `--world`, built as `bench iterations` builds one;
`--tolerance`, `--max-iterations` and `--dt` set the solver for every world), simulates the same seeds with `builtin` and with a served
model (`server:MODEL`, one `deepcontact serve` process started here, on a Unix socket of its own
as `bench iterations` starts one, or where `--bind` says: loopback TCP with `127.0.0.1:0`) and times
every step's parts (simclient.simulate.StepRecord):

    builtin:     collide + solve                                 (what Box2D alone does)
    learned:     collide + export + round trip + inject + solve  (the round trip includes
                                                                  encoding and decoding)
    in-process:  collide + export + predict + inject + solve     (the same model called in
                                                                  this process, bench.inprocess)

over steps with contacts (medians over all seeds' steps, ms; the whole step also as its mean,
and the learned mean over Builtin's, the ratio a user's simulation would see). The break-even
is what the learned warm start costs per step beyond Box2D's own work
(export + round trip + inject, median) divided by what one velocity
iteration costs at that size (the slope of builtin's solve times over its
iterations, least squares over its steps: a step's solve also has a fixed part,
the islands, the constraints' set-up and the positions' pass, which no warm
start saves): how many iterations per step it must save to pay for
itself, beside how many it does save (builtin's mean iterations minus the
model's). The in-process run gives the same warm starts without gRPC, so its
overhead is what the model's own work (features, inference, combination) costs
and the rest of the served overhead is the transport's; its break-even says
whether a warm start run beside the solver would pay. Sizes: `thesis` (100
bodies of 0.5 m in 15 x 15 m) and N, the scene family at N bodies (radius 0.3-0.55 m, friction 0.2-0.8) in a square
box growing with N so the density stays the thesis's (15 m per 100 bodies,
times sqrt(N / 100)); the server's grids grow with the box.

"first round trip" is the median over seeds of each simulation's first served step,
which a server that had not run this grid size before would be slow on (the
server warms a model up when a stream declares its world, so it should not be).
The deadline is long (1 s by default) so that every step is served and
timed, not replaced by builtin. A third table says where the learned step's
mean goes: the sweeps saved and what they are worth, the served overhead's mean and the
model's own (in process), and the mean overhead at which the learned step would be 1.5 and
1.0 times Builtin's: what the round trip may cost for a ratio. `--pin` puts the server on the host's last core and the
simulations on the others, so that neither moves between cores nor takes the other's caches. Writes DIR/walltime.json, DIR/walltime.md
(the table) and DIR/walltime.png (step time against bodies, one line per
warm start).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from pathlib import Path

import numpy as np

from bench.figures import save_figure
from deepcontact.io import write_json_atomic
from simclient import seeds as seed_ranges
from simclient import worlds
from simclient.engine import Box2D, SolverConfig
from simclient.scene import SceneSpec
from simclient.worlds import WorldSpec

FAMILY_RADIUS = (0.3, 0.55)
FAMILY_FRICTION = (0.2, 0.8)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--sizes", default=None,
                        help="worlds: 'thesis' and/or body counts of the scene family (default thesis,100,400,1600)")
    parser.add_argument("--world", metavar="PATH.py:FUNCTION",
                        help="a world of your own instead of --sizes: FUNCTION(seed) in PATH.py (or MODULE:FUNCTION) "
                             "returns a patched Box2D.b2World (docs/worlds.md)")
    parser.add_argument("--tolerance", type=float, metavar="NS",
                        help="the solver stops after the first sweep whose largest impulse change is at most this "
                             "(N s; default 1e-4)")
    parser.add_argument("--max-iterations", type=int, metavar="N",
                        help="the solver's cap on velocity iterations a step (default 1000)")
    parser.add_argument("--dt", type=float, metavar="S", help="time step in s (default 0.01)")
    parser.add_argument("--seeds", default="901-903", help="benchmark seeds per size (default 901-903)")
    parser.add_argument("--model", default="default", help="served model (default default, the shipped alias)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--deadline-ms", type=float, default=1000.0,
                        help="per-step deadline (default 1000: every step is served and timed)")
    parser.add_argument("--in-process", action=argparse.BooleanOptionalAction, default=True,
                        help="also simulate with the model called in this process, no gRPC (default on)")
    parser.add_argument("--out", type=Path, default=Path("bench/results/walltime"),
                        help="output folder (default bench/results/walltime)")
    parser.add_argument("--bind", default="local",
                        help="where the server started here listens: 'local' (default), a Unix socket in a "
                             "folder of its own, what a simulation and its server on one host use; "
                             "127.0.0.1:0 a free loopback port; unix:PATH a Unix socket there")
    parser.add_argument("--pin", action="store_true",
                        help="the server on this host's last core and the simulations on the others (a host of "
                             "two cores or more), as a simulation and its server sharing a host may be run: "
                             "neither moves between cores nor takes the other's caches (default: both on every core)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def pinned_cores() -> tuple[set[int], set[int]]:
    """(the server's cores, the simulation's) for --pin: the last of this process's cores, and the
    rest. ValueError on a host of one core."""
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) < 2:
        raise ValueError(f"--pin needs two cores or more; this process may run on {len(cores)}")
    return {cores[-1]}, set(cores[:-1])


def scene_for(size: str, steps: int, solver: SolverConfig = SolverConfig()) -> SceneSpec:
    """The world of one size: 'thesis' or a body count of the scene family (ValueError otherwise)."""
    if size == "thesis":
        return dataclasses.replace(SceneSpec.thesis(), steps=steps, solver=solver)
    try:
        n = int(size)
    except ValueError:
        raise ValueError(f"size {size!r}: use 'thesis' or a number of bodies") from None
    if n < 1:
        raise ValueError(f"size {size!r}: at least one body")
    side = round(15.0 * math.sqrt(n / 100.0), 2)
    return SceneSpec(name=f"family-{n}", bodies=n, box_size=(side, side), radius=FAMILY_RADIUS,
                     friction=FAMILY_FRICTION, steps=steps, solver=solver)


def specs_from_args(args: argparse.Namespace) -> list:
    """The worlds to time: each of --sizes (SceneSpecs), or the user's --world (a WorldSpec),
    every one with the solver's settings the flags give. ValueError, in one line, if none fits."""
    overrides = {k: v for k, v in (("velocity_threshold", args.tolerance), ("velocity_iterations", args.max_iterations),
                                   ("dt", args.dt)) if v is not None}
    if not all(math.isfinite(v) and v > 0 for v in overrides.values()) or overrides.get("velocity_iterations", 1) < 1:
        raise ValueError(f"--tolerance and --dt must be > 0 and --max-iterations >= 1, got "
                         f"{args.tolerance}, {args.dt} and {args.max_iterations}")
    if args.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {args.steps}")
    solver = dataclasses.replace(SolverConfig(), **overrides)
    if args.world is not None:
        if args.sizes is not None:
            raise ValueError("give --sizes (the project's worlds) or --world (your own), not both")
        spec = WorldSpec(args.world, steps=args.steps, solver=solver)
        spec.validate()
        return [spec]
    specs = [scene_for(s.strip(), args.steps, solver) for s in (args.sizes or "thesis,100,400,1600").split(",")
             if s.strip()]
    if not specs:
        raise ValueError("give at least one size")
    for spec in specs:
        spec.validate()
    return specs


def dynamic_bodies(spec, seed: int) -> int:
    """How many dynamic bodies the world of (spec, seed) starts with: a user's world's size."""
    engine = worlds.build(spec, seed)
    return sum(body.type == Box2D.b2_dynamicBody for body in engine.world.bodies)


def step_times(run: dict, learned: bool) -> dict[str, np.ndarray]:
    """Per step with contacts (ms): the parts and the whole step, and the velocity iterations."""
    cols = {k: np.asarray(v, float) for k, v in run["per_step"].items()
            if k in ("contact_points", "velocity_iterations", "collide_ms", "export_ms", "provider_ms",
                     "inject_ms", "solve_ms")}
    keep = cols["contact_points"] > 0
    out = {k: v[keep] for k, v in cols.items()}
    out["overhead_ms"] = out["export_ms"] + out["provider_ms"] + out["inject_ms"] if learned else \
        np.zeros(int(keep.sum()))
    out["step_ms"] = out["collide_ms"] + out["overhead_ms"] + out["solve_ms"]
    return out


def _first_round_trip(run: dict) -> float:
    """Round trip (ms) of a simulation's first served step: the one a cold server would be slow on."""
    return next(lat for lat in run["per_step"]["latency_ms"] if lat is not None)


def _server_inference_ms(runs: list[dict]) -> float | None:
    """Median inference time (ms) the server reported over the served steps, None without any."""
    times = [t["inference"] for r in runs for t in r["per_step"]["server_us"] if t]
    return 1e-3 * float(np.median(times)) if times else None


def _pooled(runs: list[dict], learned: bool) -> dict[str, np.ndarray]:
    """step_times of several simulations, their steps end to end."""
    return {k: np.concatenate([step_times(r, learned)[k] for r in runs]) for k in step_times(runs[0], learned)}


def solve_fit(solve_ms: np.ndarray, iterations: np.ndarray) -> tuple[float, float] | None:
    """(fixed ms, ms a sweep): the least-squares line solve_ms = fixed + per_sweep * iterations
    over a run's steps (N,) each, or None where the steps do not vary in their sweeps. A step's
    solve is more than its sweeps (the islands, the constraints' set-up, the positions' pass),
    so a median of solve / sweeps overstates what one sweep costs, and what one saved is worth."""
    if len(iterations) < 2 or np.ptp(iterations) == 0:
        return None
    per, fixed = np.polyfit(np.asarray(iterations, float), np.asarray(solve_ms, float), 1)
    return float(fixed), float(per)


def overhead_allowed(ratio: float, builtin_mean_ms: float, learned_mean_ms: float,
                     learned_overhead_mean_ms: float) -> float:
    """The mean served overhead (ms a step) at which the learned step's mean would be `ratio`
    times Builtin's, its collide and solve as measured: what the round trip may cost."""
    return ratio * builtin_mean_ms - (learned_mean_ms - learned_overhead_mean_ms)


def summarize_size(builtin: list[dict], learned: list[dict], in_process: list[dict] | None = None) -> dict:
    """One size's row from builtin's, the served model's and (optionally) the in-process model's
    runs on the same seeds."""
    b, m = _pooled(builtin, False), _pooled(learned, True)
    # What a sweep costs: the slope of Builtin's solve times over its sweeps (a step's solve has
    # a fixed part, which a saved sweep does not save); the median ratio where they do not vary.
    fit_b = solve_fit(b["solve_ms"], b["velocity_iterations"])
    per_iteration = fit_b[1] if fit_b is not None and fit_b[1] > 0 else \
        float(np.median(b["solve_ms"] / np.maximum(b["velocity_iterations"], 1)))
    overhead = float(np.median(m["overhead_ms"]))
    saved = float(b["velocity_iterations"].mean() - m["velocity_iterations"].mean())
    row = {
        "steps_with_contacts": int(len(b["step_ms"])),
        "median_contact_points": float(np.median(b["contact_points"])),
        "builtin": {"step_ms": float(np.median(b["step_ms"])), "solve_ms": float(np.median(b["solve_ms"])),
                    "collide_ms": float(np.median(b["collide_ms"])),
                    "mean_iterations": float(b["velocity_iterations"].mean()),
                    "mean_step_ms": float(b["step_ms"].mean())},
        "learned": {"step_ms": float(np.median(m["step_ms"])), "solve_ms": float(np.median(m["solve_ms"])),
                    "collide_ms": float(np.median(m["collide_ms"])), "overhead_ms": overhead,
                    "round_trip_ms": float(np.median(m["provider_ms"])),
                    "mean_iterations": float(m["velocity_iterations"].mean()),
                    "mean_step_ms": float(m["step_ms"].mean()),
                    "fallback_steps": int(sum(r["summary"]["fallback_steps"] for r in learned)),
                    "first_round_trip_ms": float(np.median([_first_round_trip(r) for r in learned])),
                    "server_inference_ms": _server_inference_ms(learned)},
        "ms_per_iteration": per_iteration,
        "break_even_iterations": overhead / per_iteration if per_iteration > 0 else None,
        "saved_iterations": saved,
    }
    # Where the learned step's mean goes, and the mean overhead it could afford at 1.5 and 1.0
    # times Builtin's mean step, its collide and solve as measured.
    mean_overhead = float(m["overhead_ms"].mean())
    row["budget"] = {
        "builtin_solve_fit": fit_b, "learned_overhead_mean_ms": mean_overhead,
        "learned_solve_mean_ms": float(m["solve_ms"].mean()), "builtin_solve_mean_ms": float(b["solve_ms"].mean()),
        "saved_ms": saved * per_iteration,
        "overhead_allowed_ms": {str(r): overhead_allowed(r, float(b["step_ms"].mean()), float(m["step_ms"].mean()),
                                                         mean_overhead) for r in (1.5, 1.0)},
    }
    if in_process:
        p = _pooled(in_process, True)
        own = float(np.median(p["overhead_ms"]))
        row["in_process"] = {
            "step_ms": float(np.median(p["step_ms"])), "solve_ms": float(np.median(p["solve_ms"])),
            "mean_step_ms": float(p["step_ms"].mean()),
            "predict_ms": float(np.median(p["provider_ms"])), "overhead_ms": own,
            "mean_iterations": float(p["velocity_iterations"].mean()),
            "break_even_iterations": own / per_iteration if per_iteration > 0 else None,
            "saved_iterations": float(b["velocity_iterations"].mean() - p["velocity_iterations"].mean()),
            "overhead_mean_ms": float(p["overhead_ms"].mean())}
        stages = [st for r in in_process for st in r.get("stages", ())]
        # Three columns for every kind: before inference (a grid model's p2g, a graph model's
        # features), inference, after it (g2p; the face route's solve and admission).
        for names, key in ((("p2g", "features"), "p2g_ms"), (("inference",), "inference_ms"),
                           (("g2p", "solve", "admit"), "g2p_ms")):
            times = [sum(st[n] for n in names if n in st) for st in stages if any(n in st for n in names)]
            row["in_process"][key] = 1e3 * float(np.median(times)) if times else None
    return row


def run(args: argparse.Namespace) -> int:
    from server.process import ServerProcess
    from simclient.simulate import connect

    try:
        seeds = seed_ranges.parse_seeds(args.seeds)
        specs = specs_from_args(args)
        # A user's world that cannot be built for a seed: said now, before a server starts.
        bodies = {spec.name: dynamic_bodies(spec, seeds[0]) if isinstance(spec, WorldSpec) else spec.bodies
                  for spec in specs}
    except ValueError as exc:
        print(f"deepcontact bench walltime: {exc}", file=sys.stderr)
        return 2
    try:
        server_cores, simulation_cores = pinned_cores() if args.pin else (None, None)
        local = args.bind == "local"
        server = ServerProcess(args.models, local_socket=local, cpus=server_cores,
                               **({} if local else {"bind": args.bind})).start()
    except (ValueError, RuntimeError, TimeoutError) as exc:
        print(f"deepcontact bench walltime: {exc}", file=sys.stderr)
        return 2
    every_core = os.sched_getaffinity(0)
    if simulation_cores is not None:
        os.sched_setaffinity(0, simulation_cores)
    rows = {}
    try:
        try:
            connect(server.address, args.model, connect_timeout=10.0, allow_fallback=False).close()
        except (ValueError, ConnectionError) as exc:
            print(f"deepcontact bench walltime: {exc}", file=sys.stderr)
            return 2
        from tqdm import tqdm

        arms = 3 if args.in_process else 2
        bar = tqdm(total=arms * len(specs) * len(seeds), unit="sim", disable=args.quiet, file=sys.stderr)
        for spec in specs:
            runs = _simulate_size(spec, seeds, server.address, args, bar.update)
            rows[spec.name] = {"bodies": bodies[spec.name],
                               "box_size": list(spec.box_size) if isinstance(spec, SceneSpec) else None,
                               **summarize_size(**runs)}
        bar.close()
    finally:
        server.stop()
        os.sched_setaffinity(0, every_core)
    args.out.mkdir(parents=True, exist_ok=True)
    pinned = {"server": sorted(server_cores), "simulation": sorted(simulation_cores)} if args.pin else None
    write_json_atomic(args.out / "walltime.json", {
        "command": "deepcontact " + " ".join(sys.argv[1:]), "model": args.model, "bind": args.bind, "seeds": seeds,
        "pinned": pinned, "solver": dataclasses.asdict(specs[0].solver), "sizes": rows})
    table = markdown_table(rows, args.model, seeds, specs[0].solver, pinned)
    tmp = args.out / ".walltime.md.part"
    tmp.write_text(table)
    tmp.replace(args.out / "walltime.md")
    plot(rows, args.model, args.out / "walltime.png")
    print(table)
    print(f"wrote {args.out}/walltime.json, walltime.md and walltime.png")
    return 0


def _simulate_size(spec, seeds: list[int], address: str, args: argparse.Namespace, tick) -> dict[str, list[dict]]:
    """Every seed of one world size (a SceneSpec) with each arm: Builtin, the served model (a
    channel of its own per simulation) and, with --in-process, the model in this process.
    Returns each arm's simulation results in seed order; `tick()` is called after each simulation."""
    from simclient.simulate import connect, run_simulation
    from simclient.warmstarts import make_provider

    runs = {"builtin": [], "learned": []}
    local = None
    if args.in_process:
        from bench.inprocess import InProcess

        local, runs["in_process"] = InProcess.load(args.models, args.model, spec), []
    for seed in seeds:
        runs["builtin"].append(run_simulation(spec, seed, make_provider("builtin")))
        tick()
        client = connect(address, args.model, connect_timeout=10.0, allow_fallback=False)
        try:
            runs["learned"].append(run_simulation(spec, seed, make_provider(f"server:{args.model}"),
                                                  client=client, deadline_ms=args.deadline_ms))
        finally:
            client.close()
        tick()
        if local is not None:
            runs["in_process"].append(run_simulation(spec, seed, local))
            runs["in_process"][-1]["stages"] = local.stages
            tick()
    return runs


def markdown_table(rows: dict, model: str, seeds: list[int], solver: SolverConfig = SolverConfig(),
                   pinned: dict | None = None) -> str:
    """The table `bench walltime` prints: per world, the medians of a step's parts, the whole
    step's mean over steps with contacts as a ratio to Builtin's, and the break-even. pinned:
    {"server": cores, "simulation": cores} where --pin set them, said above the table."""
    where = (f" The server on core {','.join(map(str, pinned['server']))}, the simulations on "
             f"{','.join(map(str, pinned['simulation']))} (--pin)." if pinned else "")
    lines = [f"Seeds {seeds[0]}-{seeds[-1]} ({len(seeds)} per world); steps of {solver.dt:g} s solved to "
             f"{solver.velocity_threshold:g} N s, at most {solver.velocity_iterations} velocity iterations; "
             f"medians over steps with contacts, ms, but for the means of the whole step and their ratio. "
             f"Learned: server:{model}.{where}",
             "",
             "| world | bodies | points | builtin step | builtin solve | learned step | learned solve | round trip "
             "| first round trip | overhead | ms / iteration | break-even iterations | saved iterations | fallbacks "
             "| mean step, builtin / learned | **learned / builtin** |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in rows.items():
        b, m = r["builtin"], r["learned"]
        be = "–" if r["break_even_iterations"] is None else f"{r['break_even_iterations']:.0f}"
        lines.append(f"| {name} | {r['bodies']} | {r['median_contact_points']:.0f} | {b['step_ms']:.2f} | "
                     f"{b['solve_ms']:.2f} | {m['step_ms']:.2f} | {m['solve_ms']:.2f} | {m['round_trip_ms']:.2f} | "
                     f"{m['first_round_trip_ms']:.2f} | "
                     f"{m['overhead_ms']:.2f} | {r['ms_per_iteration']:.4f} | {be} | {r['saved_iterations']:.0f} | "
                     f"{m['fallback_steps']} | {b['mean_step_ms']:.2f} / {m['mean_step_ms']:.2f} | "
                     f"**{m['mean_step_ms'] / b['mean_step_ms']:.2f}** |")
    budgets = {name: r["budget"] for name, r in rows.items() if "budget" in r}
    if budgets:
        lines += ["", "Where the learned step's mean goes (means over steps with contacts, ms): Builtin's solve "
                      "fitted over its steps as a fixed part plus a cost a sweep (the cost a sweep above), what "
                      "the sweeps saved are worth at that cost, the served overhead (and the model's own, called "
                      "in process), and the served overhead at which the learned step's mean would be 1.5 and "
                      "1.0 times Builtin's, its collide and solve as measured.", "",
                  "| world | Builtin's solve, fixed part | the sweeps saved, worth | served overhead "
                  "| the model's own overhead | **overhead for 1.5x** | overhead for 1.0x |",
                  "|---|---|---|---|---|---|---|"]
        for name, g in budgets.items():
            fixed = "–" if g["builtin_solve_fit"] is None else f"{g['builtin_solve_fit'][0]:.2f}"
            own = rows[name].get("in_process", {}).get("overhead_mean_ms")
            allowed = g["overhead_allowed_ms"]
            lines.append(f"| {name} | {fixed} | {g['saved_ms']:.2f} | {g['learned_overhead_mean_ms']:.2f} | "
                         f"{_ms(own)} | **{allowed['1.5']:.2f}** | {allowed['1.0']:.2f} |")
    local = {name: r["in_process"] for name, r in rows.items() if "in_process" in r}
    if local:
        lines += ["", f"The same model called in this process (in-process:{model}, bench.inprocess): no gRPC, "
                      "no encoding or decoding.", "",
                  "| world | builtin step | in-process step | predict | p2g (graph: features) | inference "
                  "| g2p (graph: combination; face route: solve, admit) | overhead | served inference "
                  "| served overhead | break-even iterations | saved iterations | in-process / builtin (mean step) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for name, p in local.items():
            r = rows[name]
            be = "–" if p["break_even_iterations"] is None else f"{p['break_even_iterations']:.0f}"
            stages = " | ".join(_ms(p[k]) for k in ("p2g_ms", "inference_ms", "g2p_ms"))
            lines.append(f"| {name} | {r['builtin']['step_ms']:.2f} | {p['step_ms']:.2f} | {p['predict_ms']:.2f} | "
                         f"{stages} | {p['overhead_ms']:.2f} | {_ms(r['learned']['server_inference_ms'])} | "
                         f"{r['learned']['overhead_ms']:.2f} | {be} | "
                         f"{p['saved_iterations']:.0f} | {p['mean_step_ms'] / r['builtin']['mean_step_ms']:.2f} |")
    return "\n".join(lines) + "\n"


def _ms(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def plot(rows: dict, model: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    order = sorted(rows, key=lambda n: (rows[n]["bodies"], n != "thesis"))
    bodies = [rows[n]["bodies"] for n in order]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(bodies, [rows[n]["builtin"]["step_ms"] for n in order], "o-", color="black", label="builtin")
    ax.loglog(bodies, [rows[n]["learned"]["step_ms"] for n in order], "s-", color="tab:blue",
              label=f"server:{model}")
    ax.loglog(bodies, [rows[n]["learned"]["overhead_ms"] for n in order], "s:", color="tab:blue", lw=0.8,
              label=f"server:{model}: export + round trip + inject")
    local = [n for n in order if "in_process" in rows[n]]
    if local:
        ax.loglog([rows[n]["bodies"] for n in local], [rows[n]["in_process"]["step_ms"] for n in local], "^-",
                  color="tab:green", label=f"in-process:{model}")
        ax.loglog([rows[n]["bodies"] for n in local], [rows[n]["in_process"]["overhead_ms"] for n in local], "^:",
                  color="tab:green", lw=0.8, label=f"in-process:{model}: export + predict + inject")
    for n in order:
        if n == "thesis":
            ax.annotate("thesis", (rows[n]["bodies"], rows[n]["builtin"]["step_ms"]), fontsize=7,
                        textcoords="offset points", xytext=(4, -10))
    ax.set(xlabel="bodies", ylabel="median step time, ms (steps with contacts)",
           title="Whole step: collide + warm start + solve")
    ax.legend(fontsize=7)
    save_figure(fig, path)
