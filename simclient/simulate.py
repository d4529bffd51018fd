"""`deepcontact simulate`: one simulation with one warm start, measured.

    deepcontact simulate --scene thesis --seed 901 --warm-start server:pressure \\
        --server 127.0.0.1:50051 --out results/901.json

Per step: collide, export, get the warm start (locally, or over one
bidirectional stream for the whole simulation), inject, solve, record.
Faults never stop a simulation: a step whose reply misses the deadline, or
meets a broken or absent server, runs with Box2D's builtin warm start and
counts as a fallback, by reason; the stream reopens with backoff (counted as
reconnects) and the learned warm start comes back when the server does;
every step runs and the results file is always written (temporary name,
then rename).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from deepcontact import tls
from deepcontact.arguments import add_seed_argument
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import unknown_model
from simclient import warmstarts, worlds
from simclient.guard import Guard
from simclient.provider import Provider
from simclient.stepping import StepRecord, Stepper, columns, summarize  # noqa: F401  (StepRecord: the results' rows)
from simclient.warmstarts import make_provider

DEFAULT_DEADLINE_MS = 10.0
# Opening a stream and readying the model for a new grid: once per simulation, not a step.
DECLARE_TIMEOUT_S = 2.0


def declare_world(client, world, models=()) -> None:
    """Give `client` this simulation's world (a deepcontact.v1.World, sent first on every stream;
    simclient.worlds.world_message) and have the server ready each of `models` for its grid
    before step 0. Raises simclient.client.Refused when the server refuses one of them for this
    world, e.g. a fixed-grid model and a box of another size."""
    client.world = world
    for model in models:
        client.declare(model, DECLARE_TIMEOUT_S)


def run_simulation(spec, seed: int, provider: Provider, *, client=None, deadline_ms: float = DEFAULT_DEADLINE_MS,
                   progress=None, guard: Guard | None = None) -> dict:
    """Simulate (spec, seed) with `provider`; returns {"per_step": ..., "summary": ...}.

    spec: a project scene (simclient.scene.SceneSpec) or a user's world
    (simclient.worlds.WorldSpec). client: a simclient.client.WarmStartClient for
    `server:` providers (its world is set here); None makes every server step a
    fallback. guard: serve a server provider's answer only while it beats Box2D's
    own start (simclient.guard); None serves it every step. Raises
    simclient.client.Refused, before the first step, when the server refuses
    a model for this world: a run of fallbacks would be labelled as the model's.
    """
    engine = worlds.build(spec, seed)
    provider.prepare(engine)
    if client is not None:
        declare_world(client, worlds.world_message(spec, engine), provider.models if provider.uses_server else ())
    stepper = Stepper(engine, provider, client=client, deadline_ms=deadline_ms, guard=guard)
    records: list[StepRecord] = []
    for k in range(spec.steps):
        records.append(stepper.step(k))
        if progress is not None:
            progress(k)
    result = {"per_step": columns(records), "summary": summarize(records)}
    if stepper.refusal:
        result["refusal"] = stepper.refusal
    if provider.picks:
        result["trials"] = [list(t) for t in provider.trials]
        result["reach"] = [list(t) for t in provider.reach]
        if getattr(provider, "notes", None):
            result["notes"] = [np.asarray(t).tolist() for t in provider.notes]  # plain numbers: the results are JSON
    return result


# -- command -----------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    worlds.add_world_arguments(parser)
    add_seed_argument(parser, "world seed (benchmarks use 900-999)", required=True)
    parser.add_argument("--warm-start", required=True, metavar="W",
                        help=f"one of {warmstarts.usage()} (e.g. server:default, server:random, server:bad, "
                             "server:grid-identity)")
    parser.add_argument("--server", metavar="HOST:PORT",
                        help="warm-start server for server:MODEL (any gRPC target, e.g. dns:///server:50051, or unix:PATH for a server on a Unix socket)")
    parser.add_argument("--deadline-ms", type=float, default=DEFAULT_DEADLINE_MS,
                        help=f"per-step deadline for the server's reply; later replies fall back to builtin "
                             f"(default {DEFAULT_DEADLINE_MS:g})")
    parser.add_argument("--allow-fallback", action="store_true",
                        help="if the server cannot be reached at start-up, simulate anyway with builtin fallbacks")
    parser.add_argument("--connect-timeout", type=float, default=5.0, help="seconds to wait for the server at start-up")
    tls.add_client_arguments(parser)
    parser.add_argument("--no-guard", action="store_true",
                        help="serve the server's answer on every step; by default a guard serves it only while it "
                             "beats Box2D's own warm start on this simulation's steps, priced by trial solves "
                             "(under 5 %% of Box2D's sweeps; docs/worlds.md)")
    parser.add_argument("--out", type=Path, required=True, help="results file (JSON)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def check_writable(path: Path) -> None:
    """Fail before simulating if the results cannot be written there."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
        pass


def connect(target: str, model: str, *, connect_timeout: float, allow_fallback: bool, tls=(None, None, None)):
    """A client for `target` that serves `model` ("A+B": each of them), or None (fallbacks only).
    tls: (ca, cert, key) PEM files for a TLS server (deepcontact.tls), all None for plaintext.
    Raises SystemExit-worthy ValueError/ConnectionError with a message."""
    from deepcontact.tls import client_credentials
    from simclient.client import WarmStartClient

    client = WarmStartClient(target, credentials=client_credentials(*tls))
    if not client.wait_ready(connect_timeout):
        client.close()
        if allow_fallback:
            print(f"warning: no server at {target}; every step falls back to builtin", file=sys.stderr)
            return None
        raise ConnectionError(f"no warm-start server at {target} (waited {connect_timeout:g} s); "
                              "start one with `deepcontact serve`, or pass --allow-fallback")
    names = [m.name for m in client.list_models()]
    missing = [m for m in model.split("+") if m not in names]
    if missing:
        client.close()
        raise ValueError(f"the server at {target} has {unknown_model(missing[0], names)}")
    return client


def tls_files(args: argparse.Namespace) -> tuple:
    """(ca, cert, key) of the --tls-* flags (deepcontact.tls.add_client_arguments), as str or None:
    what travels to a worker that dials on its own."""
    return tuple(None if p is None else str(p) for p in (args.tls_ca, args.tls_cert, args.tls_key))


def run(args: argparse.Namespace) -> int:
    prog = " ".join(("deepcontact", *getattr(args, "_words", ("simulate",))))  # the words that ran this command
    try:
        spec = worlds.spec_from_args(args)
        if isinstance(spec, worlds.WorldSpec):  # a function that raises or returns no world: said now, nothing written
            worlds.build_user_world(spec.source, args.seed)
        provider = make_provider(args.warm_start)
        if provider.uses_server and not args.server:
            raise ValueError(f"{args.warm_start} needs --server HOST:PORT (start one with `deepcontact serve`)")
        tls.client_credentials(*tls_files(args))  # unreadable or mismatched files: said before anything runs
        check_writable(args.out)
    except (ValueError, OSError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    client = None
    if provider.uses_server:
        try:
            client = connect(args.server, "+".join(provider.models), connect_timeout=args.connect_timeout,
                             allow_fallback=args.allow_fallback, tls=tls_files(args))
        except (ValueError, ConnectionError) as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 2
    from simclient.client import Refused

    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=spec.steps, unit="step", desc=f"{args.warm_start} seed {args.seed}", file=sys.stderr)
    try:
        result = run_simulation(spec, args.seed, provider, client=client, deadline_ms=args.deadline_ms,
                                progress=(lambda k: bar.update(1)) if bar else None,
                                guard=None if args.no_guard else Guard())
    except ValueError as exc:  # a user's world that cannot be built for this seed
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    except Refused as exc:
        print(f"{prog}: the server at {args.server} refuses {args.warm_start} for this world: {exc}",
              file=sys.stderr)
        return 2
    finally:
        if bar:
            bar.close()
        if client is not None:
            client.close()
    result.update({"scene": worlds.spec_to_dict(spec), "seed": args.seed, "warm_start": args.warm_start,
                   "server": args.server, "deadline_ms": args.deadline_ms, "guard": not args.no_guard,
                   "command": "deepcontact " + " ".join(sys.argv[1:])})
    write_json_atomic(args.out, result)
    print(f"{args.warm_start} seed {args.seed}: {summary_line(result['summary'])} -> {args.out}")
    return 0


def summary_line(s: dict) -> str:
    """One line from summarize()'s dict; its statistics are None where no step had contacts."""
    if not s["steps_with_contacts"]:
        text = f"{s['steps']} steps, no steps with contacts (nothing to warm-start)"
    else:
        text = (f"mean {s['mean_velocity_iterations']:.1f}, median {s['median_velocity_iterations']:.0f} "
                f"velocity iterations over {s['steps_with_contacts']} steps with contacts")
    if s["p50_latency_ms"] is not None:
        text += f", latency p50 {s['p50_latency_ms']:.2f} ms p99 {s['p99_latency_ms']:.2f} ms"
    text += f", {s['fallback_steps']} fallbacks"
    if s["fallbacks_by_reason"]:
        text += " (" + ", ".join(f"{n} {reason}" for reason, n in sorted(s["fallbacks_by_reason"].items())) + ")"
    if s["reconnects"]:
        text += f", {s['reconnects']} reconnects"
    if s["guard_probes"]:
        text += (f"; guard: learned start on {s['learned_steps']} steps, Box2D's on {s['guarded_steps']}, "
                 f"{s['guard_probes']} probes, {s['guard_switches']} switches")
    return text
