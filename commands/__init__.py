"""The `deepcontact` command: the product's command table (python -m commands works too).

Each entry names the module that does the work (deepcontact.cli: `add_arguments(parser)`
and `run(args) -> int`, imported only when its subcommand runs, so `deepcontact --help` stays
fast). The research instruments are the `lab` group, whose table is lab.commands, loaded only
when `deepcontact lab ...` is parsed: the product never imports the lab.
"""

from __future__ import annotations

from deepcontact import __version__
from deepcontact.cli import Command, Group, build_parser as _build_parser, main as _main

COMMANDS = [
    Command(("demo",), "bench.demo", "run the main job: server, simulations, results table"),
    Command(("generate",), "training.generate", "record simulations into an HDF5 training file"),
    Command(("train",), "training.train", "fit a grid CNN (Pressure, U-Net or Peak) on recorded simulations (resumable)"),
    Command(("train-graph",), "training.train_graph",
            "fit the contact-graph model (message passing on the contact points) and export it"),
    Command(("export",), "training.export", "export a finished training run to ONNX with its model card"),
    Command(("evaluate",), "training.evaluate", "score exported models on recorded data with ONNX Runtime"),
    Command(("serve",), "server.serve", "serve warm starts over gRPC (models/ and the providers)"),
    Command(("health",), "deepcontact.health", "exit 0 if a warm-start server reports SERVING"),
    Command(("simulate",), "simclient.simulate", "one simulation with one warm start; iterations and latency to JSON"),
    Command(("transfer-table",), "training.transfer_table",
            "reproduce thesis Table 1 (particle-grid-particle round-trip error)"),
    Command(("bench", "engine"), "bench.engine", "time export, warm-start injection and the instrumented solve"),
    Command(("bench", "iterations"), "bench.iterations", "every warm start on the same held-out worlds: table and figures"),
    Command(("bench", "load"), "bench.load", "latency and throughput with many simulations streaming at once"),
    Command(("bench", "scale"), "bench.scale", "simulations per second per added worker or Ray CPU; same answers on each"),
    Command(("bench", "soak"), "bench.soak", "a long load on one server: nothing lost, memory flat (RSS over time)"),
    Command(("bench", "server"), "bench.server",
            "per-stage server cost of the shipped model on thesis steps (target: 300 us outside inference)"),
    Command(("bench", "transfer"), "bench.transfer", "time P2G and G2P on a settled thesis world"),
    Command(("bench", "walltime"), "bench.walltime",
            "whole step time with builtin, a served model and the same model in process, and the break-even, per world size"),
    Group(("lab",), "lab.commands",
          "research instruments: oracles, probes and composites of warm starts, analysis benches (lab/README.md)"),
]
GROUPS = {("bench",): "benchmarks"}


def build_parser():
    """The `deepcontact` parser (argparse), the lab group's commands loaded only when it is parsed."""
    return _build_parser(
        COMMANDS, prog="deepcontact", version=f"deepcontact {__version__}", groups=GROUPS,
        description=("Warm-start Box2D's contact solver with a neural network served over gRPC: "
                     "a message-passing network on the contact points (the default) or the thesis's "
                     "CNN on grids."))


def main(argv: list[str] | None = None) -> int:
    """Run `deepcontact ARGV...`; the exit status."""
    return _main(build_parser(), argv)
