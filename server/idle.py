"""Ending streams that have gone quiet.

Every open stream holds one of the server's `--max-concurrent` worker threads
until it ends. A simulation that hangs, is paused, or sits on a machine that
dropped off the network (a half-open TCP connection, which gRPC's default
keepalive notices only after two hours) would keep its slot, and enough of them
lock every new client out with RESOURCE_EXHAUSTED. So a stream that has sent
nothing for `idle_s` seconds is cancelled by the server. The client in
simclient.client sends its next step once more on a fresh stream when the one
it had was cancelled, so a paused simulation resumes without a failed step.

The handler marks each message it receives (`touch`, a dict store: nothing on
the hot path waits or allocates a timer); one daemon thread looks over the open
streams a few times per `idle_s` and cancels the ones past it. gRPC's sync server
has no way for another thread to end an RPC with a status of its own, so the
client sees CANCELLED; the server logs which stream and why.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time

import grpc

from server import metrics

log = logging.getLogger("deepcontact.server")


class IdleStreams:
    """Open streams and when each last sent a message; cancels those idle past `idle_s`.

    idle_s: seconds without a message after which a stream is ended (> 0).
    """

    def __init__(self, idle_s: float):
        if not idle_s > 0:
            raise ValueError(f"idle_s must be > 0, got {idle_s}")
        self.idle_s = float(idle_s)
        self.ended = 0  # streams cancelled for idleness since start
        self._last: dict[int, list] = {}  # token -> [its last message's time, monotonic s; its context]
        self._tokens = itertools.count()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- called by the stream's handler --------------------------------------
    def open(self, context: grpc.ServicerContext) -> int:
        token = next(self._tokens)
        with self._lock:
            self._last[token] = [time.monotonic(), context]
        return token

    def touch(self, token: int) -> None:
        entry = self._last.get(token)
        if entry is not None:
            entry[0] = time.monotonic()

    def close(self, token: int) -> None:
        with self._lock:
            self._last.pop(token, None)

    def __len__(self) -> int:
        return len(self._last)

    # -- the watcher ----------------------------------------------------------
    def start(self) -> "IdleStreams":
        if self._thread is None:
            self._thread = threading.Thread(target=self._watch, name="idle-streams", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def _watch(self) -> None:
        # Looking four times per idle_s ends a stream between idle_s and 1.25 idle_s after its last message.
        while not self._stop.wait(self.idle_s / 4):
            self.end_idle(time.monotonic())

    def end_idle(self, now: float) -> int:
        """Cancel every stream whose last message is more than idle_s before `now` (monotonic s);
        returns how many."""
        with self._lock:
            stale = [(t, e) for t, e in self._last.items() if now - e[0] > self.idle_s]
            for token, _ in stale:
                del self._last[token]
        for _, (last, context) in stale:
            log.info("ended an idle stream", extra={"peer": context.peer(), "idle_s": round(now - last, 1),
                                                     "limit_s": self.idle_s})
            context.cancel()
            metrics.IDLE_ENDED.inc()
        self.ended += len(stale)
        return len(stale)
