"""What `python examples/NAME.py` runs: the world with Box2D's own warm start, then through a
WarmStartSession, on one seed; a table of both. Starts a server on the shipped models (a Unix
socket of its own) unless --server names one."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(build, description: str, argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--server", help="a running `deepcontact serve` (default: start one on models/)")
    parser.add_argument("--model", default="default", help="the model to ask (default: default)")
    parser.add_argument("--seed", type=int, default=901, help="the world's seed (default 901)")
    parser.add_argument("--steps", type=int, default=250, help="steps (default 250)")
    parser.add_argument("--dt", type=float, default=0.01, help="time step, s (default 0.01)")
    parser.add_argument("--no-guard", action="store_true", help="serve the model's answer on every step")
    args = parser.parse_args(argv)

    from server.process import ServerProcess
    from simclient import WarmStartSession
    from simclient.engine import Engine, SolverConfig
    from simclient.stepping import summarize

    server = None if args.server else ServerProcess(ROOT / "models", local_socket=True).start()
    try:
        builtin = Engine(build(args.seed), SolverConfig(dt=args.dt))
        its = [s.velocity_iterations for s in (builtin.step() for _ in range(args.steps)) if s.contact_points]
        with WarmStartSession(build(args.seed), args.server or server.address, model=args.model,
                              guard=not args.no_guard) as session:
            for _ in range(args.steps):
                session.step(args.dt, 1000, 1000)
            learned = session.summary()
    finally:
        if server is not None:
            server.stop()
    base = sum(its) / len(its) if its else float("nan")
    print(f"seed {args.seed}, {args.steps} steps of {args.dt} s, mean velocity iterations over steps with contacts:")
    print(f"  builtin                     {base:7.1f}")
    guard = "guard off" if args.no_guard else "guard on"
    print(f"  server:{args.model} ({guard}) {learned['mean_velocity_iterations'] or float('nan'):7.1f}"
          f"   / builtin {(learned['mean_velocity_iterations'] or float('nan')) / base:.3f}")
    if not args.no_guard:
        print(f"  the learned start on {learned['learned_steps']} steps, Box2D's on {learned['guarded_steps']} "
              f"({learned['guard_probes']} probes, {learned['guard_switches']} switches)")
    return 0


if __name__ == "__main__":
    sys.exit("run an example: python examples/pyramid.py (or stack, chain, car)")
