"""`deepcontact bench scale`: throughput per added worker, and the same answers on every backend.

    deepcontact bench scale --seeds 1-64 --repeats 3 --json bench/results/scale.json

Runs the commands a user runs, as child processes, one configuration after
the other within each repeat (so a busy machine slows all of them alike):

    generate          --workers 1 (this process), --workers 2, --ray --workers 1, --ray --workers 2
    bench iterations  --workers 1, --workers 2, --ray --workers 2, against
                      `deepcontact serve` started here (its start-up is not timed;
                      --replicas K starts K of them, the streams spread over them
                      by the client's round_robin)

Any other count is a configuration too (`--configs workers=1,workers=4,workers=16`
on a machine with more cores): `workers=N` is `--workers N`, `ray=N` is
`--ray --workers N`.

`--ray` starts a local Ray for each run, and its start-up is in the time, as
a user waits for it. Per configuration: the median wall time, simulations per
second, and the speed-up over one worker of the same command (ratio of the
medians; and the median of the ratios taken within one repeat). Every run's
answers are compared with the first run's: the HDF5 contents timings aside
(training.dataset.differences), the iteration figures of summary.json
(bench.iterations.TIMING_FIELDS aside). The machine's 1-minute load average
after each run is reported beside the times: on a shared machine it says
how many cores the runs really had.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from deepcontact.arguments import add_models_argument
from deepcontact.io import write_json_atomic
from simclient import seeds as seed_ranges

# The configurations measured unless --configs names others.
DEFAULT_CONFIGS = {"generate": ("workers=1", "workers=2", "ray=1", "ray=2"),
                   "iterations": ("workers=1", "workers=2", "ray=2")}
COMMANDS = tuple(DEFAULT_CONFIGS)


def config_flags(config: str) -> list[str]:
    """The command-line flags of a configuration: "workers=N" -> --workers N, "ray=N" -> --ray --workers N.
    Raises ValueError for anything else."""
    backend, _, count = config.partition("=")
    if backend not in ("workers", "ray") or not count.isdigit() or int(count) < 1:
        raise ValueError(f"unknown configuration {config!r} (workers=N or ray=N, N >= 1)")
    return (["--ray"] if backend == "ray" else []) + ["--workers", str(int(count))]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seeds", default="1-64", help="generate's training seeds (default 1-64)")
    parser.add_argument("--iteration-seeds", default="901-908", help="bench iterations' seeds (default 901-908)")
    parser.add_argument("--warm-starts", default="builtin,server:pressure",
                        help="bench iterations' warm starts (default builtin,server:pressure)")
    add_models_argument(parser, "models for the server")
    parser.add_argument("--steps", type=int, help="steps per simulation (default: the thesis world's 250)")
    parser.add_argument("--repeats", type=int, default=3, help="runs of every configuration (default 3)")
    parser.add_argument("--commands", default="generate,iterations", help="which to measure (default generate,iterations)")
    parser.add_argument("--configs",
                        help="which configurations: workers=N (a process pool of N) or ray=N (a local Ray with N "
                             "CPUs), comma-separated (default workers=1,workers=2,ray=1,ray=2 for generate and "
                             "workers=1,workers=2,ray=2 for iterations)")
    parser.add_argument("--replicas", type=int, default=1,
                        help="bench iterations: deepcontact serve processes, the streams spread over them (default 1)")
    parser.add_argument("--json", metavar="FILE", help="write the results here as JSON")


def run(args: argparse.Namespace) -> int:
    commands = [c.strip() for c in args.commands.split(",") if c.strip()]
    configs = [c.strip() for c in args.configs.split(",") if c.strip()] if args.configs else None
    try:
        seed_ranges.parse_seeds(args.seeds)
        seed_ranges.parse_seeds(args.iteration_seeds)
        unknown = sorted(set(commands) - set(COMMANDS))
        if unknown:
            raise ValueError(f"unknown {', '.join(unknown)} (commands: {', '.join(COMMANDS)})")
        for config in configs or ():
            config_flags(config)
        if args.repeats < 1:
            raise ValueError("--repeats must be >= 1")
        if args.replicas < 1:
            raise ValueError("--replicas must be >= 1")
    except ValueError as exc:
        print(f"deepcontact bench scale: {exc}", file=sys.stderr)
        return 2
    results = {}
    with tempfile.TemporaryDirectory(prefix="deepcontact-scale-") as tmp:
        for command in commands:
            chosen = configs or list(DEFAULT_CONFIGS[command])
            try:
                results[command] = _speedups(_measure(command, chosen, args, Path(tmp)))
            except RuntimeError as exc:
                print(f"deepcontact bench scale: {exc}", file=sys.stderr)
                return 1
    for command, rows in results.items():
        print(_table(command, rows))
    if args.json:
        write_json_atomic(args.json, {"command": "deepcontact " + " ".join(sys.argv[1:]), "results": results})
    same = all(row["same_answers"] for rows in results.values() for row in rows.values())
    print("every run gave the same answers as the first" if same else "the answers differ between runs (table above)")
    return 0 if same else 1


def _measure(command: str, configs: list[str], args, tmp: Path) -> dict:
    """{config: {"seconds": [wall s per repeat], "load": [1-minute load average after each],
    "simulations": n, "same_answers": bool}}."""
    steps = ["--steps", str(args.steps)] if args.steps else []
    servers = []
    if command == "iterations" and "server:" in args.warm_starts:
        from server.process import ServerProcess

        for _ in range(args.replicas):
            servers.append(ServerProcess(args.models).start())
    # One address, or a list the client's round_robin spreads its streams over.
    target = (servers[0].address if len(servers) == 1
              else "ipv4:" + ",".join(s.address for s in servers) if servers else None)
    try:
        if command == "generate":
            n = len(seed_ranges.parse_seeds(args.seeds))
            base = ["generate", "--seeds", args.seeds, "--quiet", *steps]
        else:
            n = len(seed_ranges.parse_seeds(args.iteration_seeds)) * len(args.warm_starts.split(","))
            # A long deadline: a step that misses it falls back to builtin and changes the answers.
            base = ["bench", "iterations", "--seeds", args.iteration_seeds, "--warm-starts", args.warm_starts,
                    "--deadline-ms", "1000", "--quiet", *steps] + (["--server", target] if target else [])
        rows = {c: {"seconds": [], "load": [], "simulations": n, "same_answers": True} for c in configs}
        reference = None
        for r in range(args.repeats):
            for config in configs:
                run_dir = tmp / f"{command}-{config}-{r}"
                out = run_dir / "train.h5" if command == "generate" else run_dir
                argv = [*base, "--out", str(out), *config_flags(config)]
                t0 = time.perf_counter()
                done = subprocess.run([sys.executable, "-m", "commands", *argv], capture_output=True, text=True)
                rows[config]["seconds"].append(time.perf_counter() - t0)
                # The machine may be shared: its load during the run says how many cores were ours.
                rows[config]["load"].append(os.getloadavg()[0])
                if done.returncode != 0:
                    last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
                    raise RuntimeError(f"deepcontact {' '.join(argv)} failed: {last}")
                answers = _answers(command, out)
                if reference is None:
                    reference = answers
                elif not _same(command, reference, answers):
                    rows[config]["same_answers"] = False
    finally:
        for server in servers:
            server.stop()
    return rows


def _answers(command: str, out: Path):
    """What must not depend on the backend: the file (generate) or the iteration figures."""
    if command == "generate":
        return out
    from bench.iterations import TIMING_FIELDS

    summary = json.loads((out / "summary.json").read_text())["warm_starts"]
    return {name: {k: v for k, v in s.items() if k not in TIMING_FIELDS} for name, s in summary.items()}


def _same(command: str, a, b) -> bool:
    if command == "generate":
        from training.dataset import differences

        return differences(a, b) == []
    return a == b


def _speedups(rows: dict) -> dict:
    """Adds median_s, and for more than one worker the speed-up over one: over one worker of the
    same backend (ray=1 for ray=N), or over one process when that was not measured."""
    for config, row in rows.items():
        row["median_s"] = statistics.median(row["seconds"])
        backend, _, count = config.partition("=")
        one = None
        if int(count) > 1:
            same_backend = f"{backend}=1"
            row["against"] = same_backend if same_backend in rows else "workers=1"
            one = rows.get(row["against"])
        if one is None:
            row["against"] = None
            continue
        row["speedup"] = statistics.median(one["seconds"]) / row["median_s"]
        row["median_of_ratios"] = statistics.median(a / b for a, b in zip(one["seconds"], row["seconds"]))
    return rows


def _table(command: str, rows: dict) -> str:
    first = next(iter(rows.values()))
    lines = [f"{command}: {first['simulations']} simulations per run, {len(first['seconds'])} runs per configuration",
             "", "| configuration | median wall s | simulations/s | speed-up | against | median of per-run ratios "
             "| same answers | load average |", "|---|---|---|---|---|---|---|---|"]
    for config, row in rows.items():
        speedup = f"{row['speedup']:.2f}x" if row["against"] else "–"
        per_run = f"{row['median_of_ratios']:.2f}x" if row["against"] else "–"
        lines.append(f"| {config} | {row['median_s']:.1f} | {row['simulations'] / row['median_s']:.2f} | {speedup} | "
                     f"{row['against'] or '–'} | {per_run} | {'yes' if row['same_answers'] else 'NO'} | "
                     f"{statistics.median(row['load']):.1f} |")
    return "\n".join(lines) + "\n"
