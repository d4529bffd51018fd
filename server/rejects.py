"""Refusing a request: count it, log it (not too often), end the RPC with a status.

Every refusal, whatever its cause, is counted in Prometheus
(`deepcontact_errors_total{code}`) and answered with its status and a short
message. The log gets one line per RPC method and status code per interval
(10 s) at most, saying how many refusals it left out since the last one: a
client that floods the server with bad requests must not flood its log.
A stream is ended by its first refused message, so it logs once at most.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Hashable
from typing import NoReturn

import grpc

from server import metrics

log = logging.getLogger("deepcontact.server")
LOG_INTERVAL_S = 10.0


class LogLimiter:
    """Admits one event per key per `interval_s` seconds.

        left_out = limiter.admit(key)   # None: do not log; n: log, n were left out before
    """

    def __init__(self, interval_s: float = LOG_INTERVAL_S, clock: Callable[[], float] = time.monotonic):
        self.interval_s = interval_s
        self._clock = clock
        self._lock = threading.Lock()
        self._last: dict[Hashable, float] = {}
        self._left_out: dict[Hashable, int] = {}

    def admit(self, key: Hashable) -> int | None:
        now = self._clock()
        with self._lock:
            last = self._last.get(key)
            if last is not None and now - last < self.interval_s:
                self._left_out[key] = self._left_out.get(key, 0) + 1
                return None
            self._last[key] = now
            return self._left_out.pop(key, 0)


_limiter = LogLimiter()


def reject(context: grpc.ServicerContext, code: grpc.StatusCode, message: str, *, rpc: str) -> NoReturn:
    """End the RPC with `code` and `message` (raises, as context.abort does)."""
    metrics.ERRORS.labels(code=code.name).inc()
    left_out = _limiter.admit((rpc, code))
    if left_out is not None:
        log.info("rejected", extra={"rpc": rpc, "code": code.name, "detail": message,
                                    "not_logged_since_last": left_out})
    context.abort(code, message)
