"""`deepcontact simulate` against a real server process on loopback."""

from __future__ import annotations

import dataclasses
import json
import threading
import time

import pytest

from commands import main
from server.process import ServerProcess
from simclient.client import WarmStartClient
from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
from simclient.warmstarts import make_provider
from tests.server.conftest import write_conv_model

SUMMARY_KEYS = {"steps", "steps_with_contacts", "mean_velocity_iterations", "median_velocity_iterations",
                "p90_velocity_iterations", "mse_normal", "mse_tangent", "p50_latency_ms", "p99_latency_ms",
                "fallback_steps"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    folder = tmp_path_factory.mktemp("models")
    write_conv_model(folder, "tiny")
    with ServerProcess(folder) as srv:
        yield srv


def test_results_file_has_per_step_arrays_and_the_summary(server, tmp_path):
    out = tmp_path / "r.json"
    assert main(["simulate", "--seed", "901", "--steps", "40", "--warm-start", "server:tiny",
                 "--server", server.address, "--deadline-ms", "1000", "--out", str(out), "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert SUMMARY_KEYS <= set(result["summary"])
    per_step = result["per_step"]
    assert len(per_step["velocity_iterations"]) == 40
    for key in ("contact_points", "position_iterations", "residual_trace", "mse_normal", "mse_tangent",
                "latency_ms", "server_us", "solve_ms", "fallback", "client_us"):
        assert len(per_step[key]) == 40
    assert result["summary"]["fallback_steps"] == 0
    assert all(len(t) == n for t, n in zip(per_step["residual_trace"], per_step["velocity_iterations"]))


def test_server_zero_equals_none_exactly(server):
    spec = dataclasses.replace(SceneSpec.thesis(), steps=60)
    local = run_simulation(spec, 902, make_provider("none"))
    with WarmStartClient(server.address) as client:
        remote = run_simulation(spec, 902, make_provider("server:zero"), client=client, deadline_ms=1000)
    assert remote["per_step"]["velocity_iterations"] == local["per_step"]["velocity_iterations"]


def test_a_server_killed_mid_run_costs_fallbacks_not_the_run(tmp_path):
    folder = tmp_path / "models"
    folder.mkdir()
    write_conv_model(folder, "tiny")
    srv = ServerProcess(folder).start()
    spec = dataclasses.replace(SceneSpec.thesis(), steps=150)
    steps_seen = []

    def kill_later():
        while len(steps_seen) < 40:
            time.sleep(0.005)
        srv.kill()  # SIGKILL, as a crash

    killer = threading.Thread(target=kill_later)
    killer.start()
    with WarmStartClient(srv.address, backoff_s=(0.01, 0.05)) as client:
        result = run_simulation(spec, 903, make_provider("server:tiny"), client=client, deadline_ms=1000,
                                progress=steps_seen.append)
    killer.join()
    summary = result["summary"]
    assert summary["steps"] == 150
    assert 0 < summary["fallback_steps"] <= 150 - 40
    assert not any(result["per_step"]["fallback"][:30])


def test_bad_invocations_fail_before_simulating(server, tmp_path, capsys):
    out = str(tmp_path / "x.json")
    assert main(["simulate", "--seed", "1", "--warm-start", "server:tiny", "--out", out]) == 2
    assert "--server" in capsys.readouterr().err
    assert main(["simulate", "--seed", "1", "--warm-start", "server:nope", "--server", server.address,
                 "--out", out]) == 2
    assert "no model 'nope'" in capsys.readouterr().err
    assert main(["simulate", "--seed", "1", "--warm-start", "server:tiny", "--server", "127.0.0.1:9",
                 "--connect-timeout", "0.5", "--out", out]) == 2
    assert "--allow-fallback" in capsys.readouterr().err
    assert main(["simulate", "--seed", "1", "--warm-start", "server:tiny", "--server", "127.0.0.1:9",
                 "--connect-timeout", "0.5", "--allow-fallback", "--steps", "10", "--no-guard", "--out", out,
                 "--quiet"]) == 0
    assert json.loads((tmp_path / "x.json").read_text())["summary"]["fallback_steps"] > 0
    assert main(["simulate", "--seed", "1", "--warm-start", "builtin", "--out", "/proc/none/x.json"]) == 2


def test_a_world_the_server_refuses_ends_the_run_with_its_reason(tmp_path, capsys):
    # A model that cannot serve this world (here a box past the server's grid bound; a fixed-grid
    # model and a box of another size are refused the same way) is an error, not a run of
    # fallbacks written down as the model's.
    folder = tmp_path / "models"
    folder.mkdir()
    write_conv_model(folder, "tiny")
    out = tmp_path / "x.json"
    with ServerProcess(folder, "--max-grid-nodes", str(61 * 61)) as srv:  # the thesis box and no more
        # A long deadline: on a busy host a step can miss the default 10 ms, which is not what this tests.
        args = ["simulate", "--seed", "901", "--steps", "10", "--warm-start", "server:tiny", "--server", srv.address,
                "--deadline-ms", "1000", "--out", str(out), "--quiet"]
        assert main(args + ["--box-size", "16", "16"]) == 2
        err = capsys.readouterr().err
        assert "refuses server:tiny for this world" in err and "65x65" in err
        assert not out.exists()
        assert main(args) == 0  # the thesis box is served
    assert json.loads(out.read_text())["summary"]["fallback_steps"] == 0


def test_declaring_a_world_says_refused_and_a_silent_server_is_no_refusal(server):
    from simclient import worlds
    from simclient.client import Refused
    from simclient.simulate import declare_world

    spec = SceneSpec.thesis()
    with WarmStartClient(server.address) as client:
        with pytest.raises(Refused, match="NOT_FOUND"):
            declare_world(client, worlds.world_message(spec, worlds.build(spec, 901)), ["nope"])
    with WarmStartClient("127.0.0.1:9") as client:  # nothing listens: no answer, so no refusal either
        assert client.declare("tiny", timeout=0.2) is False


def test_the_simulation_sends_each_points_friction_so_the_shipped_face_route_is_served(tmp_path):
    # models/face solves each step on its classifier's labels on the server, which needs each
    # point's friction (StepRequest.point_friction); a request without it is refused, so a step
    # served without a fallback is one whose request carried it.
    import shutil
    from pathlib import Path

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    target = json.loads((shipped / "face.json").read_text())["alias_of"]
    for name in ("face.json", f"{target}.json", f"{target}.onnx"):
        shutil.copy(shipped / name, tmp_path)
    spec = dataclasses.replace(SceneSpec.thesis(), steps=40)
    with ServerProcess(tmp_path) as srv, WarmStartClient(srv.address) as client:
        served = run_simulation(spec, 901, make_provider("server:face"), client=client, deadline_ms=5000)
    assert served["summary"]["fallback_steps"] == 0 and served["summary"]["steps_with_contacts"] > 0
