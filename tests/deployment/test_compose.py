"""docker-compose.yml: every service runs a real `deepcontact` subcommand with valid flags.

No Docker engine runs here; the file is parsed and each command is checked
against the real argument parser, the way the container's entrypoint would run it.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from deepcontact.cli import build_parser

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def test_compose_has_the_three_services():
    assert set(COMPOSE["services"]) == {"server", "simclient", "loadtest"}


@pytest.mark.parametrize("service", ["server", "simclient", "loadtest"])
def test_each_command_parses_as_a_deepcontact_subcommand(service):
    argv = COMPOSE["services"][service]["command"]
    args = build_parser().parse_args(argv)  # argparse exits on unknown commands or flags
    assert args._module


def test_the_healthcheck_is_deepcontact_health():
    test = COMPOSE["services"]["server"]["healthcheck"]["test"]
    assert test[:2] == ["CMD", "deepcontact"]
    build_parser().parse_args(test[2:])


def test_clients_reach_the_server_through_dns_round_robin():
    for service in ("simclient", "loadtest"):
        command = COMPOSE["services"][service]["command"]
        assert command[command.index("--server") + 1] == "dns:///server:50051"


def test_the_dockerfile_sets_up_with_the_makefile():
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert "make setup" in dockerfile and 'ENTRYPOINT ["deepcontact"]' in dockerfile
