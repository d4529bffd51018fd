"""`deepcontact bench soak`: a long load on one server; nothing lost, memory flat.

    deepcontact bench soak --duration 600 --clients 8 --out bench/results/soak

Starts `deepcontact serve` (with Prometheus metrics) and puts `--clients`
lockstep streams on it for `--duration` seconds with `bench load`'s load
generator (worker processes; live thesis simulations, or `--replay FILE.h5`).
Meanwhile it samples the server's resident memory (VmRSS in
/proc/PID/status) and its answered-step counter every `--sample-s` seconds.

Checks, each a line of the summary and a field of the JSON:
  - accounting: every step a client sent was answered or counted as an
    error, by reason (sent = answered + errors); the server answered at
    least as many steps as the clients received;
  - memory: after `--warmup-s` of load, the server's RSS grows by at most
    `--rss-bound-mb` over its first sample after the warm-up (the growth is
    max(RSS after warm-up) - that sample; a least-squares slope is reported
    beside it).
Writes DIR/soak.json and DIR/soak.png (RSS and steps answered per second
over time); exits 1 if a check fails.

To soak TLS, the server is given `--server-tls-cert/--server-tls-key` (and
`--server-tls-client-ca` for mutual TLS; its certificate must name 127.0.0.1,
which the clients dial) and the clients `--tls-ca` (and `--tls-cert/--tls-key`).
"""

from __future__ import annotations

import argparse
import re
import sys
import threading
import time
import urllib.request
from pathlib import Path

import grpc
import numpy as np
from grpc_health.v1 import health_pb2, health_pb2_grpc

from bench import load
from bench.figures import save_figure
from deepcontact import tls
from deepcontact.io import write_json_atomic
from deepcontact.modelcard import unknown_model

_STEPS_LINE = re.compile(r'^deepcontact_steps_total\{[^}]*\} ([0-9.e+]+)$', re.M)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=600.0, help="seconds of load (default 600)")
    parser.add_argument("--clients", type=int, default=8, help="concurrent lockstep streams (default 8)")
    parser.add_argument("--models", type=Path, default=Path("models"), help="models for the server (default models/)")
    parser.add_argument("--model", default="default", help="model to request (default: default, the shipped model)")
    parser.add_argument("--replay", type=Path, metavar="FILE.h5",
                        help="send recorded steps from this data file (default: live thesis simulations)")
    parser.add_argument("--processes", type=int, default=8, help="most load-generating processes (default 8)")
    parser.add_argument("--deadline-ms", type=float, default=1000.0,
                        help="per-step deadline; a later reply counts as DEADLINE_EXCEEDED (default 1000)")
    parser.add_argument("--sample-s", type=float, default=5.0, help="seconds between memory samples (default 5)")
    parser.add_argument("--warmup-s", type=float, default=None,
                        help="load before memory must stay flat (default: a fifth of --duration, at most 60 s)")
    parser.add_argument("--rss-bound-mb", type=float, default=20.0,
                        help="most the server's RSS may grow after the warm-up, MB (default 20)")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--server-tls-cert", type=Path, metavar="FILE",
                        help="the server serves TLS with this PEM certificate chain (with --server-tls-key; it "
                             "must name IP 127.0.0.1, which the clients dial, and they need --tls-ca)")
    parser.add_argument("--server-tls-key", type=Path, metavar="FILE", help="PEM private key of --server-tls-cert")
    parser.add_argument("--server-tls-client-ca", type=Path, metavar="FILE",
                        help="the server requires client certificates signed by this CA (mutual TLS; the clients "
                             "then need --tls-cert and --tls-key)")
    tls.add_client_arguments(parser)


# -- sampling the server ---------------------------------------------------------

def rss_mb(pid: int) -> float:
    """Resident memory of process `pid` (VmRSS), MB (10^6 bytes)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024 / 1e6
    raise OSError(f"no VmRSS for process {pid}")


def steps_answered(metrics_port: int) -> int:
    """The server's deepcontact_steps_total, summed over models."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5).read().decode()
    return int(sum(float(x) for x in _STEPS_LINE.findall(text)))


class Sampler:
    """Every `every_s` seconds, in a thread: (seconds since start, RSS MB, steps answered)."""

    def __init__(self, pid: int, metrics_port: int, every_s: float):
        self.pid, self.metrics_port, self.every_s = pid, metrics_port, every_s
        self.samples: list[tuple[float, float, int]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="soak-sampler", daemon=True)

    def __enter__(self) -> "Sampler":
        self._t0 = time.monotonic()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self._sample()  # the state after the load

    def _sample(self) -> None:
        self.samples.append((time.monotonic() - self._t0, rss_mb(self.pid), steps_answered(self.metrics_port)))

    def _loop(self) -> None:
        while not self._stop.is_set():
            self._sample()
            self._stop.wait(self.every_s)


# -- checks ------------------------------------------------------------------------

def memory_check(samples: list[tuple[float, float, int]], warmup_s: float, bound_mb: float) -> dict:
    """RSS after warm-up: its first sample, max, growth over the first, slope (MB/h), within bound.

    samples: [(t s, RSS MB, steps answered)]. Warm-up starts at the first
    sample in which the server had answered a step.
    """
    t, rss, answered = (np.array(c, float) for c in zip(*samples))
    started = t[np.argmax(answered > 0)] if (answered > 0).any() else t[0]
    after = t >= started + warmup_s
    if after.sum() < 2:
        return {"warmup_s": warmup_s, "samples_after_warmup": int(after.sum()), "within_bound": None}
    base, peak = float(rss[after][0]), float(rss[after].max())
    slope = float(np.polyfit(t[after], rss[after], 1)[0]) * 3600.0
    return {"warmup_s": warmup_s, "load_started_s": float(started), "samples_after_warmup": int(after.sum()),
            "rss_first_mb": float(rss[0]), "rss_after_warmup_mb": base, "rss_max_after_warmup_mb": peak,
            "rss_final_mb": float(rss[-1]), "growth_after_warmup_mb": peak - base, "slope_mb_per_h": slope,
            "bound_mb": bound_mb, "within_bound": peak - base <= bound_mb}


def accounting_check(level: dict, server_answered: int) -> dict:
    """Client counts from load.run_level against each other and the server's."""
    errors = sum(level["errors"].values())
    return {"sent": level["sent"], "answered": level["steps"], "errors": level["errors"],
            "server_answered": server_answered,
            "balanced": level["sent"] == level["steps"] + errors and server_answered >= level["steps"]}


# -- command -----------------------------------------------------------------------

def run(args: argparse.Namespace) -> int:
    warmup_s = args.warmup_s if args.warmup_s is not None else min(60.0, args.duration / 5)
    problems = [message for bad, message in (
        (args.duration <= 0, "--duration must be > 0"), (args.clients < 1, "--clients must be >= 1"),
        (args.sample_s <= 0, "--sample-s must be > 0"), (warmup_s < 0, "--warmup-s must be >= 0"),
        (args.replay is not None and not args.replay.exists(), f"{args.replay}: no such data file")) if bad]
    problems += [p for p in (_tls_problem(args),) if p]
    if problems:
        print(f"deepcontact bench soak: {'; '.join(problems)}", file=sys.stderr)
        return 2
    credentials = tls.credentials_from_args(args)
    args.out.mkdir(parents=True, exist_ok=True)
    metrics_port = load._free_port()
    try:
        server = _server_process(args.models, ["--metrics-port", str(metrics_port), *_server_tls_args(args)],
                                 args.out / "server.log", credentials).start()
    except (RuntimeError, TimeoutError) as exc:
        print(f"deepcontact bench soak: {exc}", file=sys.stderr)
        return 2
    try:
        from simclient.client import WarmStartClient

        with WarmStartClient(server.address, credentials=credentials) as probe:
            names = [m.name for m in probe.list_models()]
            if args.model not in names:
                print(f"deepcontact bench soak: {args.models}: {unknown_model(args.model, names)}", file=sys.stderr)
                return 2
        with Sampler(server.proc.pid, metrics_port, args.sample_s) as sampler:
            level = load.run_level(server.address, args.model, args.clients, args.duration, replay=args.replay,
                                   max_processes=args.processes, deadline_s=args.deadline_ms / 1e3,
                                   client_tls=load.tls_files(args))
    finally:
        server.stop()
    samples = sampler.samples
    memory = memory_check(samples, warmup_s, args.rss_bound_mb)
    steps = accounting_check(level, samples[-1][2])
    result = {"command": "deepcontact " + " ".join(sys.argv[1:]), "model": args.model, "clients": args.clients,
              "duration_s": args.duration, "deadline_ms": args.deadline_ms, "sample_s": args.sample_s,
              "replay": str(args.replay) if args.replay else None, "steps": steps, "memory": memory,
              "latency_ms": level["latency_ms"], "steps_per_s": level["steps_per_s"],
              "samples": [{"t_s": t, "rss_mb": r, "steps_answered": n} for t, r, n in samples]}
    write_json_atomic(args.out / "soak.json", result)
    plot(result, args.out / "soak.png")
    return _report(result, args.out)


def _tls_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the TLS flags, in a sentence, or None. The clients dial the server
    this command starts, so client and server TLS come together, and every file is read
    before a server starts."""
    server_tls = args.server_tls_cert is not None or args.server_tls_key is not None
    if (args.server_tls_cert is None) != (args.server_tls_key is None):
        return "--server-tls-cert and --server-tls-key go together"
    if args.server_tls_client_ca is not None and not server_tls:
        return "--server-tls-client-ca needs --server-tls-cert and --server-tls-key"
    if server_tls and args.tls_ca is None:
        return "a TLS server needs --tls-ca, the CA its certificate is verified by"
    if not server_tls and any(load.tls_files(args)):
        return ("--tls-ca, --tls-cert and --tls-key dial the server started here, which serves TLS with "
                "--server-tls-cert and --server-tls-key")
    try:
        tls.credentials_from_args(args)
    except ValueError as exc:
        return str(exc)
    if server_tls:
        try:
            tls.server_credentials(args.server_tls_cert, args.server_tls_key, args.server_tls_client_ca)
        except ValueError as exc:  # its message names serve's flags, which --server-tls-* pass on
            return f"the server's TLS files (--server-tls-*): {exc}"
    return None


def _server_tls_args(args: argparse.Namespace) -> list[str]:
    """`deepcontact serve`'s TLS flags for the server soak starts (none for plaintext)."""
    if args.server_tls_cert is None:
        return []
    out = ["--tls-cert", str(args.server_tls_cert), "--tls-key", str(args.server_tls_key)]
    return out + (["--tls-client-ca", str(args.server_tls_client_ca)] if args.server_tls_client_ca else [])


def _server_process(models: Path, extra: list[str], log: Path, credentials: grpc.ChannelCredentials | None):
    """A ServerProcess whose start-up health check dials it as the clients will: over TLS
    with their credentials when it serves TLS."""
    from server.process import ServerProcess

    class _Server(ServerProcess):
        def wait_healthy(self, timeout: float) -> None:
            if credentials is None:
                return super().wait_healthy(timeout)
            try:
                with grpc.secure_channel(self.address, credentials) as channel:
                    status = health_pb2_grpc.HealthStub(channel).Check(
                        health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"),
                        timeout=max(timeout, 1.0), wait_for_ready=True).status
            except grpc.RpcError as err:  # e.g. a handshake its certificates do not pass
                self.stop()
                raise RuntimeError(f"the server at {self.address} did not answer over TLS ({err.code().name}); "
                                   f"its log: {log}") from None
            if status != health_pb2.HealthCheckResponse.SERVING:
                self.stop()
                raise RuntimeError(f"server at {self.address} reports {status}")

    return _Server(models, *extra, log=log)


def _report(result: dict, out: Path) -> int:
    steps, memory = result["steps"], result["memory"]
    errors = ", ".join(f"{n} {reason}" for reason, n in sorted(steps["errors"].items())) or "none"
    print(f"{result['clients']} streams for {result['duration_s']:g} s: {steps['sent']} steps sent, "
          f"{steps['answered']} answered, errors {errors}; server answered {steps['server_answered']} "
          f"-> {'balanced' if steps['balanced'] else 'NOT BALANCED'}")
    if memory["within_bound"] is None:
        print(f"server RSS: too few samples after the {memory['warmup_s']:g} s warm-up to judge "
              f"({memory['samples_after_warmup']}); run longer or sample more often")
    else:
        print(f"server RSS after {memory['warmup_s']:g} s warm-up {memory['rss_after_warmup_mb']:.1f} MB, "
              f"max {memory['rss_max_after_warmup_mb']:.1f} MB: growth {memory['growth_after_warmup_mb']:.1f} MB "
              f"(bound {memory['bound_mb']:g} MB), slope {memory['slope_mb_per_h']:+.1f} MB/h "
              f"-> {'within bound' if memory['within_bound'] else 'OVER BOUND'}")
    print(f"wrote {out}/soak.json and soak.png")
    return 0 if steps["balanced"] and memory["within_bound"] is not False else 1


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s["t_s"] for s in result["samples"]]) / 60
    rss = np.array([s["rss_mb"] for s in result["samples"]])
    answered = np.array([s["steps_answered"] for s in result["samples"]], float)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 4.5), sharex=True)
    ax1.plot(t, rss, "-", lw=1.2)
    memory = result["memory"]
    if memory["within_bound"] is not None:
        start = (memory["load_started_s"] + memory["warmup_s"]) / 60
        ax1.axvspan(t[0], start, color="0.9", label="warm-up")
        ax1.axhline(memory["rss_after_warmup_mb"] + memory["bound_mb"], color="r", ls=":", lw=1,
                    label=f"bound (+{memory['bound_mb']:g} MB)")
        ax1.legend(fontsize=7, loc="lower right")
    ax1.set(ylabel="server RSS (MB)", title=f"soak: {result['clients']} streams, {result['model']}, "
                                            f"{result['duration_s']:g} s")
    if len(t) > 1:
        ax2.step(t[1:], np.diff(answered) / np.diff(t * 60), where="pre", lw=1)
    ax2.set(xlabel="minutes", ylabel="steps answered / s")
    save_figure(fig, path, dpi=90)
