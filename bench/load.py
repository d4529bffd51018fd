"""`deepcontact bench load`: per-step latency with many simulations streaming at once.

    deepcontact bench load --model pressure --clients 1,4,16,64 --duration 20 --out bench/results/load

For each concurrency level, that many streams send one simulation's steps back
to back, each in lockstep (send, wait for the reply, send the next), or, with
--rate HZ, at most HZ steps a second each, as simulations stepping in real time
do. Streams
run in worker processes (threads within them, at most --processes processes),
so one GIL does not cap the load. Steps come from a recorded file
(`--replay FILE.h5`, cheap to generate load from) or, by default, from live
thesis simulations, one per stream.

Per level: steps sent and answered (sent = answered + errors), steps per
second, who answered them (the model's route, a face card's fallback, Box2D's
own start where the server shed them), latency p50/p90/p99/p99.9
(HdrHistogram, µs resolution), errors by
reason (simclient.client.StepFailed: gRPC status code, WRONG_STEP, ...), the
server's stage timings, and a check that no stream ever got a reply out of
order or for another step. `deepcontact bench soak` runs one long level.

Without --server the command starts the servers it compares itself: one
server process without micro-batching, one with it, and --server-processes
processes sharing one port (SO_REUSEPORT). Writes DIR/load.json and
DIR/latency_vs_load.png. A --server that serves TLS is dialled with --tls-ca
(and --tls-cert/--tls-key where it requires client certificates).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from bench.figures import save_figure
from deepcontact import tls
from deepcontact.io import write_json_atomic

HIGHEST_US = 60_000_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--server", metavar="HOST:PORT", help="load this server (default: start and compare our own)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="models for servers started here (default models/)")
    parser.add_argument("--model", default="default", help="model to request (default: default, the shipped model)")
    parser.add_argument("--clients", default="1,4,16,64", help="concurrency levels (default 1,4,16,64)")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds per level (default 20)")
    parser.add_argument("--replay", type=Path, metavar="FILE.h5", help="send recorded steps from this data file")
    parser.add_argument("--processes", type=int, default=8, help="most load-generating processes (default 8)")
    parser.add_argument("--server-processes", type=int, default=2,
                        help="processes sharing one port in the multi-process comparison (default 2)")
    parser.add_argument("--batch-max", type=int, default=8, help="micro-batch size in the batching comparison (default 8)")
    parser.add_argument("--batch-delay-us", type=int, default=1000, help="micro-batch wait (default 1000)")
    parser.add_argument("--max-concurrent", type=int, default=64,
                        help="--max-concurrent of the servers started here (default 64)")
    parser.add_argument("--deadline-ms", type=float, default=5000.0,
                        help="per-step deadline; a step past it counts as DEADLINE_EXCEEDED (default 5000)")
    parser.add_argument("--rate", type=float, metavar="HZ",
                        help="each stream sends at most this many steps a second, as a simulation running in real "
                             "time does (default: back to back, in lockstep: each step sent as its reply comes)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    tls.add_client_arguments(parser)


#: (--tls-ca, --tls-cert, --tls-key) as paths, or Nones: what crosses to the load processes
#: (credentials objects do not), each of which builds its own.
TlsFiles = tuple[str | None, str | None, str | None]
PLAINTEXT: TlsFiles = (None, None, None)


def tls_files(args: argparse.Namespace) -> TlsFiles:
    """The client TLS flags of a command as run_level's client_tls."""
    return tuple(None if f is None else str(f) for f in (args.tls_ca, args.tls_cert, args.tls_key))


# -- load generation (runs in worker processes) -------------------------------

def _steps_source(replay: str | None, stream_index: int, limit: int = 250):
    """An endless iterator of (bodies, points, friction) for one stream; friction: (P,)
    float32, each point's friction coefficient, as the simulation client sends it."""
    from simclient.provider import point_friction
    from simclient.scene import SceneSpec, body_friction, build_world, spec_from_dict

    if replay:
        from training.dataset import Dataset

        with Dataset(replay) as ds:
            rows = np.flatnonzero(ds.steps["point_count"] > 0)
            start = (stream_index * 97) % max(len(rows) - limit, 1)
            scene = spec_from_dict(ds.scene)
            steps = []
            for i in rows[start:start + limit]:
                bodies, points, row = ds.step(int(i))
                # The records carry no friction; the seed's scene gives every body's.
                mu = point_friction(body_friction(scene, int(row["seed"])), points)
                steps.append((bodies, points, mu.astype(np.float32)))
        while True:
            yield from steps
    else:
        spec = SceneSpec.thesis()
        seed = 900 + stream_index % 100
        while True:
            engine = build_world(spec, seed)
            mu = engine.body_friction()
            for _ in range(spec.steps):
                engine.collide()
                bodies, points = engine.bodies(), engine.contacts()
                yield bodies, points, point_friction(mu, points).astype(np.float32)
                engine.solve()


def _stream_worker(target, model, source, stream_index, timing, deadline_s, out: dict, lock, credentials=None,
                   rate: float | None = None):
    from hdrh.histogram import HdrHistogram

    from deepcontact import wire
    from simclient.client import StepFailed, WarmStartClient
    from simclient.scene import SceneSpec

    latency = HdrHistogram(1, HIGHEST_US, 3)
    server_total = HdrHistogram(1, HIGHEST_US, 3)
    server_inference = HdrHistogram(1, HIGHEST_US, 3)
    errors: dict[str, int] = {}
    answered_by: dict[str, int] = {}  # who answered the steps answered: the model's route ("model") or served_by
    ok = wrong_order = 0
    period = 1.0 / rate if rate else 0.0  # a paced stream sends a step every period s, a simulation in real time
    thesis = SceneSpec.thesis()  # the worlds these steps come from
    world = wire.encode_world(*thesis.domain, thesis.walls(), thesis.physics, thesis.solver.stopping_tolerance)
    with WarmStartClient(target, world=world, credentials=credentials, backoff_s=(0.01, 0.2)) as client:
        start_at, stop_at = timing()
        while time.time() < start_at:
            time.sleep(0.001)
        k = 0
        next_at = time.perf_counter()
        while time.time() < stop_at:
            if period:
                next_at += period
            bodies, points, friction = next(source)
            request = wire.encode_step(k, model, bodies, points, builtin=points["builtin"], friction=friction)
            t0 = time.perf_counter()
            try:
                reply = client.step(request, deadline_s)
                dt = time.perf_counter() - t0
                if reply.step != k or reply.point_count != len(points):
                    wrong_order += 1
                    errors["WRONG_STEP"] = errors.get("WRONG_STEP", 0) + 1
                else:
                    ok += 1
                    by = reply.served_by or "model"
                    answered_by[by] = answered_by.get(by, 0) + 1
                    latency.record_value(max(1, int(dt * 1e6)))
                    server_total.record_value(max(1, reply.timings.total_us))
                    server_inference.record_value(max(1, reply.timings.inference_us))
            except StepFailed as exc:
                if exc.backing_off:  # nothing was sent; wait out the reconnect backoff
                    time.sleep(0.005)
                    continue
                if exc.reason == "WRONG_STEP":
                    wrong_order += 1
                errors[exc.reason] = errors.get(exc.reason, 0) + 1
                time.sleep(0.002)  # do not spin on a refusing server
            k += 1  # sent: answered (ok) or counted in errors
            if period:  # paced: wait for the step's turn (a stream that fell behind sends at once)
                time.sleep(max(0.0, next_at - time.perf_counter()))
    with lock:
        out["sent"] += k
        out["ok"] += ok
        out["wrong_order"] += wrong_order
        for code, n in errors.items():
            out["errors"][code] = out["errors"].get(code, 0) + n
        for by, n in answered_by.items():
            out["answered_by"][by] = out["answered_by"].get(by, 0) + n
        for name, h in (("latency", latency), ("server_total", server_total), ("server_inference", server_inference)):
            out[name].add(h)


def _process_worker(target, model, replay, stream_indices, deadline_s, ready, start_time, duration, result_path,
                    client_tls=PLAINTEXT, rate=None):
    from hdrh.histogram import HdrHistogram

    from deepcontact.tls import client_credentials

    credentials = client_credentials(*client_tls)  # checked by the command before any process started

    out = {"sent": 0, "ok": 0, "wrong_order": 0, "errors": {}, "answered_by": {},
           "latency": HdrHistogram(1, HIGHEST_US, 3), "server_total": HdrHistogram(1, HIGHEST_US, 3),
           "server_inference": HdrHistogram(1, HIGHEST_US, 3)}
    lock = threading.Lock()
    # Load every stream's steps before reporting ready, so the timed window
    # measures the server, not start-up.
    sources = {i: _steps_source(replay, i) for i in stream_indices}
    for src in sources.values():
        next(src)
    ready.wait()  # a barrier across all load processes and the parent

    def timing():
        while start_time.value == 0.0:
            time.sleep(0.001)
        return start_time.value, start_time.value + duration

    threads = [threading.Thread(target=_stream_worker, args=(target, model, sources[i], i, timing, deadline_s,
                                                             out, lock, credentials, rate)) for i in stream_indices]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # Histograms travel as HdrHistogram's own compressed encoding inside JSON: no pickle.
    for name in ("latency", "server_total", "server_inference"):
        out[name] = out[name].encode().decode("ascii")
    Path(result_path).write_text(json.dumps(out))


def run_level(target: str, model: str, clients: int, duration: float, *, replay: Path | None,
              max_processes: int, deadline_s: float, client_tls: TlsFiles = PLAINTEXT,
              rate: float | None = None) -> dict:
    """`clients` concurrent streams for `duration` seconds against target; client_tls: the client's
    (CA, certificate, key) files for a TLS target (tls_files), PLAINTEXT for none; rate: each
    stream's steps a second at most (None: back to back, in lockstep)."""
    from hdrh.histogram import HdrHistogram

    ctx = mp.get_context("spawn")  # no gRPC state crosses a fork
    n_proc = max(1, min(clients, max_processes))
    groups = [list(range(i, clients, n_proc)) for i in range(n_proc)]
    ready = ctx.Barrier(n_proc + 1)
    start_time = ctx.Value("d", 0.0)
    with tempfile.TemporaryDirectory(prefix="deepcontact-load-") as tmp:
        paths = [Path(tmp) / f"w{i}.json" for i in range(n_proc)]
        procs = [ctx.Process(target=_process_worker, args=(target, model, str(replay) if replay else None, g,
                                                           deadline_s, ready, start_time, duration, str(p), client_tls,
                                                           rate))
                 for g, p in zip(groups, paths)]
        for p in procs:
            p.start()
        ready.wait(timeout=300)
        start_time.value = time.time() + 1.0  # the streams connect, then all start together
        for p in procs:
            p.join(timeout=duration + 120)
            if p.is_alive():
                p.kill()
        parts = [json.loads(p.read_text()) for p in paths if p.exists()]
    if len(parts) < n_proc:
        print(f"warning: {n_proc - len(parts)} load processes did not report", file=sys.stderr)
    hist = {name: HdrHistogram(1, HIGHEST_US, 3) for name in ("latency", "server_total", "server_inference")}
    errors: dict[str, int] = {}
    answered_by: dict[str, int] = {}
    sent = ok = wrong = 0
    for part in parts:
        sent += part["sent"]
        ok += part["ok"]
        wrong += part["wrong_order"]
        for code, n in part["errors"].items():
            errors[code] = errors.get(code, 0) + n
        for by, n in part["answered_by"].items():
            answered_by[by] = answered_by.get(by, 0) + n
        for name, h in hist.items():
            h.decode_and_add(part[name].encode("ascii"))

    def pct(h, q):
        return h.get_value_at_percentile(q) / 1e3 if h.get_total_count() else None

    lat = hist["latency"]
    return {
        "clients": clients, "processes": n_proc, "duration_s": duration,
        "sent": sent, "steps": ok, "steps_per_s": ok / duration,
        "latency_ms": {"p50": pct(lat, 50), "p90": pct(lat, 90), "p99": pct(lat, 99), "p99.9": pct(lat, 99.9)},
        "server_ms": {"total_p50": pct(hist["server_total"], 50), "inference_p50": pct(hist["server_inference"], 50),
                      "total_p99": pct(hist["server_total"], 99)},
        "errors": errors, "wrong_order_or_step": wrong, "rate_per_stream": rate,
        # who answered: "model" for the model's own route, else the reply's served_by (a face
        # card's fallback, "builtin" where Box2D's start was served: a step shed or past every route)
        "answered_by": answered_by,
    }


def _has_contacts(replay: Path) -> bool:
    from training.dataset import Dataset

    with Dataset(replay) as ds:
        return bool((ds.steps["point_count"] > 0).any())


# -- configurations ------------------------------------------------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run(args: argparse.Namespace) -> int:
    try:
        levels = [int(c) for c in args.clients.split(",") if c.strip()]
        if not levels or min(levels) < 1:
            raise ValueError
    except ValueError:
        print(f"deepcontact bench load: --clients takes positive integers, e.g. 1,4,16,64 (got {args.clients!r})",
              file=sys.stderr)
        return 2
    if args.duration <= 0:
        print("deepcontact bench load: --duration must be > 0", file=sys.stderr)
        return 2
    if args.rate is not None and not args.rate > 0:
        print("deepcontact bench load: --rate must be > 0 steps a second", file=sys.stderr)
        return 2
    if args.replay is not None and not args.replay.exists():
        print(f"deepcontact bench load: {args.replay}: no such data file", file=sys.stderr)
        return 2
    if args.replay is not None and not _has_contacts(args.replay):
        print(f"deepcontact bench load: {args.replay}: no steps with contacts to send", file=sys.stderr)
        return 2
    problem = _tls_problem(args)
    if problem:
        print(f"deepcontact bench load: {problem}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    if args.server:
        configs = [("given server", None)]
    else:
        common = ["--max-concurrent", str(args.max_concurrent)]
        configs = [
            ("1 process", [common]),
            (f"1 process, micro-batching {args.batch_max}/{args.batch_delay_us}us",
             [common + ["--batch-max", str(args.batch_max), "--batch-delay-us", str(args.batch_delay_us)]]),
            (f"{args.server_processes} processes (SO_REUSEPORT)", [common] * args.server_processes),
        ]
    results = []
    try:
        _run_configs(args, configs, levels, results)
    except (RuntimeError, TimeoutError) as exc:  # a server that would not start
        print(f"deepcontact bench load: {exc}", file=sys.stderr)
        return 2
    write_json_atomic(args.out / "load.json", {
        "model": args.model, "replay": str(args.replay) if args.replay else None, "duration_s": args.duration,
        "command": "deepcontact " + " ".join(sys.argv[1:]), "results": results})
    _plot(results, args.out / "latency_vs_load.png")
    print(f"wrote {args.out}/load.json and latency_vs_load.png")
    return 0


def _tls_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the client TLS flags, in a sentence, or None. They are for
    --server: the servers this command starts serve plaintext on loopback."""
    if any(tls_files(args)) and not args.server:
        return ("--tls-ca, --tls-cert and --tls-key are for a --server that serves TLS; "
                "the servers started here serve plaintext on loopback")
    try:
        tls.credentials_from_args(args)
    except ValueError as exc:
        return str(exc)
    return None


def _run_configs(args, configs, levels, results: list[dict]) -> None:
    credentials = tls.credentials_from_args(args)
    for label, servers in configs:
        procs = []
        try:
            target = args.server
            if servers is not None:
                from server.process import ServerProcess

                port = _free_port()
                for i, extra in enumerate(servers):
                    procs.append(ServerProcess(args.models, *extra, bind=f"127.0.0.1:{port}",
                                               log=args.out / f"server-{len(results)}-{i}.log").start())
                target = f"127.0.0.1:{port}"
            from simclient.client import WarmStartClient

            with WarmStartClient(target, credentials=credentials) as probe:
                if not probe.wait_ready(10) or args.model not in [m.name for m in probe.list_models()]:
                    raise RuntimeError(f"{target} does not serve {args.model!r}")
            for clients in levels:
                r = run_level(target, args.model, clients, args.duration, replay=args.replay,
                              max_processes=args.processes, deadline_s=args.deadline_ms / 1e3,
                              client_tls=tls_files(args), rate=args.rate)
                r["config"] = label
                results.append(r)
                lat = r["latency_ms"]
                print(f"[{label}] {clients:3d} streams: {r['steps_per_s']:7.1f} steps/s, latency p50 "
                      f"{_fmt(lat['p50'])} p99 {_fmt(lat['p99'])} p99.9 {_fmt(lat['p99.9'])} ms, "
                      f"errors {r['errors'] or 0}, out of order {r['wrong_order_or_step']}, "
                      f"answered by {_mix(r['answered_by'])}", flush=True)
        finally:
            for p in procs:
                p.stop()


def _fmt(x):
    return "-" if x is None else f"{x:.2f}"


def _mix(answered_by: dict[str, int]) -> str:
    """'model 71%, contact-graph 20%, builtin 9%': who answered the steps answered."""
    total = sum(answered_by.values())
    return ", ".join(f"{by} {n / total:.0%}" for by, n in sorted(answered_by.items(), key=lambda kv: -kv[1])) or "-"


def _plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    for config in dict.fromkeys(r["config"] for r in results):
        rs = [r for r in results if r["config"] == config and r["steps"] > 0]
        if not rs:
            continue
        x = [r["clients"] for r in rs]
        ax1.plot(x, [r["latency_ms"]["p50"] for r in rs], "o-", label=f"{config} p50")
        ax1.plot(x, [r["latency_ms"]["p99"] for r in rs], "s--", label=f"{config} p99")
        ax2.plot(x, [r["steps_per_s"] for r in rs], "o-", label=config)
    for ax in (ax1, ax2):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("concurrent streams")
    ax1.set(yscale="log", ylabel="round trip (ms)", title="latency per step")
    ax2.set(ylabel="steps / s", title="throughput")
    ax1.legend(fontsize=6)
    ax2.legend(fontsize=7)
    save_figure(fig, path)
