"""`deepcontact demo` (and `make demo`): the main job in one command.

Starts `deepcontact serve` with the shipped models on a Unix socket of its own,
waits for its health check, runs the thesis world on a held-out seed with
`none`, `builtin` and the shipped models through the server (the thesis-style
`pressure` and `default`, the best measured variant: models/default.json says
which), prints the table
(iterations per step, round-trip latency, fallbacks) and, for the last model
served again as a `shadow:`, every model's and builtin's iterations on its very
states (one seed's closed-loop ratio is mostly where the trajectory went), writes the figures to
the folder it names, and stops the server, also when a step fails. It is
`deepcontact bench iterations` with a fixed small selection, so it lives with
the benchmarks, above the parts it composes (server, simclient, deepcontact).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench import iterations
from deepcontact.modelcard import ModelCard


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seed", type=int, default=901, help="held-out thesis seed (default 901)")
    parser.add_argument("--model", default="pressure,default",
                        help="shipped models to compare, comma-separated (default pressure,default; "
                             "default is an alias of the best measured variant)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")
    parser.add_argument("--out", type=Path, default=Path("demo-results"), help="folder for the table and figures (default demo-results/)")


def run(args: argparse.Namespace) -> int:
    names = [m.strip() for m in args.model.split(",") if m.strip()]
    missing = [m for m in names if not (args.models / f"{m}.json").exists()]
    if missing:
        print(f"deepcontact demo: no model card {', '.join(missing)} in {args.models}/ "
              f"(models/pressure.onnx is rebuilt by `make default-model`)", file=sys.stderr)
        return 2
    servers = ",".join(f"server:{m}" for m in names)
    # One seed's closed-loop ratio is mostly where its trajectory went; the shadow serves the
    # last model again and prices builtin and the others on its very states (trial solves).
    shadow = "shadow:" + "+".join(f"server:{m}" for m in [names[-1], *names[:-1]])
    for m in names:
        target = ModelCard.alias_target(args.models / f"{m}.json")
        if target:
            print(f"deepcontact demo: {m} is {target} ({args.models}/{m}.json)", file=sys.stderr)
    parser = argparse.ArgumentParser()
    iterations.add_arguments(parser)
    bench_args = parser.parse_args([
        "--seeds", str(args.seed), "--warm-starts", f"none,builtin,{servers},{shadow}",
        "--models", str(args.models), "--out", str(args.out),
    ])
    print(f"deepcontact demo: thesis world, seed {args.seed}; warm starts none, builtin, {servers}, and "
          f"{shadow} (the same states priced for each) (a server on a Unix socket of its own)", file=sys.stderr)
    code = iterations.run(bench_args)
    if code == 0:
        print(f"figures and table in {args.out}/ (fig20_contacts_iterations.png, fig21_convergence.png, "
              f"fig26_mse.png, results.md, summary.json)")
    return code
