"""The `deepcontact` command.

Each subcommand lives in the module that does the work and exposes
`add_arguments(parser)` and `run(args) -> int`; the modules are imported only
when their subcommand runs, so `deepcontact --help` stays fast (no TensorFlow).
A command ends with its summary or a one-line error, never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# (path of words, module, one-line help)
COMMANDS: list[tuple[tuple[str, ...], str, str]] = [
    (("demo",), "bench.demo", "run the main job: server, simulations, results table"),
    (("generate",), "training.generate", "record simulations into an HDF5 training file"),
    (("train",), "training.train", "fit a grid CNN (Pressure, U-Net or Peak) on recorded simulations (resumable)"),
    (("train-graph",), "training.train_graph", "fit the contact-graph model (message passing on the contact points) and export it"),
    (("export",), "training.export", "export a finished training run to ONNX with its model card"),
    (("evaluate",), "training.evaluate", "score exported models on recorded data with ONNX Runtime"),
    (("serve",), "server.serve", "serve warm starts over gRPC (models/ and the providers)"),
    (("health",), "deepcontact.health", "exit 0 if a warm-start server reports SERVING"),
    (("simulate",), "simclient.simulate", "one simulation with one warm start; iterations and latency to JSON"),
    (("transfer-table",), "training.transfer_table", "reproduce thesis Table 1 (particle-grid-particle round-trip error)"),
    (("bench", "admission"), "bench.admission", "what admitting a motion (nearest_admissible) costs a step, beside Box2D's solve"),
    (("bench", "corrections"), "bench.corrections", "a served model's corrections against the solver's, by size: where it errs"),
    (("bench", "face-solve"), "bench.face_solve", "the face route's solve by step size: its system, the dual solve against gelsy, the admission"),
    (("bench", "faces"), "bench.faces", "a served model's answer read as an active set (open, sticks, slides): how many labels a step are wrong"),
    (("bench", "engine"), "bench.engine", "time export, warm-start injection and the instrumented solve"),
    (("bench", "generate"), "bench.generate", "what recording simulations costs over running them"),
    (("bench", "graph-size"), "bench.graph_size", "a contact-graph model's inference against the step's points and bodies"),
    (("bench", "inference"), "bench.inference", "ONNX Runtime levers on a grid model's inference: session options, int8, cropped grids"),
    (("bench", "iterations"), "bench.iterations", "every warm start on the same held-out worlds: table and figures"),
    (("bench", "load"), "bench.load", "latency and throughput with many simulations streaming at once"),
    (("bench", "scale"), "bench.scale", "simulations per second per added worker or Ray CPU; same answers on each"),
    (("bench", "soak"), "bench.soak", "a long load on one server: nothing lost, memory flat (RSS over time)"),
    (("bench", "order"), "bench.order", "does the order of the solver's sweep choose its answer? a Gauss-Seidel replica in several orders"),
    (("bench", "server"), "bench.server", "per-stage server cost of the shipped model on thesis steps (target: 300 us outside inference)"),
    (("bench", "step-gate"), "bench.step_gate", "a per-step gate between a model's warm start and Box2D's, fitted on some seeds (of one world or several), priced on others beside a race of the two starts' first sweeps"),
    (("bench", "surrogate"), "bench.surrogate", "does the training loss's score of a step follow the iterations a model saves there?"),
    (("bench", "transfer"), "bench.transfer", "time P2G and G2P on a settled thesis world"),
    (("bench", "walltime"), "bench.walltime", "whole step time with builtin, a served model and the same model in process, and the break-even, per world size"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deepcontact",
        description=("Warm-start Box2D's contact solver with a neural network served over gRPC: "
                     "a message-passing network on the contact points (the default) or the thesis's "
                     "CNN on grids."),
    )
    from deepcontact import __version__

    parser.add_argument("--version", action="version", version=f"deepcontact {__version__}")
    groups: dict[tuple[str, ...], argparse._SubParsersAction] = {
        (): parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    }
    group_help = {("bench",): "benchmarks (admission, corrections, engine, face-solve, faces, generate, graph-size, inference, iterations, load, order, scale, server, soak, step-gate, surrogate, transfer, walltime)"}
    for words, module, help_text in COMMANDS:
        for depth in range(1, len(words)):
            prefix = words[:depth]
            if prefix not in groups:
                sub = groups[prefix[:-1]].add_parser(prefix[-1], help=group_help.get(prefix, ""))
                groups[prefix] = sub.add_subparsers(dest=f"command_{depth}", metavar="COMMAND", required=True)
        sub = groups[words[:-1]].add_parser(words[-1], help=help_text, description=help_text)
        sub.set_defaults(_module=module, _words=words)
        _LazyArguments.attach(sub, module)
    return parser


class _LazyArguments:
    """Adds a subcommand's own arguments only when that subcommand is parsed."""

    @staticmethod
    def attach(sub: argparse.ArgumentParser, module: str) -> None:
        original = sub.parse_known_args

        def parse_known_args(args=None, namespace=None):
            if not getattr(sub, "_deepcontact_loaded", False):
                importlib.import_module(module).add_arguments(sub)
                sub._deepcontact_loaded = True
            return original(args, namespace)

        sub.parse_known_args = parse_known_args


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        # Commands answer what they expect with their own one-line errors; this is
        # for what they did not expect (a bug). DEEPCONTACT_DEBUG=1 shows where.
        if os.environ.get("DEEPCONTACT_DEBUG"):
            raise
        print(f"deepcontact {' '.join(args._words)}: unexpected error: {type(exc).__name__}: {exc} "
              "(DEEPCONTACT_DEBUG=1 shows the traceback)", file=sys.stderr)
        return 1
