"""server.process.ServerProcess: `deepcontact serve` as a child process, for commands and tests."""

from __future__ import annotations

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
