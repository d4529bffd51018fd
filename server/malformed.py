"""Bytes that are not a request message: INVALID_ARGUMENT, on every RPC served.

When a request deserializer raises, gRPC Python answers INTERNAL and logs a
traceback per request. On a request stream it does worse (grpcio 1.85,
grpc/_server.py): the failed parse sends the status and then ends the
handler's request iterator as if the client had closed its side, so the
handler returns normally and gRPC sends a second status. The core refuses
that second batch, its completion never comes, the call never leaves the
server's books, and `grpc.Server.stop(grace)` waits for it forever -- a
server that was sent one bad stream message does not stop on SIGTERM.

So no deserializer on this server raises. `MalformedRequests`, a server
interceptor, gives every handler a deserializer that returns a `Malformed`
marker instead of raising, and a behaviour that refuses the marker with
INVALID_ARGUMENT before the servicer sees it: the request of a unary RPC,
each message of a request stream. It wraps every service on the server
(WarmStart, health, reflection), so an RPC added to the proto is covered
without a list here.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from typing import Any

import grpc

from server.rejects import reject


@dataclasses.dataclass(frozen=True)
class Malformed:
    """What a request deserializer returns for bytes it cannot parse."""

    size: int  # bytes received
    reason: str  # the parser's complaint


def tolerant(deserializer: Callable[[bytes], Any] | None) -> Callable[[bytes], Any] | None:
    """`deserializer`, returning Malformed where it would raise."""
    if deserializer is None:  # the handler takes raw bytes: nothing to parse
        return None

    def parse(data: bytes) -> Any:
        try:
            return deserializer(data)
        except Exception as exc:  # DecodeError, or whatever a parser raises on junk
            return Malformed(len(data), str(exc) or type(exc).__name__)

    return parse


def _refuse(context: grpc.ServicerContext, method: str, bad: Malformed, which: str) -> None:
    reject(context, grpc.StatusCode.INVALID_ARGUMENT,
           f"{which} is not a valid protobuf message ({bad.size} bytes): {bad.reason}", rpc=method)


def _checked_stream(requests: Iterator, context: grpc.ServicerContext, method: str) -> Iterator:
    for i, request in enumerate(requests):
        if isinstance(request, Malformed):
            _refuse(context, method, request, f"message {i} of the request stream")
        yield request


def _guard(behavior: Callable | None, method: str, *, streaming: bool) -> Callable | None:
    if behavior is None:
        return None
    if streaming:
        def guarded(requests, context, *rest):
            return behavior(_checked_stream(requests, context, method), context, *rest)
    else:
        def guarded(request, context, *rest):
            if isinstance(request, Malformed):
                _refuse(context, method, request, "the request")
            return behavior(request, context, *rest)
    # gRPC reads these off the behaviour (health's Watch sets them).
    for attr in ("experimental_non_blocking", "experimental_thread_pool"):
        if hasattr(behavior, attr):
            setattr(guarded, attr, getattr(behavior, attr))
    return guarded


def guarded_handler(handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
    """The same handler with a tolerant deserializer and behaviours that refuse Malformed."""
    return handler._replace(
        request_deserializer=tolerant(handler.request_deserializer),
        unary_unary=_guard(handler.unary_unary, method, streaming=False),
        unary_stream=_guard(handler.unary_stream, method, streaming=False),
        stream_unary=_guard(handler.stream_unary, method, streaming=True),
        stream_stream=_guard(handler.stream_stream, method, streaming=True),
    )


class MalformedRequests(grpc.ServerInterceptor):
    """Server interceptor: every RPC's handler through `guarded_handler`
    (built once per method, then reused)."""

    def __init__(self):
        self._guarded: dict[str, tuple[grpc.RpcMethodHandler, grpc.RpcMethodHandler]] = {}

    def intercept_service(self, continuation, handler_call_details):
        handler = continuation(handler_call_details)
        if handler is None or handler.request_deserializer is None:
            return handler
        method = handler_call_details.method
        cached = self._guarded.get(method)
        if cached is None or cached[0] is not handler:
            cached = (handler, guarded_handler(handler, method))
            self._guarded[method] = cached
        return cached[1]
