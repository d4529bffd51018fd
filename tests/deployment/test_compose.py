"""docker-compose.yml: every service runs a real `deepcontact` subcommand with valid flags.

No Docker engine runs here; the file is parsed and each command is checked
against the real argument parser, the way the container's entrypoint would run it.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from commands import build_parser

ROOT = Path(__file__).resolve().parents[2]
COMPOSE = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
DEEPCONTACT = ["server", "simclient", "loadtest", "sweep"]  # the image's entrypoint, deepcontact
RAY = ["ray-head", "ray-worker"]  # entrypoint ray
SCALE = ["ray-head", "ray-worker", "sweep"]  # --profile scale, with the server replicas


def test_compose_has_the_services():
    assert set(COMPOSE["services"]) == {*DEEPCONTACT, *RAY}


@pytest.mark.parametrize("service", DEEPCONTACT)
def test_each_command_parses_as_a_deepcontact_subcommand(service):
    argv = COMPOSE["services"][service]["command"]
    args = build_parser().parse_args(argv)  # argparse exits on unknown commands or flags
    assert args._module


def test_the_healthcheck_is_deepcontact_health():
    test = COMPOSE["services"]["server"]["healthcheck"]["test"]
    assert test[:2] == ["CMD", "deepcontact"]
    build_parser().parse_args(test[2:])


def test_clients_reach_the_server_through_dns_round_robin():
    for service in ("simclient", "loadtest", "sweep"):
        command = COMPOSE["services"][service]["command"]
        assert command[command.index("--server") + 1] == "dns:///server:50051"


def test_the_dockerfile_builds_a_server_and_a_client_each_with_only_what_it_uses():
    dockerfile = (ROOT / "Dockerfile").read_text()
    stages = {stage: base for base, stage in re.findall(r"^FROM (\S+) AS (\S+)$", dockerfile, re.M)}
    assert stages == {"build": "${PYTHON_IMAGE}", "runtime": "${RUNTIME_IMAGE}", "server": "runtime",
                      "client": "runtime", "cluster": "runtime"}
    server = dockerfile.split("FROM runtime AS server")[1].split("FROM ")[0]
    client = dockerfile.split("FROM runtime AS client")[1]
    assert "build-essential" not in server + client and "box2d" not in server  # no compilers; no engine to serve
    assert "[train]" not in server + client and "tensorflow" not in (server + client).lower()
    assert "/tmp/wheels/box2d/" in client and 'ENTRYPOINT ["deepcontact"]' in server + client
    targets = {"server": "server", "simclient": "client", "loadtest": "client", "ray-head": "cluster",
               "ray-worker": "cluster", "sweep": "cluster"}
    for service, target in targets.items():
        assert COMPOSE["services"][service]["build"]["target"] == target


def ray_start(service: str) -> dict:
    """The service's `ray start` options, parsed by Ray's own command line."""
    from ray.scripts.scripts import start

    spec = COMPOSE["services"][service]
    assert spec["entrypoint"] == ["ray"] and spec["command"][0] == "start"
    return start.make_context("start", list(spec["command"][1:])).params  # click fails on unknown options


def test_the_scale_profile_runs_ray_without_dashboard_or_usage_stats():
    head, worker = ray_start("ray-head"), ray_start("ray-worker")
    assert head["head"] and head["block"] and head["num_cpus"] == 0  # the head only coordinates
    assert head["include_dashboard"] is False and head["disable_usage_stats"] and worker["disable_usage_stats"]
    assert worker["address"] == f"ray-head:{head['port']}" and worker["num_cpus"] == 1  # one simulation per worker
    for service in SCALE:
        spec = COMPOSE["services"][service]
        assert spec["profiles"] == ["scale"]
        assert spec["environment"]["RAY_AUTH_MODE"] == "token" and "RAY_AUTH_TOKEN" in spec["environment"]


def test_the_sweep_drives_ray_through_ray_client_and_waits_for_its_parts():
    head = ray_start("ray-head")
    sweep = COMPOSE["services"]["sweep"]
    args = build_parser().parse_args(sweep["command"])
    assert args.ray == f"ray://ray-head:{head['ray_client_server_port']}"
    assert set(sweep["depends_on"]) == {"server", "ray-head", "ray-worker"}
