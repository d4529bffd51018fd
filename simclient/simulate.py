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
import collections
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from deepcontact import wire
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import unknown_model
from simclient.scene import SceneSpec, add_scene_arguments, build_world, spec_from_args, spec_to_dict
from simclient.provider import Provider, point_friction
from simclient.warmstarts import make_provider

DEFAULT_DEADLINE_MS = 10.0
# Opening a stream and readying the model for a new grid: once per simulation, not a step.
DECLARE_TIMEOUT_S = 2.0


@dataclasses.dataclass
class StepRecord:
    contact_points: int
    velocity_iterations: int
    position_iterations: int
    residual_trace: list[float]
    mse_normal: float | None
    mse_tangent: float | None
    latency_ms: float | None  # round trip to the server; None for local warm starts
    server_us: dict | None  # the server's stage timings
    client_us: float  # export + encode + decode + inject, microseconds
    provider_ms: float  # time to obtain the warm start (round trip or local computation)
    solve_ms: float
    collide_ms: float  # the engine's collision step, before the warm start
    export_ms: float  # reading bodies and contact points out of the engine
    inject_ms: float  # handing the warm start to the engine (0 without one)
    fallback: bool
    fallback_reason: str | None  # StepFailed.reason, or NO_SERVER; None when not a fallback
    reconnect: bool  # this step's request went on a stream reopened after the first
    served_by: str | None = None  # the reply's served_by: another card's answer than the model's route


@dataclasses.dataclass
class _Served:
    """What one step got from the server: the warm start (None: Box2D's own) and what it cost."""

    warm: tuple[np.ndarray, np.ndarray] | None = None
    latency_ms: float | None = None  # the round trip, or until the step failed
    server_us: dict | None = None  # the server's stage timings
    codec_s: float = 0.0  # encoding the request and decoding the reply, seconds
    fallback_reason: str | None = None  # set: the step fell back to builtin
    reconnect: bool = False
    served_by: str | None = None  # the reply's served_by, where set


class _Laps:
    """Seconds between successive calls of lap(): one step's parts, timed in order."""

    def __init__(self):
        self._t = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        seconds, self._t = now - self._t, now
        return seconds


def _ask_server(client, provider: Provider, engine, k: int, bodies, points, timeout: float) -> _Served:
    """Step k's warm start from the server, or a counted fallback."""
    from simclient.client import StepFailed

    if len(points) == 0:
        return _Served()  # nothing to warm-start; no round trip
    if client is None:
        return _Served(fallback_reason="NO_SERVER")
    oracle = engine.oracle() if provider.sends_oracle else None
    t0 = time.perf_counter()
    request = wire.encode_step(k, provider.model, bodies, points, builtin=points["builtin"], impulses=oracle,
                               friction=point_friction(engine.body_friction(), points))
    t1 = time.perf_counter()
    streams = client.reconnects
    try:
        reply = client.step(request, timeout)
    except StepFailed as exc:
        return _Served(latency_ms=1e3 * (time.perf_counter() - t1), fallback_reason=exc.reason,
                       reconnect=client.reconnects > streams)
    t2 = time.perf_counter()
    warm = wire.decode_impulses(reply)
    t3 = time.perf_counter()
    tm = reply.timings
    return _Served(warm=warm, latency_ms=1e3 * (t2 - t1), codec_s=(t1 - t0) + (t3 - t2),
                   server_us={"decode": tm.decode_us, "p2g": tm.p2g_us, "inference": tm.inference_us,
                              "g2p": tm.g2p_us, "total": tm.total_us},
                   reconnect=client.reconnects > streams, served_by=reply.served_by or None)


def _pick(provider, client, engine, k: int, bodies, points, timeout: float) -> _Served:
    """A pick:/shadow:/mean:/price:/split:/boost:/admit:/graft:/feedback: oracle's warm start for step k: every candidate asked and
    priced by trial solves, the cheapest (or the first, their mean, builtin) served. A server candidate that fell back is priced as builtin, and
    the step counts as a fallback."""
    if len(points) == 0:
        return _Served()
    warms, reasons = [], []
    for c in provider.candidates:
        if c.uses_server:
            asked = _ask_server(client, c, engine, k, bodies, points, timeout)
            warms.append(asked.warm)
            reasons.append(asked.fallback_reason)
        else:
            warms.append(c.warm_start(engine, bodies, points, k))
    return _Served(warm=provider.pick(engine, points, warms), fallback_reason=next((r for r in reasons if r), None))


def declare_world(client, spec: SceneSpec, models=()) -> None:
    """Give `client` this scene's world (sent first on every stream) and have the server ready each
    of `models` for its grid before step 0. Raises simclient.client.Refused when the server refuses
    one of them for this world, e.g. a fixed-grid model and a box of another size."""
    lower, upper = spec.domain
    client.world = wire.encode_world(lower, upper, spec.walls(), spec.physics)
    for model in models:
        client.declare(model, DECLARE_TIMEOUT_S)


def run_simulation(spec: SceneSpec, seed: int, provider: Provider, *, client=None,
                   deadline_ms: float = DEFAULT_DEADLINE_MS, progress=None) -> dict:
    """Simulate (spec, seed) with `provider`; returns {"per_step": ..., "summary": ...}.

    client: a simclient.client.WarmStartClient for `server:` providers (its
    world is set here); None makes every server step a fallback. Raises
    simclient.client.Refused, before the first step, when the server refuses
    a model for this world: a run of fallbacks would be labelled as the model's.
    """
    engine = build_world(spec, seed)
    provider.prepare(engine)
    if client is not None:
        declare_world(client, spec, provider.models if provider.uses_server else ())
    records: list[StepRecord] = []
    timeout = deadline_ms / 1e3
    for k in range(spec.steps):
        laps = _Laps()
        engine.collide()
        collide_s = laps.lap()
        bodies, points = engine.bodies(), engine.contacts()
        export_s = laps.lap()
        if provider.picks:
            served = _pick(provider, client, engine, k, bodies, points, timeout)
        elif provider.uses_server:
            served = _ask_server(client, provider, engine, k, bodies, points, timeout)
        else:
            served = _Served(warm=provider.warm_start(engine, bodies, points, k))
        provider_s = laps.lap()
        inject_s = 0.0
        if served.warm is not None:
            engine.set_warm_start(*served.warm)
            inject_s = laps.lap()
        stats = engine.solve()
        records.append(_record(stats, engine.contacts(), served, provider,
                               collide_s=collide_s, export_s=export_s, provider_s=provider_s, inject_s=inject_s))
        if progress is not None:
            progress(k)
    result = {"per_step": _columns(records), "summary": summarize(records)}
    if provider.picks:
        result["trials"] = [list(t) for t in provider.trials]
        result["reach"] = [list(t) for t in provider.reach]
        if getattr(provider, "notes", None):
            result["notes"] = [np.asarray(t).tolist() for t in provider.notes]  # plain numbers: the results are JSON
    return result


def _record(stats, after: np.ndarray, served: _Served, provider: Provider, *, collide_s: float, export_s: float,
            provider_s: float, inject_s: float) -> StepRecord:
    """One step's record from the solve's statistics and the contact points after it (seconds in)."""
    provider.observe(after)
    mse_n = mse_t = None
    if len(after):
        err = after["warm_start"] - after["impulse"]
        mse_n, mse_t = float(np.mean(err[:, 0] ** 2)), float(np.mean(err[:, 1] ** 2))
    return StepRecord(
        contact_points=stats.contact_points, velocity_iterations=stats.velocity_iterations,
        position_iterations=stats.position_iterations,
        residual_trace=[float(x) for x in stats.residual_trace],
        mse_normal=mse_n, mse_tangent=mse_t, latency_ms=served.latency_ms, server_us=served.server_us,
        client_us=1e6 * (export_s + served.codec_s + inject_s), provider_ms=1e3 * provider_s,
        solve_ms=stats.solve_ms, collide_ms=1e3 * collide_s, export_ms=1e3 * export_s, inject_ms=1e3 * inject_s,
        fallback=served.fallback_reason is not None, fallback_reason=served.fallback_reason,
        reconnect=served.reconnect, served_by=served.served_by)


def _columns(records: list[StepRecord]) -> dict[str, list]:
    return {f.name: [getattr(r, f.name) for r in records] for f in dataclasses.fields(StepRecord)}


def summarize(records: list[StepRecord]) -> dict:
    """Iteration statistics over steps with at least one contact point."""
    solved = [r for r in records if r.contact_points > 0]
    its = np.array([r.velocity_iterations for r in solved], float)
    lat = np.array([r.latency_ms for r in records if r.latency_ms is not None and not r.fallback], float)
    mse_n = [r.mse_normal for r in solved if r.mse_normal is not None]
    mse_t = [r.mse_tangent for r in solved if r.mse_tangent is not None]
    client = np.array([r.client_us for r in solved], float)

    def stat(fn, a):
        return float(fn(a)) if len(a) else None

    return {
        "steps": len(records),
        "steps_with_contacts": len(solved),
        "mean_velocity_iterations": stat(np.mean, its),
        "median_velocity_iterations": stat(np.median, its),
        "p90_velocity_iterations": stat(lambda a: np.percentile(a, 90), its),
        "mse_normal": stat(np.mean, mse_n),
        "mse_tangent": stat(np.mean, mse_t),
        "p50_latency_ms": stat(np.median, lat),
        "p99_latency_ms": stat(lambda a: np.percentile(a, 99), lat),
        "fallback_steps": sum(r.fallback for r in records),
        "fallbacks_by_reason": dict(collections.Counter(r.fallback_reason for r in records if r.fallback)),
        "reconnects": sum(r.reconnect for r in records),
        # Steps a server answered with another card's (a face card's fallback; docs/server.md, Deadlines).
        "served_by": dict(collections.Counter(r.served_by for r in records if r.served_by)),
        "median_client_us": stat(np.median, client),
        "total_solve_ms": float(sum(r.solve_ms for r in records)),
    }


# -- command -----------------------------------------------------------------

def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_scene_arguments(parser)
    parser.add_argument("--seed", type=int, required=True, help="world seed (benchmarks use 900-999)")
    parser.add_argument("--warm-start", required=True, metavar="W",
                        help="none, builtin, copy, copy2, copy0, extrapolate, or server:MODEL "
                             "(server:random, server:bad, server:grid-identity, server:<onnx model>); "
                             "probes and oracles (oracle:VARIANT, solve@K, jitter@S, pick:W1+W2...) "
                             "are listed in simclient/warmstarts.py, oracles.py and composites.py")
    parser.add_argument("--server", metavar="HOST:PORT",
                        help="warm-start server for server:MODEL (any gRPC target, e.g. dns:///server:50051, or unix:PATH for a server on a Unix socket)")
    parser.add_argument("--deadline-ms", type=float, default=DEFAULT_DEADLINE_MS,
                        help=f"per-step deadline for the server's reply; later replies fall back to builtin "
                             f"(default {DEFAULT_DEADLINE_MS:g})")
    parser.add_argument("--allow-fallback", action="store_true",
                        help="if the server cannot be reached at start-up, simulate anyway with builtin fallbacks")
    parser.add_argument("--connect-timeout", type=float, default=5.0, help="seconds to wait for the server at start-up")
    parser.add_argument("--out", type=Path, required=True, help="results file (JSON)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def check_writable(path: Path) -> None:
    """Fail before simulating if the results cannot be written there."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.name}.", suffix=".probe"):
        pass


def connect(target: str, model: str, *, connect_timeout: float, allow_fallback: bool):
    """A client for `target` that serves `model` ("A+B": each of them), or None (fallbacks only).
    Raises SystemExit-worthy ValueError/ConnectionError with a message."""
    from simclient.client import WarmStartClient

    client = WarmStartClient(target)
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


def run(args: argparse.Namespace) -> int:
    try:
        spec = spec_from_args(args)
        provider = make_provider(args.warm_start)
        if provider.uses_server and not args.server:
            raise ValueError(f"{args.warm_start} needs --server HOST:PORT (start one with `deepcontact serve`)")
        check_writable(args.out)
    except (ValueError, OSError) as exc:
        print(f"deepcontact simulate: {exc}", file=sys.stderr)
        return 2
    client = None
    if provider.uses_server:
        try:
            client = connect(args.server, "+".join(provider.models), connect_timeout=args.connect_timeout,
                             allow_fallback=args.allow_fallback)
        except (ValueError, ConnectionError) as exc:
            print(f"deepcontact simulate: {exc}", file=sys.stderr)
            return 2
    from simclient.client import Refused

    bar = None
    if not args.quiet:
        from tqdm import tqdm

        bar = tqdm(total=spec.steps, unit="step", desc=f"{args.warm_start} seed {args.seed}", file=sys.stderr)
    try:
        result = run_simulation(spec, args.seed, provider, client=client, deadline_ms=args.deadline_ms,
                                progress=(lambda k: bar.update(1)) if bar else None)
    except Refused as exc:
        print(f"deepcontact simulate: the server at {args.server} refuses {args.warm_start} for this world: {exc}",
              file=sys.stderr)
        return 2
    finally:
        if bar:
            bar.close()
        if client is not None:
            client.close()
    result.update({"scene": spec_to_dict(spec), "seed": args.seed, "warm_start": args.warm_start,
                   "server": args.server, "deadline_ms": args.deadline_ms,
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
    return text
