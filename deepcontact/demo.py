"""`deepcontact demo` (and `make demo`): the main job in one command.

Starts `deepcontact serve` with the shipped models on a free loopback port,
waits for its health check, runs the thesis world on a held-out seed with
`none`, `builtin` and the shipped model through the server, prints the table
(iterations per step, round-trip latency, fallbacks), writes the figures to
the folder it names, and stops the server, also when a step fails. It is
`deepcontact bench iterations` with a fixed small selection.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench import iterations


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=901, help="held-out thesis seed (default 901)")
    parser.add_argument("--model", default="pressure", help="shipped model to compare (default pressure)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")
    parser.add_argument("--out", type=Path, default=Path("demo-results"), help="folder for the table and figures (default demo-results/)")


def run(args: argparse.Namespace) -> int:
    if not (args.models / f"{args.model}.onnx").exists():
        print(f"deepcontact demo: no model {args.model!r} in {args.models}/ "
              f"(the shipped one is rebuilt by `make default-model`)", file=sys.stderr)
        return 2
    parser = argparse.ArgumentParser()
    iterations.add_arguments(parser)
    bench_args = parser.parse_args([
        "--seeds", str(args.seed), "--warm-starts", f"none,builtin,server:{args.model}",
        "--models", str(args.models), "--out", str(args.out),
    ])
    print(f"deepcontact demo: thesis world, seed {args.seed}; warm starts none, builtin and "
          f"server:{args.model} (a server on a free loopback port)", file=sys.stderr)
    code = iterations.run(bench_args)
    if code == 0:
        print(f"figures and table in {args.out}/ (fig20_contacts_iterations.png, fig21_convergence.png, "
              f"fig26_mse.png, results.md, summary.json)")
    return code
