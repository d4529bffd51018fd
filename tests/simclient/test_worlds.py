"""Users' worlds on the command line: --world PATH.py:FUNCTION (or MODULE:FUNCTION)."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

import Box2D
from deepcontact import wire
from commands import main
from simclient import worlds
from simclient.engine import SolverConfig

WORLD = textwrap.dedent("""
    import Box2D

    def build(seed):
        world = Box2D.b2World(gravity=(0, -9.8))
        world.CreateStaticBody().CreateEdgeFixture(vertices=[(-5, 0), (5, 0)])
        for i in range(6):
            world.CreateDynamicBody(position=(0.01 * (seed % 7), 0.5 + 1.01 * i)).CreatePolygonFixture(
                box=(0.5, 0.5), density=1.0, friction=0.6)
        return world

    def broken(seed):
        raise RuntimeError("no world today")

    def nothing(seed):
        return 42
    """)


@pytest.fixture()
def world_file(tmp_path):
    path = tmp_path / "my_world.py"
    path.write_text(WORLD)
    return path


@pytest.mark.parametrize("source, says", [
    ("{folder}/nope.py:build", "there is no file"),
    ("{file}:absent", "has no function 'absent'"),
    ("{file}", "takes PATH.py:FUNCTION or MODULE:FUNCTION"),
    ("no_such_module_here:build", "cannot import module no_such_module_here"),
    ("{file}:broken", "broken(901) raised RuntimeError: no world today"),
    ("{file}:nothing", "returned int, not a Box2D.b2World"),
])
def test_a_world_that_cannot_be_built_is_one_line_and_nothing_is_written(world_file, tmp_path, capsys, source,
                                                                        says):
    source = source.format(folder=tmp_path, file=world_file)
    out = tmp_path / "out"
    assert main(["simulate", "--world", source, "--seed", "901", "--warm-start", "builtin",
                 "--out", str(out / "r.json"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1
    assert main(["bench", "iterations", "--world", source, "--seeds", "901", "--warm-starts", "builtin",
                 "--out", str(out), "--quiet"]) == 2
    assert says in capsys.readouterr().err
    assert not out.exists()


def test_scene_flags_do_not_mix_with_a_world(world_file, tmp_path, capsys):
    assert main(["simulate", "--world", f"{world_file}:build", "--bodies", "30", "--seed", "901",
                 "--warm-start", "builtin", "--out", str(tmp_path / "r.json")]) == 2
    assert "--bodies describes the project's scenes" in capsys.readouterr().err


def test_simulate_and_bench_iterations_run_a_users_world(world_file, tmp_path):
    out = tmp_path / "r.json"
    assert main(["simulate", "--world", f"{world_file}:build", "--seed", "901", "--steps", "60", "--dt", "0.005",
                 "--warm-start", "builtin", "--out", str(out), "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert result["scene"]["kind"] == "world" and result["scene"]["solver"]["dt"] == 0.005
    assert result["summary"]["steps"] == 60 and result["summary"]["steps_with_contacts"] > 0
    bench = tmp_path / "bench"
    assert main(["bench", "iterations", "--world", f"{world_file}:build", "--seeds", "901-902", "--steps", "40",
                 "--warm-starts", "none,builtin", "--tolerance", "1e-3", "--out", str(bench), "--quiet"]) == 0
    summary = json.loads((bench / "summary.json").read_text())
    assert summary["scene"] == f"{world_file}:build" and summary["scene_spec"]["solver"]["velocity_threshold"] == 1e-3
    assert set(summary["ratios_to_builtin"]) == {"none", "builtin"}
    assert (bench / "fig21_convergence.png").exists() and (bench / "results.md").exists()


def test_a_module_and_function_name_a_world_too():
    spec = worlds.WorldSpec("tests.simclient.test_session:everything_world", steps=5)
    engine = worlds.build(spec, 3)
    assert engine.world.jointCount == 4 and engine.config == spec.solver
    assert worlds.spec_from_dict(json.loads(json.dumps(worlds.spec_to_dict(spec)))) == spec


def test_a_world_is_described_by_its_fixtures_box_and_its_static_edges():
    world = Box2D.b2World(gravity=(0.0, -3.0))
    ground = world.CreateStaticBody(position=(1.0, 0.0))
    ground.CreateEdgeFixture(vertices=[(-5.0, 0.0), (5.0, 0.0)])
    ground.CreateChainFixture(vertices_chain=[(5.0, 0.0), (7.0, 1.0), (9.0, 1.0)])
    ground.CreatePolygonFixture(box=(0.5, 0.5, (0.0, 3.0), 0.0))
    world.CreateDynamicBody(position=(0.0, 8.0)).CreateCircleFixture(radius=0.5)
    message = worlds.describe(world, 0.02)
    lower, upper, edges = wire.decode_world(message)
    assert lower[0] < -4.0 and lower[1] < 0.0 and upper[0] > 10.0 and upper[1] > 8.5
    assert len(edges) == 1 + 2 + 4  # the edge, the chain's two segments, the box's four sides
    np.testing.assert_allclose(edges[0], [-4.0, 0.0, 6.0, 0.0])  # in world coordinates: the body sits at x = 1
    physics = wire.decode_physics(message)
    assert physics.dt == pytest.approx(0.02) and physics.gravity == pytest.approx((0.0, -3.0))
    assert wire.decode_tolerance(message) == 0.0  # a stopping rule not said: none declared


def test_a_stream_declares_its_solvers_stopping_rule():
    """The World a simulation declares says where its solver stops (solver_tolerance, N s), a
    project scene's and a user's world's alike; a solver run to its cap declares none (0)."""
    import dataclasses

    from simclient.scene import SceneSpec

    thesis = SceneSpec.thesis()
    declared = worlds.world_message(thesis, worlds.build(thesis, 901))
    assert wire.decode_tolerance(declared) == pytest.approx(1e-4)
    spec = dataclasses.replace(worlds.WorldSpec("examples/stack.py:build", steps=5),
                               solver=SolverConfig(velocity_threshold=2e-3))
    assert wire.decode_tolerance(worlds.world_message(spec, worlds.build(spec, 901))) == pytest.approx(2e-3)
    capped = dataclasses.replace(spec, solver=SolverConfig(velocity_threshold=-1.0))
    assert wire.decode_tolerance(worlds.world_message(capped, worlds.build(capped, 901))) == 0.0
    declared.solver_tolerance = float("nan")
    with pytest.raises(wire.WireError, match="solver_tolerance"):
        wire.decode_tolerance(declared)
    declared.solver_tolerance = -1e-4
    with pytest.raises(wire.WireError, match="solver_tolerance"):
        wire.decode_tolerance(declared)
