"""A real `deepcontact serve` process: bytes that are not messages get
INVALID_ARGUMENT on every RPC it serves, and SIGTERM stops it within grace + 1 s
whatever was sent before, with streams open or a handler stuck."""

from __future__ import annotations

import random
import signal
import subprocess
import threading
import time

import grpc
import pytest
from google.protobuf import message_factory
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from deepcontact import wire
from deepcontact.v1 import warmstart_pb2 as pb
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.process import ServerProcess

GRACE_S = 1.0
BAD_CODES = (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN, grpc.StatusCode.UNAVAILABLE)


def served_rpcs():
    """(full method name, method descriptor) of every RPC declared in proto/ and
    of the health and reflection services the server adds, from their descriptors."""
    for file in (pb.DESCRIPTOR, health_pb2.DESCRIPTOR, reflection_pb2.DESCRIPTOR):
        for service in file.services_by_name.values():
            for method in service.methods:
                yield f"/{service.full_name}/{method.name}", method


def malformed_payloads(message_type, seed: int = 0) -> list[bytes]:
    """Bytes that the request type's own parser refuses: an absurd length
    prefix, a truncated varint, an invalid wire type, a message cut short, and
    random bytes."""
    cls = message_factory.GetMessageClass(message_type)
    rng = random.Random(seed)
    candidates = [b"\x0a\xff\xff\xff\xff\x0fab", b"\x08", b"\x0f\x01", b"\x3a\x20" + b"x" * 8]
    candidates += [rng.randbytes(rng.randint(1, 300)) for _ in range(40)]
    out = []
    for data in candidates:
        try:
            cls.FromString(data)
        except Exception:
            out.append(data)
    assert len(out) >= 5, message_type.full_name
    return out[:8]


def call(channel, name: str, method, payloads: list[bytes], timeout: float = 5.0):
    """Send raw request bytes; returns (replies, status code)."""
    kind = ("stream" if method.client_streaming else "unary") + "_" + ("stream" if method.server_streaming else "unary")
    rpc = getattr(channel, kind)(name)  # no serializers: bytes travel as they are
    replies = []
    try:
        answer = rpc(iter(payloads) if method.client_streaming else payloads[0], timeout=timeout)
        for reply in (answer if method.server_streaming else [answer]):
            replies.append(reply)
        return replies, grpc.StatusCode.OK
    except grpc.RpcError as err:
        return replies, err.code()


def serving(address: str) -> int:
    with grpc.insecure_channel(address) as channel:
        return health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"), timeout=5).status


def sigterm_and_time_exit(srv: ServerProcess, within: float) -> tuple[int, float]:
    t0 = time.monotonic()
    srv.proc.send_signal(signal.SIGTERM)
    try:
        code = srv.proc.wait(timeout=within + 10)
    except subprocess.TimeoutExpired:
        srv.kill()
        pytest.fail(f"still running {within + 10:.0f} s after SIGTERM")
    return code, time.monotonic() - t0


@pytest.fixture()
def serve(model_dir, tmp_path):
    started = []

    def start(*extra):
        srv = ServerProcess(model_dir, "--grace", str(GRACE_S), *extra, log=tmp_path / "serve.log").start()
        started.append(srv)
        return srv

    yield start
    for srv in started:
        srv.kill()


def test_every_rpc_answers_malformed_bytes_with_invalid_argument_then_sigterm_stops_it(serve, tmp_path,
                                                                                      thesis_steps):
    world, steps = thesis_steps
    valid_first = {  # a first message each stream answers, so the bad one comes mid-stream
        "deepcontact.v1.StepRequest": wire.encode_step(0, "zero", *steps[0], world=world).SerializeToString(),
        "grpc.reflection.v1alpha.ServerReflectionRequest":
            reflection_pb2.ServerReflectionRequest(list_services="").SerializeToString(),
    }
    srv = serve()
    rpcs = dict(served_rpcs())
    with grpc.insecure_channel(srv.address) as channel:
        listed = set(ProtoReflectionDescriptorDatabase(channel).get_services())
        assert listed == {name.split("/")[1] for name in rpcs}  # nothing served goes untested
        for name, method in rpcs.items():
            for i, bad in enumerate(malformed_payloads(method.input_type, seed=len(name))):
                replies, code = call(channel, name, method, [bad])
                assert code == grpc.StatusCode.INVALID_ARGUMENT, (name, bad)
                if method.client_streaming:
                    first = valid_first.get(method.input_type.full_name, b"")
                    replies, code = call(channel, name, method, [first, bad, first])
                    assert code == grpc.StatusCode.INVALID_ARGUMENT, (name, bad)
                    assert len(replies) == 1, name  # the good message was answered, the bad one ended it
            # Empty bytes parse (an empty message): answered by the service, never an internal error.
            assert call(channel, name, method, [b""], timeout=0.5)[1] not in BAD_CODES
        # A flood of bad requests.
        predict = channel.unary_unary("/deepcontact.v1.WarmStart/Predict")
        for _ in range(50):
            with pytest.raises(grpc.RpcError):
                predict(b"\x0f\x01", timeout=5)
        # Still serving, and correctly.
        assert serving(srv.address) == health_pb2.HealthCheckResponse.SERVING
        reply = pb_grpc.WarmStartStub(channel).Predict(wire.encode_step(3, "bad", *steps[0], world=world))
        assert reply.step == 3 and (wire.decode_impulses(reply)[0] == 50).all()

    code, took = sigterm_and_time_exit(srv, GRACE_S + 1)
    assert code == 0 and took < GRACE_S + 1
    log = (tmp_path / "serve.log").read_text()
    assert "Traceback" not in log
    assert '"msg": "stopped"' in log
    rejected_predict = [line for line in log.splitlines()
                        if '"rejected"' in line and "WarmStart/Predict" in line and "protobuf" in line]
    assert len(rejected_predict) == 1  # 58 refusals within seconds: one log line


def test_sigterm_reports_not_serving_at_once_and_exits_with_a_stream_open_and_a_handler_stuck(serve, thesis_steps):
    world, steps = thesis_steps
    srv = serve("--fault-delay-ms", "60000", "--fault-every", "2")  # step 2 holds its handler for a minute
    with grpc.insecure_channel(srv.address) as channel:
        statuses = []
        watch = health_pb2_grpc.HealthStub(channel).Watch(
            health_pb2.HealthCheckRequest(service="deepcontact.v1.WarmStart"))
        watcher = threading.Thread(target=lambda: statuses.extend(r.status for r in _until_error(watch)))
        watcher.start()
        stub = pb_grpc.WarmStartStub(channel)
        gate = threading.Event()

        def idle_stream():  # one step, then the simulation goes quiet without closing
            yield wire.encode_step(1, "zero", *steps[0], world=world)
            gate.wait(30)

        idle = stub.Stream(idle_stream())
        assert next(idle).step == 1
        stuck = stub.Predict.future(wire.encode_step(2, "zero", *steps[0], world=world))
        time.sleep(0.3)  # the stuck step reaches its handler
        try:
            code, took = sigterm_and_time_exit(srv, GRACE_S + 1)
        finally:
            gate.set()
        watcher.join(5)
    assert code == 0 and took < GRACE_S + 1
    assert statuses[:2] == [health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING]
    with pytest.raises(grpc.RpcError):
        stuck.result()


def test_a_second_signal_exits_at_once(model_dir, tmp_path, thesis_steps):
    world, steps = thesis_steps
    srv = ServerProcess(model_dir, "--grace", "60", log=tmp_path / "serve.log").start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            gate = threading.Event()

            def idle_stream():
                yield wire.encode_step(1, "zero", *steps[0], world=world)
                gate.wait(30)

            idle = pb_grpc.WarmStartStub(channel).Stream(idle_stream())
            assert next(idle).step == 1  # this stream would hold the drain for 60 s
            srv.proc.send_signal(signal.SIGTERM)
            # The first signal handled (Python runs handlers in the main thread when it next runs:
            # on a loaded machine both could be pending at once, and be handled in signal order).
            log = tmp_path / "serve.log"
            until = time.monotonic() + 10
            while "shutting down" not in log.read_text() and time.monotonic() < until:
                time.sleep(0.02)
            assert srv.proc.poll() is None  # draining
            t0 = time.monotonic()
            srv.proc.send_signal(signal.SIGINT)
            assert srv.proc.wait(timeout=10) == 128 + signal.SIGINT
            assert time.monotonic() - t0 < 5
            gate.set()
    finally:
        srv.kill()
    assert "second signal" in (tmp_path / "serve.log").read_text()


def _until_error(replies):
    try:
        yield from replies
    except grpc.RpcError:
        return
