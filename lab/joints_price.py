"""`deepcontact lab joints-price`: does declining at jointed points pay? A model priced on
Box2D's own states of a world with joints, with the joints sent and with them withheld.

    deepcontact lab joints-price --world examples/chain.py:build --seeds 850-869 --model default

With the joints sent (StepRequest.joint_bodies), the server answers Box2D's own start at every
point on a jointed body and the model the rest (server/joints.py); withheld, the model answers
every point, as for a client older than the field. Each step is priced both ways by the
engine's trial solves from Box2D's trajectory (`price:`), so the two are compared on the very
same states. Prints each way's sweeps over Box2D's, with the 95 % bootstrap interval over seeds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bench.stats import ratio_interval


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--world", required=True, metavar="PATH.py:FUNCTION", help="a world with joints")
    parser.add_argument("--seeds", default="850-869", help="seeds (default the choosing seeds 850-869)")
    parser.add_argument("--steps", type=int, default=250, help="steps per simulation (default 250)")
    parser.add_argument("--model", default="default", help="the served model (default: default)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="model folder (default models/)")


def price(spec, seed: int, model: str, address: str, send_joints: bool) -> tuple[np.ndarray, np.ndarray]:
    """(Box2D's sweeps, the model's) at each step with contacts of Box2D's own trajectory."""
    import lab  # noqa: F401  (registers price:)
    from simclient.client import WarmStartClient
    from simclient.simulate import run_simulation
    from simclient.warmstarts import make_provider

    with WarmStartClient(address) as client:
        engine_joints = _withheld() if not send_joints else None
        try:
            result = run_simulation(spec, seed, make_provider(f"price:server:{model}"), client=client,
                                    deadline_ms=1000)
        finally:
            if engine_joints is not None:
                engine_joints()
    trials = np.array(result["trials"], float).reshape(-1, 2)
    return trials[:, 0], trials[:, 1]


def _withheld():
    """Make Engine.joints return none (as a client older than the joints' field sends); returns
    the function that puts it back."""
    from simclient.engine import Engine

    real = Engine.joints
    Engine.joints = lambda self: np.zeros((0, 2), np.int32)

    def restore():
        Engine.joints = real

    return restore


def world_and_seeds(args: argparse.Namespace, command: str):
    """(WorldSpec, seeds) of --world, --steps and --seeds, or None once a one-line error naming
    `command` is printed (a world that cannot be loaded, seeds that do not parse)."""
    from simclient import seeds as seed_ranges
    from simclient.worlds import WorldSpec

    try:
        seeds = seed_ranges.parse_seeds(args.seeds)
        spec = WorldSpec(args.world, steps=args.steps)
        spec.validate()
    except ValueError as exc:
        print(f"deepcontact lab {command}: {exc}", file=sys.stderr)
        return None
    return spec, seeds


def run(args: argparse.Namespace) -> int:
    from server.process import ServerProcess

    parsed = world_and_seeds(args, "joints-price")
    if parsed is None:
        return 2
    spec, seeds = parsed
    rows = {}
    with ServerProcess(args.models, local_socket=True) as server:
        for sent in (True, False):
            pairs = [price(spec, s, args.model, server.address, sent) for s in seeds]
            rows["joints sent" if sent else "joints withheld"] = ratio_interval([p[1] for p in pairs],
                                                                               [p[0] for p in pairs])
    print(f"`{args.world}`, seeds {args.seeds}, server:{args.model} on Box2D's own states (price:): "
          "its sweeps over Box2D's")
    print("| joints | / builtin |\n|---|---|")
    for label, ratio in rows.items():
        print(f"| {label} | {ratio.text()} |")
    return 0
