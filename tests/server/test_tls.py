"""Safe to expose: plaintext only on loopback or a Unix socket, server TLS, mutual TLS
(deepcontact.tls), and the client commands' --tls-ca/--tls-cert/--tls-key, over a real
server. The certificates are made at test time with the openssl command line: a CA, a
server certificate for localhost and 127.0.0.1 and a client certificate it signed, and a
second, unrelated CA with a client certificate of its own."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from deepcontact import tls, wire
from commands import main
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.serve import Server
from simclient.client import StepFailed, WarmStartClient

OPENSSL = "/usr/bin/openssl"
KEY = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]


def _openssl(*args: str) -> None:
    subprocess.run([OPENSSL, *args], check=True, capture_output=True)


def _ca(folder: Path, name: str) -> tuple[Path, Path]:
    cert, key = folder / f"{name}.pem", folder / f"{name}.key"
    _openssl("req", "-x509", *KEY, "-keyout", str(key), "-out", str(cert), "-days", "1", "-subj", f"/CN={name}",
             "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    return cert, key


def _signed(folder: Path, name: str, ca: tuple[Path, Path], extensions: str) -> tuple[Path, Path]:
    cert, key, request, ext = (folder / f"{name}{s}" for s in (".pem", ".key", ".csr", ".ext"))
    _openssl("req", *KEY, "-keyout", str(key), "-out", str(request), "-subj", f"/CN={name}")
    ext.write_text(extensions + "\n")
    _openssl("x509", "-req", "-in", str(request), "-CA", str(ca[0]), "-CAkey", str(ca[1]), "-CAcreateserial",
             "-out", str(cert), "-days", "1", "-extfile", str(ext))
    return cert, key


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    """Paths: ca, server_cert/server_key (localhost, 127.0.0.1), client_cert/client_key (signed by
    ca), other_ca, other_cert/other_key (a client certificate of the other CA)."""
    folder = tmp_path_factory.mktemp("pki")
    ca, other_ca = _ca(folder, "ca"), _ca(folder, "other-ca")
    server = _signed(folder, "server", ca, "subjectAltName=DNS:localhost,IP:127.0.0.1\n"
                                           "extendedKeyUsage=serverAuth")
    client = _signed(folder, "client", ca, "extendedKeyUsage=clientAuth")
    other = _signed(folder, "other-client", other_ca, "extendedKeyUsage=clientAuth")
    return SimpleNamespace(ca=ca[0], server_cert=server[0], server_key=server[1], client_cert=client[0],
                           client_key=client[1], other_ca=other_ca[0], other_cert=other[0], other_key=other[1])


@pytest.fixture()
def mtls_server(model_dir, pki):
    """A real server on loopback that requires client certificates signed by pki.ca."""
    credentials = tls.server_credentials(pki.server_cert, pki.server_key, client_ca=pki.ca)
    server = Server(models=model_dir, bind="127.0.0.1:0", credentials=credentials).start()
    yield server
    server.stop()


def _predict(address, credentials, thesis_steps, model="tiny"):
    world, steps = thesis_steps
    with grpc.secure_channel(address, credentials) as channel:
        return pb_grpc.WarmStartStub(channel).Predict(wire.encode_step(0, model, *steps[0], world=world), timeout=10)


def _health(address, credentials):
    with grpc.secure_channel(address, credentials) as channel:
        return health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10).status


def test_a_client_with_a_certificate_of_the_servers_ca_is_served(mtls_server, pki, thesis_steps):
    good = tls.client_credentials(pki.ca, pki.client_cert, pki.client_key)
    reply = _predict(mtls_server.address, good, thesis_steps)
    assert reply.point_count == len(thesis_steps[1][0][1])
    world, steps = thesis_steps
    with WarmStartClient(mtls_server.address, world=world, credentials=good) as client:  # a step on a stream
        bodies, points = steps[1]
        assert client.step(wire.encode_step(1, "tiny", bodies, points), timeout=10).point_count == len(points)


def test_clients_without_a_certificate_of_its_ca_are_refused_and_the_server_stays_healthy(mtls_server, pki,
                                                                                          thesis_steps):
    refused = {grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.UNAUTHENTICATED}
    for credentials in (tls.client_credentials(ca=pki.ca),  # no client certificate
                        tls.client_credentials(pki.ca, pki.other_cert, pki.other_key)):  # the other CA's
        with pytest.raises(grpc.RpcError) as err:
            _predict(mtls_server.address, credentials, thesis_steps)
        assert err.value.code() in refused
    with grpc.insecure_channel(mtls_server.address) as channel:  # plaintext at a TLS port
        with pytest.raises(grpc.RpcError) as err:
            pb_grpc.WarmStartStub(channel).Predict(wire.encode_step(0, "bad", *thesis_steps[1][0],
                                                                    world=thesis_steps[0]), timeout=10)
        assert err.value.code() in refused
    # The stream client falls back on a refused step rather than raise anything else.
    with WarmStartClient(mtls_server.address, world=thesis_steps[0],
                         credentials=tls.client_credentials(ca=pki.ca)) as client:
        with pytest.raises(StepFailed) as failed:
            client.step(wire.encode_step(0, "tiny", *thesis_steps[1][0]), timeout=10)
        assert failed.value.code in refused
    good = tls.client_credentials(pki.ca, pki.client_cert, pki.client_key)
    assert _health(mtls_server.address, good) == health_pb2.HealthCheckResponse.SERVING
    assert _predict(mtls_server.address, good, thesis_steps).point_count == len(thesis_steps[1][0][1])


def test_health_dials_a_mutual_tls_server_with_the_three_flags(mtls_server, pki, capsys):
    flags = ["--tls-ca", str(pki.ca), "--tls-cert", str(pki.client_cert), "--tls-key", str(pki.client_key)]
    assert main(["health", "--server", mtls_server.address, *flags]) == 0
    assert capsys.readouterr().out.strip() == f"{mtls_server.address}: SERVING"
    assert main(["health", "--server", mtls_server.address, "--tls-ca", str(pki.ca)]) == 1  # no client certificate
    assert capsys.readouterr().err.strip().rsplit(": ", 1)[1] in ("UNAVAILABLE", "UNAUTHENTICATED")
    assert main(["health", "--server", mtls_server.address, "--tls-cert", str(pki.client_cert)]) == 2
    assert capsys.readouterr().err.strip() == ("deepcontact health: --tls-cert and --tls-key go together "
                                               "(a client certificate and its key)")


def test_bench_load_dials_a_mutual_tls_server(mtls_server, pki, tmp_path):
    flags = ["--tls-ca", str(pki.ca), "--tls-cert", str(pki.client_cert), "--tls-key", str(pki.client_key)]
    assert main(["bench", "load", "--server", mtls_server.address, "--model", "tiny", "--clients", "1",
                 "--duration", "1", "--processes", "1", "--out", str(tmp_path), *flags]) == 0
    (r,) = json.loads((tmp_path / "load.json").read_text())["results"]
    assert r["steps"] > 0 and r["errors"] == {} and r["wrong_order_or_step"] == 0


def test_bench_soak_runs_its_server_and_clients_over_mutual_tls(model_dir, pki, tmp_path):
    assert main(["bench", "soak", "--models", str(model_dir), "--model", "tiny", "--clients", "1",
                 "--processes", "1", "--duration", "1", "--sample-s", "0.2", "--warmup-s", "0.2",
                 "--rss-bound-mb", "500", "--out", str(tmp_path),
                 "--server-tls-cert", str(pki.server_cert), "--server-tls-key", str(pki.server_key),
                 "--server-tls-client-ca", str(pki.ca),
                 "--tls-ca", str(pki.ca), "--tls-cert", str(pki.client_cert), "--tls-key", str(pki.client_key)]) == 0
    steps = json.loads((tmp_path / "soak.json").read_text())["steps"]
    assert steps["answered"] > 0 and steps["errors"] == {} and steps["balanced"]
    assert '"mutual_tls": true' in (tmp_path / "server.log").read_text()


@pytest.mark.parametrize("extra, says", [
    ([], "--bind 0.0.0.0:0 is not a loopback address or a Unix socket: serve it with --tls-cert and --tls-key, "
         "or give --insecure"),
    (["--tls-client-ca", "ca.pem"], "--tls-client-ca needs --tls-cert and --tls-key"),
])
def test_serve_refuses_plaintext_beyond_loopback_and_a_client_ca_without_tls(model_dir, capsys, extra, says):
    assert main(["serve", "--models", str(model_dir), "--bind", "0.0.0.0:0", *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith("deepcontact serve: ") and says in err and err.count("\n") == 1


def test_serve_names_a_tls_file_it_cannot_use(model_dir, pki, capsys):
    assert main(["serve", "--models", str(model_dir), "--tls-cert", str(pki.server_cert),
                 "--tls-key", str(pki.client_key)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("deepcontact serve: --tls-cert ") and str(pki.client_key) in err
    assert main(["serve", "--models", str(model_dir), "--tls-cert", str(pki.server_cert),
                 "--tls-key", str(pki.server_key), "--tls-client-ca", "no-such-ca.pem"]) == 2
    assert "no-such-ca.pem: cannot read it" in capsys.readouterr().err


def _serve(model_dir, tmp_path, *extra):
    """`deepcontact serve --bind 0.0.0.0:0 EXTRA` as a process: (process, the loopback address of its port)."""
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, "-m", "commands", "serve", "--models", str(model_dir),
                             "--bind", "0.0.0.0:0", "--port-file", str(port_file), "--grace", "1", *extra],
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not port_file.exists():
        if proc.poll() is not None:
            pytest.fail(proc.stderr.read())
        assert time.monotonic() < deadline
        time.sleep(0.05)
    return proc, f"127.0.0.1:{port_file.read_text().strip()}"


def _stop(proc) -> list[dict]:
    """SIGTERM; the exit status must be 0. Its log lines."""
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)  # reading stderr meanwhile: a full pipe cannot hold it
    assert proc.returncode == 0
    return [json.loads(line) for line in err.splitlines() if line.startswith("{")]


def test_with_insecure_serve_serves_plaintext_beyond_loopback_and_warns(model_dir, tmp_path):
    proc, address = _serve(model_dir, tmp_path, "--insecure")
    try:
        with grpc.insecure_channel(address) as channel:
            status = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10).status
        assert status == health_pb2.HealthCheckResponse.SERVING
        log = _stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    warnings = [line for line in log if line["level"] == "WARNING"]
    assert len(warnings) == 1 and "plaintext on a non-loopback address" in warnings[0]["msg"]
    assert [line["msg"] for line in log].index(warnings[0]["msg"]) < [line["msg"] for line in log].index("serving")


def test_serve_with_mutual_tls_beyond_loopback_answers_health_with_the_three_flags(model_dir, pki, tmp_path,
                                                                                   capsys):
    proc, address = _serve(model_dir, tmp_path, "--tls-cert", str(pki.server_cert), "--tls-key",
                           str(pki.server_key), "--tls-client-ca", str(pki.ca))
    try:
        flags = ["--tls-ca", str(pki.ca), "--tls-cert", str(pki.client_cert), "--tls-key", str(pki.client_key)]
        assert main(["health", "--server", address, *flags]) == 0
        assert capsys.readouterr().out.strip() == f"{address}: SERVING"
        other = ["--tls-ca", str(pki.ca), "--tls-cert", str(pki.other_cert), "--tls-key", str(pki.other_key)]
        assert main(["health", "--server", address, *other]) == 1
        log = _stop(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not [line for line in log if line["level"] == "WARNING"]
    (serving,) = [line for line in log if line["msg"] == "serving"]
    assert serving["tls"] is True and serving["mutual_tls"] is True


def test_client_credentials_say_what_is_wrong_in_one_line(pki, tmp_path):
    assert tls.client_credentials() is None
    assert tls.credentials_from_args(SimpleNamespace(tls_ca=None, tls_cert=None, tls_key=None)) is None
    assert isinstance(tls.client_credentials(ca=pki.ca), grpc.ChannelCredentials)
    with pytest.raises(ValueError, match="--tls-cert and --tls-key go together"):
        tls.client_credentials(pki.ca, cert=pki.client_cert)
    with pytest.raises(ValueError, match="--tls-cert and --tls-key go together"):
        tls.client_credentials(pki.ca, key=pki.client_key)
    missing = tmp_path / "missing.pem"
    with pytest.raises(ValueError, match=f"--tls-ca {missing}: cannot read it"):
        tls.client_credentials(ca=missing)
    not_pem = tmp_path / "not.pem"
    not_pem.write_text("hello")
    with pytest.raises(ValueError, match=f"--tls-cert {not_pem}: not a PEM file"):
        tls.client_credentials(cert=not_pem, key=pki.client_key)
    with pytest.raises(ValueError, match="not a certificate and its own unencrypted key"):
        tls.client_credentials(cert=pki.client_cert, key=pki.other_key)


@pytest.mark.parametrize("bind, local", [
    ("127.0.0.1:50051", True), ("127.8.9.10:0", True), ("localhost:50051", True), ("[::1]:50051", True),
    ("unix:/tmp/warmstart.sock", True), ("unix-abstract:warmstart", True),
    ("0.0.0.0:50051", False), ("[::]:50051", False), (":50051", False), ("10.1.2.3:50051", False),
    ("example.com:50051", False), ("192.168.0.1:0", False),
])
def test_is_local_bind(bind, local):
    assert tls.is_local_bind(bind) is local


def test_simulate_and_bench_iterations_dial_a_mutual_tls_server(mtls_server, pki, tmp_path):
    flags = ["--tls-ca", str(pki.ca), "--tls-cert", str(pki.client_cert), "--tls-key", str(pki.client_key)]
    out = tmp_path / "r.json"
    assert main(["simulate", "--seed", "901", "--steps", "30", "--warm-start", "server:tiny", "--server",
                 mtls_server.address, "--deadline-ms", "1000", "--no-guard", "--out", str(out), "--quiet", *flags]) == 0
    assert json.loads(out.read_text())["summary"]["fallback_steps"] == 0
    assert main(["bench", "iterations", "--seeds", "901", "--steps", "30", "--warm-starts", "builtin,server:tiny",
                 "--server", mtls_server.address, "--deadline-ms", "1000", "--out", str(tmp_path / "it"), "--quiet",
                 *flags]) == 0
    summary = json.loads((tmp_path / "it" / "summary.json").read_text())
    assert summary["warm_starts"]["server:tiny"]["fallback_steps"] == 0


def test_a_session_dials_a_mutual_tls_server_and_is_refused_without_a_certificate(mtls_server, pki):
    from simclient import WarmStartSession
    from simclient.scene import SceneSpec, build_world

    world = build_world(SceneSpec.thesis(), 901).world
    with WarmStartSession(world, mtls_server.address, model="tiny", deadline_ms=1000, guard=False,
                          tls_ca=pki.ca, tls_cert=pki.client_cert, tls_key=pki.client_key) as session:
        for _ in range(30):
            session.step(0.01, 1000, 1000)
        assert session.summary()["fallback_steps"] == 0
    with pytest.raises(ConnectionError):  # the handshake fails: no server that answers
        WarmStartSession(world, mtls_server.address, model="tiny", tls_ca=pki.ca, connect_timeout=1.0)
