"""The streaming client: one bidirectional stream per simulation, in lockstep.

    with WarmStartClient("127.0.0.1:50051") as client:
        reply = client.step(request, timeout=0.005)   # send step k, wait for reply k

The client owns its channel. A simulation sends a step and waits for its
reply before the next one, so the request iterator handed to gRPC is fed from
a queue one message at a time (a plain generator would be drained eagerly and
the round trips would include queueing). A step that does not come back in
time, or a broken stream, raises `StepFailed`; the caller falls back for that
step. A reply that misses its deadline is never used: the stream stays open, and
the late reply, which comes before the next step's (replies keep the order of
the steps), is dropped when it arrives; only where more than MAX_LATE replies
are owed at once (a server that stopped answering) is the stream dropped, and
the next `step()` reopens it and resends the world. After a broken stream,
reopening waits out an exponential backoff (50 ms doubling to 2 s by default;
steps meanwhile fail at once, unsent), and the channel reconnects at least
every 0.5 s, so a restarted server gets its learned warm starts back within
about the backoff cap (+ 0.5 s) of coming up. Each step carries when it was
sent (sent_unix_us), so that a server on the same host counts its budget from
there.
A stream the server ended between steps (it ends streams idle for a minute,
`deepcontact serve --stream-idle-s`) is replaced by a fresh one for the next
step: a simulation paused for longer loses no step.
"""

from __future__ import annotations

import collections
import queue
import threading
import time

import grpc

from deepcontact.v1 import warmstart_pb2 as pb
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc

_END = object()
# During an outage the channel tries to connect at least this often (a TCP connect, cheap).
CHANNEL_RECONNECT_MAX_S = 0.5
#: Late replies a stream may owe before it is taken for broken and dropped. Reopening a stream
#: costs the server a new RPC and the world's declaration: under load, dropping a stream at
#: every late reply turned a few late steps into a storm of reconnections.
MAX_LATE = 4


class StepFailed(RuntimeError):
    """No usable reply for this step: deadline, server error, or no server.

    `reason` is a short key for counting: the gRPC status code's name
    (DEADLINE_EXCEEDED for a missed deadline), BACKING_OFF (not sent: the
    stream is waiting out its reconnect backoff), STREAM_ENDED or WRONG_STEP.
    """

    def __init__(self, message: str, code: grpc.StatusCode | None = None, *, reason: str | None = None):
        super().__init__(message)
        self.code = code
        self.reason = reason or (code.name if code is not None else "OTHER")

    @property
    def backing_off(self) -> bool:
        return self.reason == "BACKING_OFF"


# Codes with which the server refuses a model or a world outright (a fixed-grid model asked for a
# grid of another size, a domain past the server's grid bound, an unknown model): every later
# step of the same simulation would get the same answer, so falling back and retrying would
# only hide the reason.
REFUSALS = frozenset({grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND,
                      grpc.StatusCode.FAILED_PRECONDITION})


class Refused(StepFailed):
    """The server refused a model for this world when the world was declared (`declare`);
    the message is the server's reason."""


class WarmStartClient:
    """A channel and, lazily, one open stream to a warm-start server.

    target: "host:port" or any gRPC target ("dns:///server:50051" with
    round_robin spreads streams over replicas). world: the World message to
    (re)send as the first message of every stream.
    """

    def __init__(self, target: str, *, world: pb.World | None = None,
                 credentials: grpc.ChannelCredentials | None = None,
                 backoff_s: tuple[float, float] = (0.05, 2.0)):
        self._backoff_min, self._backoff_max = backoff_s
        options = [("grpc.lb_policy_name", "round_robin"), ("grpc.enable_retries", 0),
                   # The channel reconnects on its own schedule, by default 1 s growing 1.6x to 120 s:
                   # after a long outage it would still be waiting when the server is back, and our
                   # streams fail fast on it. Bounded here, it is connected again by the time our
                   # own backoff lets the next stream try.
                   ("grpc.initial_reconnect_backoff_ms", int(1e3 * self._backoff_min)),
                   ("grpc.min_reconnect_backoff_ms", int(1e3 * self._backoff_min)),
                   ("grpc.max_reconnect_backoff_ms", int(1e3 * min(self._backoff_max, CHANNEL_RECONNECT_MAX_S)))]
        self.channel = (grpc.secure_channel(target, credentials, options) if credentials
                        else grpc.insecure_channel(target, options))
        self.stub = pb_grpc.WarmStartStub(self.channel)
        self.world = world
        self._backoff = 0.0
        self._retry_at = 0.0
        self._outbox: queue.SimpleQueue | None = None
        self._inbox: queue.SimpleQueue | None = None
        self._replies = None
        self._late: collections.deque = collections.deque()  # (step, model) whose replies the stream still owes
        self._opened = False
        self.reconnects = 0  # streams reopened after the first

    # -- lifecycle ---------------------------------------------------------
    def close(self) -> None:
        self._close_stream()
        self.channel.close()

    def __enter__(self) -> "WarmStartClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def wait_ready(self, timeout: float) -> bool:
        """True once the channel connects within timeout (seconds)."""
        ready = grpc.channel_ready_future(self.channel)
        try:
            ready.result(timeout=timeout)
            return True
        except grpc.FutureTimeoutError:
            # Unsubscribes it: its polling thread would otherwise outlive the channel
            # and print a traceback when the channel closes.
            ready.cancel()
            return False

    def set_world(self, world: pb.World) -> None:
        """Declare another world (a new dt or gravity): the open stream, which declared the old
        one, is closed, and the next step opens one led by this world."""
        self.world = world
        self._close_stream()

    def list_models(self, timeout: float = 5.0) -> list[pb.ModelInfo]:
        return list(self.stub.ListModels(pb.ListModelsRequest(), timeout=timeout).models)

    # -- one step ----------------------------------------------------------
    def declare(self, model: str, timeout: float) -> bool:
        """Open the stream now with a message that only declares the world, so
        the server readies `model` for this world's grid (ONNX Runtime's first run
        of a grid shape is slow) before the first step with contacts. Waits up to
        `timeout` s; False when no reply came (the first step then opens a
        stream as usual). Raises Refused when the server refuses `model` for
        this world (a code in REFUSALS)."""
        try:
            self.step(pb.StepRequest(step=0, model=model), timeout)
            return True
        except StepFailed as exc:
            if exc.code in REFUSALS:
                raise Refused(str(exc), exc.code) from None
            return False

    def step(self, request: pb.StepRequest, timeout: float) -> pb.Impulses:
        """Send one step on the stream and wait up to `timeout` s for its reply. The request
        carries the wait as its budget_us (unless the caller set one), so that a server can
        answer a cheaper model in time rather than a dear one too late."""
        deadline = time.monotonic() + timeout
        if not request.budget_us:
            request.budget_us = min(int(timeout * 1e6), 2**32 - 1)
        request.sent_unix_us = time.time_ns() // 1000
        reused = self._replies is not None
        got = self._exchange(request, timeout)
        if reused and isinstance(got, grpc.RpcError) and got.code() == grpc.StatusCode.CANCELLED:
            # The server ended the stream while this simulation was not using it (it ends streams
            # idle past its --stream-idle-s, server.idle): the step goes once more, on a fresh stream.
            self._close_stream()
            got = self._exchange(request, max(0.0, deadline - time.monotonic()))
        if isinstance(got, grpc.RpcError):
            self._close_stream(failed=True)
            raise StepFailed(f"{got.code().name}: {got.details()}", got.code())
        if got is _END:
            self._close_stream(failed=True)
            raise StepFailed("the server ended the stream", reason="STREAM_ENDED")
        if got.step != request.step:
            self._close_stream(failed=True)
            raise StepFailed(f"reply for step {got.step} while waiting for step {request.step}",
                             reason="WRONG_STEP")
        self._backoff = 0.0
        return got

    # -- the stream ---------------------------------------------------------
    def _exchange(self, request: pb.StepRequest, timeout: float):
        """Put `request` on the stream (opening one, led by the world, if none is open) and
        return what comes back within `timeout` s: a reply, a grpc.RpcError or _END."""
        if self._replies is None:
            self._open_stream()
            if self.world is not None:
                request.world.CopyFrom(self.world)
        self._outbox.put(request)
        until = time.monotonic() + timeout
        while True:
            try:
                got = self._inbox.get(timeout=max(0.0, until - time.monotonic()))
            except queue.Empty:
                # Its reply will come before the next step's: owed, and dropped when it arrives.
                self._late.append((request.step, request.model))
                if len(self._late) > MAX_LATE:  # a server that stopped answering: a fresh stream next step
                    self._close_stream()
                raise StepFailed(f"no reply within {timeout * 1e3:.1f} ms",
                                 grpc.StatusCode.DEADLINE_EXCEEDED) from None
            if self._late and not isinstance(got, grpc.RpcError) and got is not _END \
                    and (got.step, got.model) == self._late[0]:
                self._late.popleft()  # a step that missed its deadline, answered late: not used
                continue
            return got

    def _open_stream(self) -> None:
        now = time.monotonic()
        if now < self._retry_at:
            raise StepFailed(f"reconnecting in {1e3 * (self._retry_at - now):.0f} ms", grpc.StatusCode.UNAVAILABLE,
                             reason="BACKING_OFF")
        # SimpleQueue, not Queue: each round trip crosses two of them, and the C queue hands a
        # step from thread to thread with less of the interpreter's work than Queue's condition.
        outbox: queue.SimpleQueue = queue.SimpleQueue()
        inbox: queue.SimpleQueue = queue.SimpleQueue()

        def requests():
            while True:
                item = outbox.get()
                if item is _END:
                    return
                yield item

        replies = self.stub.Stream(requests())

        def read():
            # One reader per stream: replies (or the stream's end or error) go to the inbox.
            try:
                for reply in replies:
                    inbox.put(reply)
                inbox.put(_END)
            except grpc.RpcError as err:
                inbox.put(err)

        threading.Thread(target=read, name="warmstart-reader", daemon=True).start()
        if self._opened:
            self.reconnects += 1
        self._opened = True
        self._outbox, self._inbox, self._replies = outbox, inbox, replies

    def _close_stream(self, failed: bool = False) -> None:
        if self._outbox is not None:
            self._outbox.put(_END)
        if self._replies is not None:
            self._replies.cancel()
        self._outbox = self._inbox = self._replies = None
        self._late.clear()
        if failed:
            self._backoff = min(self._backoff_max, max(self._backoff_min, 2 * self._backoff))
            self._retry_at = time.monotonic() + self._backoff
