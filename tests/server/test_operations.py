"""Operating the server: micro-batching, overload, shutdown, TLS, reflection, stubs."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from deepcontact import protogen, wire
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.serve import Server


def stream_steps(address, world, steps, model, first_step, out, barrier=None):
    with grpc.insecure_channel(address) as channel:
        stub = pb_grpc.WarmStartStub(channel)
        if barrier is not None:
            barrier.wait()

        def requests():
            for k, (bodies, points) in enumerate(steps):
                yield wire.encode_step(first_step + k, model, bodies, points, world=world if k == 0 else None)

        out.extend(stub.Stream(requests()))


def test_micro_batching_merges_streams_and_keeps_each_reply_its_own(model_dir, thesis_steps):
    world, steps = thesis_steps
    plain = Server(models=model_dir).start()
    batched = Server(models=model_dir, batch_max=4, batch_delay_us=20_000).start()
    try:
        expected: list = []
        stream_steps(plain.address, world, steps, "tiny", 0, expected)
        outs = [[] for _ in range(4)]
        barrier = threading.Barrier(4)
        threads = [threading.Thread(target=stream_steps, args=(batched.address, world, steps, "tiny", 1000 * i,
                                                               outs[i], barrier)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        batcher = batched.batchers[0]
        assert batcher.batches < 4 * len(steps)  # some steps shared an ONNX call
        for i, out in enumerate(outs):
            assert [r.step for r in out] == [1000 * i + k for k in range(len(steps))]
            for got, want in zip(out, expected):
                np.testing.assert_allclose(wire.decode_impulses(got), wire.decode_impulses(want), rtol=1e-5, atol=1e-6)
    finally:
        plain.stop()
        batched.stop()


def test_past_the_concurrency_bound_clients_get_resource_exhausted_at_once(model_dir, thesis_steps):
    world, steps = thesis_steps
    server = Server(models=model_dir, max_concurrent=1).start()
    gate = threading.Event()
    try:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)

            def held():  # a stream that stays open until the gate opens
                yield wire.encode_step(0, "zero", *steps[0], world=world)
                gate.wait(10)

            first = stub.Stream(held())
            next(first)
            t0 = time.monotonic()
            with pytest.raises(grpc.RpcError) as err:
                stub.Predict(wire.encode_step(1, "zero", *steps[0], world=world), timeout=5)
            assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert time.monotonic() - t0 < 1.0
            gate.set()
            list(first)
    finally:
        gate.set()
        server.stop()


@pytest.mark.parametrize("extra, says", [
    (["--models", "no-such-folder"], "not a folder of models"),
    (["--grace", "-1"], "--grace"),
    (["--max-points", "0"], "--max-points"),
    (["--stream-idle-s", "-1"], "--stream-idle-s"),
    (["--tls-cert", "cert.pem"], "--tls-cert and --tls-key go together"),
])
def test_serve_refuses_bad_arguments_before_it_binds_or_logs(model_dir, capsys, extra, says):
    from commands import main

    assert main(["serve", "--models", str(model_dir), "--bind", "127.0.0.1:0", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("deepcontact serve: ") and says in err


def test_sigterm_drains_and_exits_cleanly(model_dir, tmp_path, thesis_steps):
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, "-m", "commands", "serve", "--models", str(model_dir),
                             "--bind", "127.0.0.1:0", "--port-file", str(port_file), "--grace", "2"],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not port_file.exists():
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        address = f"127.0.0.1:{port_file.read_text().strip()}"
        with grpc.insecure_channel(address) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10).status
            assert status == health_pb2.HealthCheckResponse.SERVING
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=15) == 0
        log = proc.stderr.read()
        assert '"msg": "serving"' in log and '"msg": "stopped"' in log
    finally:
        if proc.poll() is None:
            proc.kill()


def test_tls(model_dir, tmp_path, thesis_steps):
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", str(key), "-out", str(cert),
                    "-days", "1", "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost"],
                   check=True, capture_output=True)
    creds = grpc.ssl_server_credentials([(key.read_bytes(), cert.read_bytes())])
    server = Server(models=model_dir, bind="localhost:0", credentials=creds).start()
    try:
        channel_creds = grpc.ssl_channel_credentials(root_certificates=cert.read_bytes())
        with grpc.secure_channel(f"localhost:{server.port}", channel_creds) as channel:
            world, steps = thesis_steps
            reply = pb_grpc.WarmStartStub(channel).Predict(wire.encode_step(0, "bad", *steps[0], world=world))
            assert reply.point_count == len(steps[0][1])
    finally:
        server.stop()


def test_a_server_on_a_unix_socket_is_dialled_at_its_bind_address(model_dir, tmp_path, thesis_steps):
    bind = f"unix:{tmp_path / 'warmstart.sock'}"
    server = Server(models=model_dir, bind=bind).start()
    try:
        assert server.address == bind and server.host == "127.0.0.1"  # the metrics endpoint stays on loopback
        with grpc.insecure_channel(server.address) as channel:
            world, steps = thesis_steps
            reply = pb_grpc.WarmStartStub(channel).Predict(wire.encode_step(0, "bad", *steps[0], world=world))
            assert reply.point_count == len(steps[0][1])
    finally:
        server.stop()


def test_an_address_it_cannot_bind_is_refused_with_the_address(model_dir, tmp_path, capsys):
    from commands import main

    bind = f"unix:{tmp_path / 'no-such-folder' / 'warmstart.sock'}"
    assert main(["serve", "--models", str(model_dir), "--bind", bind]) == 2
    err = capsys.readouterr().err
    assert err.startswith("deepcontact serve: cannot bind ") and bind in err


def test_reflection_lists_the_service(server):
    with grpc.insecure_channel(server.address) as channel:
        services = ProtoReflectionDescriptorDatabase(channel).get_services()
    assert "deepcontact.v1.WarmStart" in services and "grpc.health.v1.Health" in services


def test_generated_stubs_are_up_to_date():
    # In a process of its own: after the training tests have run TensorFlow in this one,
    # grpc_tools' protoc crashed it (a segmentation fault in protogen.generate).
    check = subprocess.run([sys.executable, "-m", "deepcontact.protogen", "--check"], cwd=protogen.ROOT,
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stderr or "run `make proto`"


def test_prometheus_metrics_count_steps_and_errors(model_dir, tmp_path, thesis_steps):
    import socket
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        metrics_port = s.getsockname()[1]
    from server.process import ServerProcess

    world, steps = thesis_steps
    with ServerProcess(model_dir, "--metrics-port", str(metrics_port)) as server:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            stub.Predict(wire.encode_step(0, "tiny", *steps[0], world=world))
            with pytest.raises(grpc.RpcError):
                stub.Predict(wire.encode_step(0, "nope", *steps[0], world=world))
        text = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10).read().decode()
    assert 'deepcontact_steps_total{model="tiny"} 1.0' in text
    assert 'deepcontact_errors_total{code="NOT_FOUND"} 1.0' in text
    assert 'deepcontact_stage_seconds_count{stage="inference"} 1.0' in text
