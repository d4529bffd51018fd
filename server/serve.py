"""`deepcontact serve`: run the warm-start service.

    deepcontact serve --models models/ --bind 127.0.0.1:50051

Loads every ONNX model in the folder with its card, adds the providers
(zero, random, bad, grid-identity), and serves WarmStart with gRPC health
checking and server reflection. Every card and ONNX file is checked first, and
the bad ones are named together; `--skip-bad-models` serves the good ones.

Plaintext is for this machine only: an address other than loopback or a Unix
socket needs `--tls-cert/--tls-key` (`--tls-client-ca` also requires client
certificates from that CA), or `--insecure` to serve plaintext there anyway.

SIGTERM or SIGINT: health reports NOT_SERVING at once, new RPCs are refused,
open streams may finish for `--grace` seconds, then what is left is
cancelled and the process exits, within grace + 1 s whatever clients sent
before. A second signal exits at once.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import os
import signal
import sys
import threading
from concurrent import futures
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from deepcontact import tls
from deepcontact.io import write_bytes_atomic
from deepcontact.modelcard import ModelCardError
from server import metrics
from server.batching import MicroBatcher
from server.heap import keep_freed_memory
from server.idle import IdleStreams
from server.malformed import MalformedRequests
from server.predictors import load_models, providers
from server.service import DEADLINE_MARGIN_S, SERVICE_NAME, FaultDelay, Limits, WarmStartService, add_to_server

log = logging.getLogger("deepcontact.server")
# A stream silent this long is ended, freeing its worker thread (server.idle).
STREAM_IDLE_S = 60.0


class JsonFormatter(logging.Formatter):
    """One JSON object per line: time, level, message and any `extra` fields."""

    _skip = set(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime"}

    def format(self, record: logging.LogRecord) -> str:
        out = {"time": round(record.created, 6), "level": record.levelname, "msg": record.getMessage()}
        out.update({k: v for k, v in vars(record).items() if k not in self._skip})
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--models", type=Path, default=Path("models"),
                        help="folder of *.onnx models with *.json cards (default models/)")
    parser.add_argument("--bind", default="127.0.0.1:50051",
                        help="address to listen on (default 127.0.0.1:50051; port 0 picks a free one; "
                             "unix:PATH listens on a Unix socket, which clients dial as the same unix:PATH)")
    parser.add_argument("--port-file", type=Path, help="write the bound port here once serving (1 for a Unix socket)")
    parser.add_argument("--max-concurrent", type=int, default=64,
                        help="concurrent RPCs (streams count while open); more get RESOURCE_EXHAUSTED (default 64)")
    parser.add_argument("--max-queue", type=int, default=256,
                        help="steps waiting for inference in the micro-batcher; more get RESOURCE_EXHAUSTED (default 256)")
    parser.add_argument("--batch-max", type=int, default=0,
                        help="micro-batching: largest batch across streams (default 0: off)")
    parser.add_argument("--batch-delay-us", type=int, default=500,
                        help="micro-batching: longest wait for a batch to fill, microseconds (default 500)")
    parser.add_argument("--intra-op-threads", type=int, default=1,
                        help="ONNX Runtime threads per inference (default 1: best under load; 2 halves one "
                             "stream's inference on 2 cores, docs/performance.md)")
    parser.add_argument("--inter-op-threads", type=int, default=1, help="ONNX Runtime inter-op threads (default 1)")
    parser.add_argument("--max-bodies", type=int, default=Limits.max_bodies, help="bodies per step (default %(default)s)")
    parser.add_argument("--max-points", type=int, default=Limits.max_points, help="contact points per step (default %(default)s)")
    parser.add_argument("--max-grid-nodes", type=int, default=Limits.max_grid_nodes,
                        help="grid nodes a world's domain may need at a grid model's resolution; a larger world "
                             "gets INVALID_ARGUMENT (default %(default)s: 512 x 512, a 128 m square at 0.25 m)")
    parser.add_argument("--random-seed", type=int, default=0, help="seed of the `random` provider (default 0)")
    parser.add_argument("--metrics-port", type=int, default=0,
                        help="serve Prometheus metrics on this port at /metrics (default 0: off)")
    parser.add_argument("--tls-cert", type=Path, metavar="FILE",
                        help="PEM certificate chain: serve TLS (with --tls-key)")
    parser.add_argument("--tls-key", type=Path, metavar="FILE", help="PEM private key for --tls-cert")
    parser.add_argument("--tls-client-ca", type=Path, metavar="FILE",
                        help="mutual TLS: PEM certificates of the CA whose signed client certificates are admitted; "
                             "a client without one is refused in the handshake (needs --tls-cert and --tls-key)")
    parser.add_argument("--insecure", action="store_true",
                        help="serve plaintext on an address other than loopback or a Unix socket, which is refused "
                             "without TLS; anyone who reaches the address can use the service")
    parser.add_argument("--skip-bad-models", action="store_true",
                        help="serve the good models of --models and log each bad card or ONNX file, rather than "
                             "refuse to start naming them all")
    parser.add_argument("--stream-idle-s", type=float, default=STREAM_IDLE_S, metavar="S",
                        help="end a stream that has sent nothing for S seconds, so hung or vanished clients do not "
                             "hold --max-concurrent slots; simclient's client reopens on its next step "
                             "(default %(default)s; 0: never)")
    parser.add_argument("--grace", type=float, default=5.0,
                        help="on SIGTERM/SIGINT, seconds open streams may go on before they are cancelled and the "
                             "process exits (default 5); a second signal exits at once")
    parser.add_argument("--fault-delay-ms", type=float, default=0.0, metavar="MS",
                        help="testing clients: hold each reply this long, as a slow server would (default 0: off)")
    parser.add_argument("--fault-every", type=int, default=1, metavar="N",
                        help="with --fault-delay-ms: only steps whose index is a multiple of N (default 1: all)")
    parser.add_argument("--deadline-margin-ms", type=float, default=1e3 * DEADLINE_MARGIN_S, metavar="MS",
                        help="of each request's budget (the client's wait, budget_us), leave this much for the "
                             "transport and the reply: a face card whose route would not end inside the rest "
                             "serves its fallback instead (default %(default)g; docs/server.md, Deadlines)")
    parser.add_argument("--log-format", choices=("json", "text"), default="json", help="log lines (default json)")


# How long after the grace period cancelled calls may take to end.
STOP_MARGIN_S = 0.5
HEALTH_SERVICES = ("", SERVICE_NAME)  # the server as a whole, and WarmStart


class HealthServicer(health.HealthServicer):
    """grpcio-health's servicer with List, which health.proto declares and
    grpcio-health 1.85 leaves unimplemented (UNIMPLEMENTED and a logged
    traceback per call)."""

    def List(self, request, context):
        return health_pb2.HealthListResponse(statuses={
            name: self.Check(health_pb2.HealthCheckRequest(service=name), context) for name in HEALTH_SERVICES})


class Server:
    """A running service: `server.port`, `server.stop(grace)`. Used by the
    command and, in-process, by tests and benchmarks."""

    def __init__(self, *, models: Path | None, bind: str = "127.0.0.1:0", max_concurrent: int = 64,
                 max_queue: int = 256, batch_max: int = 0, batch_delay_us: int = 500,
                 intra_op_threads: int = 1, inter_op_threads: int = 1, limits: Limits = Limits(),
                 random_seed: int = 0, credentials: grpc.ServerCredentials | None = None,
                 fault: FaultDelay | None = None, stream_idle_s: float = STREAM_IDLE_S,
                 deadline_margin_s: float = DEADLINE_MARGIN_S, skip_bad_models: bool = False):
        self.models = load_models(models, intra_op_threads=intra_op_threads, inter_op_threads=inter_op_threads,
                                  max_grid_nodes=limits.max_grid_nodes, skip_bad=skip_bad_models) if models else []
        self.batchers = []
        if batch_max > 0:
            for m in (m for m in self.models if m.batchable):  # graph models have no grid to stack
                b = MicroBatcher(m.run_session, max_batch=batch_max, max_delay_us=batch_delay_us,
                                 max_queue=max_queue)
                m.infer = b
                self.batchers.append(b)
        self.idle = IdleStreams(stream_idle_s) if stream_idle_s > 0 else None
        self.service = WarmStartService(self.models + providers(random_seed, limits.max_grid_nodes), limits, fault,
                                        self.idle, deadline_margin_s)
        # Each open stream holds a worker thread, so the pool is as large as the RPC bound.
        self.grpc = grpc.server(futures.ThreadPoolExecutor(max_workers=max_concurrent, thread_name_prefix="rpc"),
                                interceptors=(MalformedRequests(),), maximum_concurrent_rpcs=max_concurrent)
        add_to_server(self.service, self.grpc)
        self.health = HealthServicer()
        health_pb2_grpc.add_HealthServicer_to_server(self.health, self.grpc)
        reflection.enable_server_reflection((SERVICE_NAME, health.SERVICE_NAME, reflection.SERVICE_NAME), self.grpc)
        try:
            if credentials is None:
                self.port = self.grpc.add_insecure_port(bind)
            else:
                self.port = self.grpc.add_secure_port(bind, credentials)
        except RuntimeError:  # gRPC raises for an address it cannot bind (a missing folder, a foreign host)
            self.port = 0
        if self.port == 0:
            raise OSError(f"cannot bind {bind} (a local address, and for unix:PATH a folder that exists)")
        # A Unix socket (unix:PATH) has no host or port: gRPC answers 1 for a bound one. Clients
        # dial the bind string itself, and the metrics endpoint, which is HTTP on TCP, stays on loopback.
        self.unix = bind.startswith(("unix:", "unix-abstract:"))
        self.host = "127.0.0.1" if self.unix else bind.rsplit(":", 1)[0]
        self.bind = bind

    @property
    def address(self) -> str:
        """What a client dials: host:port, or the unix: address as bound."""
        return self.bind if self.unix else f"{self.host}:{self.port}"

    def start(self) -> "Server":
        self.grpc.start()
        if self.idle is not None:
            self.idle.start()
        for name in HEALTH_SERVICES:
            self.health.set(name, health_pb2.HealthCheckResponse.SERVING)
        return self

    def stop(self, grace: float = 0.0) -> bool:
        """Report NOT_SERVING, refuse new RPCs, let open ones finish within
        grace seconds, cancel the rest. Returns whether every RPC ended; waits
        no longer than grace + STOP_MARGIN_S, so a call gRPC never finishes
        cannot hold the caller."""
        self.health.enter_graceful_shutdown()
        ended = self.grpc.stop(grace).wait(grace + STOP_MARGIN_S)
        if self.idle is not None:
            self.idle.stop()
        for b in self.batchers:
            b.close(timeout=0.1)
        return ended


def run(args: argparse.Namespace) -> int:
    # Arguments first: a refused command leaves the caller's logging as it was.
    problem = _argument_problem(args)
    if problem:
        print(f"deepcontact serve: {problem}", file=sys.stderr)
        return 2
    try:
        credentials = (tls.server_credentials(args.tls_cert, args.tls_key, args.tls_client_ca) if args.tls_cert
                       else None)
    except ValueError as exc:  # a file that cannot be read, or a key of another certificate
        print(f"deepcontact serve: {exc}", file=sys.stderr)
        return 2
    # One BLAS thread per call: the server's parallelism is its requests. SciPy's OpenBLAS,
    # loaded on the first solve of a face card (deepcontact.faces.solve_on_face), would
    # otherwise start a thread per core and make every small least-squares solve wait on
    # them, about twice as slow at the median on 2 busy cores and ten times at the p90.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    keep_freed_memory()  # a step's large arrays reused warm, not mapped afresh (server/heap.py)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter() if args.log_format == "json"
                         else logging.Formatter("%(asctime)s %(levelname)s %(message)s"))
    logging.basicConfig(level=logging.INFO, handlers=[handler], force=True)
    try:
        server = Server(models=args.models, bind=args.bind, max_concurrent=args.max_concurrent,
                        max_queue=args.max_queue, batch_max=args.batch_max, batch_delay_us=args.batch_delay_us,
                        intra_op_threads=args.intra_op_threads, inter_op_threads=args.inter_op_threads,
                        limits=Limits(args.max_bodies, args.max_points, args.max_grid_nodes),
                        random_seed=args.random_seed,
                        credentials=credentials,
                        fault=FaultDelay(args.fault_delay_ms / 1e3, args.fault_every) if args.fault_delay_ms else None,
                        stream_idle_s=args.stream_idle_s, deadline_margin_s=args.deadline_margin_ms / 1e3,
                        skip_bad_models=args.skip_bad_models)
    except (ModelCardError, OSError, ValueError) as exc:
        print(f"deepcontact serve: {exc}", file=sys.stderr)
        return 2
    # Everything loaded so far (the models, ONNX Runtime, NumPy, SciPy) lives as long as the
    # server: kept out of the collector's full passes, which otherwise walk it every few
    # thousand steps and hold a step for milliseconds.
    gc.freeze()
    server.start()
    if args.metrics_port:
        metrics.serve_metrics(args.metrics_port, host=server.host)
    if args.port_file:
        write_bytes_atomic(args.port_file, f"{server.port}\n".encode())
    if credentials is None and not tls.is_local_bind(args.bind):  # only with --insecure (_argument_problem)
        log.warning(f"serving plaintext on a non-loopback address, {server.address}: anyone who reaches it can "
                    "use the service (--insecure)", extra={"address": server.address, "insecure": True})
    for model in server.models:  # what each served model is, a line each
        log.info(f"model {model.name}: {model.description or '(no description on its card)'}",
                 extra={"model": model.name, "kind": model.kind})
    log.info("serving", extra={"address": server.address, "pid": os.getpid(),
                               "models": sorted(server.service.predictors), "tls": credentials is not None,
                               "mutual_tls": args.tls_client_ca is not None,
                               "batch_max": args.batch_max, "fault_delay_ms": args.fault_delay_ms})
    _serve_until_signalled(server, args.grace)
    _exit(0)


def _argument_problem(args: argparse.Namespace) -> str | None:
    """The first thing wrong with `deepcontact serve`'s arguments, in a sentence, or None."""
    if not args.models.is_dir():
        return f"{args.models} is not a folder of models"
    if args.grace < 0 or args.fault_delay_ms < 0 or args.stream_idle_s < 0 or args.fault_every < 1 \
            or not args.deadline_margin_ms >= 0:
        return "--grace, --fault-delay-ms, --stream-idle-s and --deadline-margin-ms must be >= 0, --fault-every >= 1"
    if min(args.max_bodies, args.max_points, args.max_grid_nodes) < 1:
        return "--max-bodies, --max-points and --max-grid-nodes must be >= 1"
    if bool(args.tls_cert) != bool(args.tls_key):
        return "--tls-cert and --tls-key go together"
    if args.tls_client_ca and not args.tls_cert:
        return "--tls-client-ca needs --tls-cert and --tls-key: client certificates are checked by a TLS server"
    if not args.tls_cert and not args.insecure and not tls.is_local_bind(args.bind):
        return (f"--bind {args.bind} is not a loopback address or a Unix socket: serve it with --tls-cert and "
                "--tls-key, or give --insecure to serve plaintext there")
    return None


def _serve_until_signalled(server: "Server", grace: float) -> None:
    """Block until SIGTERM or SIGINT, then drain for up to `grace` seconds; a second
    signal exits at once."""
    stop = threading.Event()

    def on_signal(signum, _frame):
        if stop.is_set():  # the operator will not wait for the drain
            log.warning("second signal: exiting now", extra={"signal": signal.Signals(signum).name})
            _exit(128 + signum)
        stop.set()

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, on_signal)
    stop.wait()
    log.info("shutting down", extra={"grace_s": grace})
    if server.stop(grace):
        log.info("stopped")
    else:
        log.warning("stopped with RPCs that did not end after cancellation")


def _exit(code: int) -> None:
    """Flush the log and end the process now.

    Not a return to the interpreter: its exit joins every thread of the RPC
    pool (ThreadPoolExecutor threads are not daemons), so one handler stuck
    in a model, a sleep or a call gRPC never finished would keep a stopped
    server alive indefinitely.
    """
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)
