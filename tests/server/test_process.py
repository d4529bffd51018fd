"""server.process.ServerProcess: `deepcontact serve` as a child process, for commands and tests."""

from __future__ import annotations

import os
from pathlib import Path

from server.process import ServerProcess
from simclient.client import WarmStartClient


def test_a_local_socket_server_is_dialled_at_a_unix_address_that_goes_with_it(model_dir):
    server = ServerProcess(model_dir, local_socket=True).start()
    socket = Path(server.address.removeprefix("unix:"))
    try:
        assert server.address.startswith("unix:") and socket.is_socket()
        with WarmStartClient(server.address) as client:
            assert "tiny" in [m.name for m in client.list_models()]
    finally:
        server.stop()
    assert not socket.exists()  # its folder is removed with the server


def test_by_default_the_server_listens_on_a_free_loopback_port(model_dir):
    with ServerProcess(model_dir) as server:
        assert server.address == f"127.0.0.1:{server.port}" and server.port > 0


def test_a_server_given_cores_runs_every_thread_on_them(model_dir):
    last = max(os.sched_getaffinity(0))
    with ServerProcess(model_dir, cpus={last}) as server:
        threads = Path(f"/proc/{server.proc.pid}/task").iterdir()
        assert all(os.sched_getaffinity(int(t.name)) == {last} for t in threads)
        with WarmStartClient(server.address) as client:
            assert "tiny" in [m.name for m in client.list_models()]
