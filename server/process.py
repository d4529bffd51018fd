"""Run `deepcontact serve` as a child process on a free loopback port (or a Unix socket).

Used by commands that need a server and were given none (the demo, the
iteration and load benchmarks) and by tests:

    with ServerProcess("models/") as server:
        client = WarmStartClient(server.address)

`local_socket=True` binds a Unix socket in the process's own temporary folder instead, the
plain choice for a server only this machine's clients dial (the iteration benchmark and the
demo); it saves a few per cent of the round trip at most (docs/performance.md).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import grpc
from grpc_health.v1 import health_pb2, health_pb2_grpc


class ServerProcess:
    def __init__(self, models: str | os.PathLike, *extra_args: str, bind: str = "127.0.0.1:0",
                 startup_timeout: float = 60.0, log: str | os.PathLike | None = None, local_socket: bool = False,
                 cpus: set[int] | None = None):
        self.models = Path(models)
        # The cores the server may run on (None: this process's): set in the child before it
        # starts, so every thread it makes inherits them and it counts them as its cores.
        self.cpus = set(cpus) if cpus is not None else None
        self.extra_args = list(extra_args)
        self.startup_timeout = startup_timeout
        self.log_path = Path(log) if log else None
        self.proc: subprocess.Popen | None = None
        self.port: int | None = None
        self._tmp = tempfile.TemporaryDirectory(prefix="deepcontact-serve-")
        # a fixed port may be shared by several processes (gRPC sets SO_REUSEPORT)
        self.bind = f"unix:{Path(self._tmp.name) / 'serve.sock'}" if local_socket else bind

    @property
    def address(self) -> str:
        """What a client dials: the loopback port bound, or a unix: bind as given."""
        return self.bind if self.bind.startswith(("unix:", "unix-abstract:")) else f"127.0.0.1:{self.port}"

    def start(self) -> "ServerProcess":
        port_file = Path(self._tmp.name) / "port"
        log = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "commands", "serve", "--models", str(self.models), "--bind", self.bind,
             "--port-file", str(port_file), *self.extra_args],
            stdout=log, stderr=log, env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=(lambda: os.sched_setaffinity(0, self.cpus)) if self.cpus is not None else None)
        deadline = time.monotonic() + self.startup_timeout
        while not port_file.exists():
            if self.proc.poll() is not None:
                raise RuntimeError(f"deepcontact serve exited with {self.proc.returncode} before serving"
                                   + (f" (log: {self.log_path})" if self.log_path else ""))
            if time.monotonic() > deadline:
                self.stop()
                raise TimeoutError(f"deepcontact serve did not start within {self.startup_timeout:.0f} s")
            time.sleep(0.02)
        self.port = int(port_file.read_text())
        self.wait_healthy(deadline - time.monotonic())
        return self

    def wait_healthy(self, timeout: float) -> None:
        with grpc.insecure_channel(self.address) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"), timeout=max(timeout, 1.0),
                wait_for_ready=True).status
        if status != health_pb2.HealthCheckResponse.SERVING:
            raise RuntimeError(f"server at {self.address} reports {status}")

    def stop(self, grace: float = 5.0) -> int | None:
        """SIGTERM, wait for the drain, SIGKILL if it hangs. Returns the exit code."""
        if self.proc is None or self.proc.poll() is not None:
            return self.proc.returncode if self.proc else None
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(timeout=grace + 10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()
        finally:
            self._tmp.cleanup()

    def kill(self) -> None:
        """SIGKILL, as a crash would."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()

    def __enter__(self) -> "ServerProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
