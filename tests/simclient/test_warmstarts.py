"""Local warm-start providers and their registry (simclient.warmstarts) on the real engine."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
from simclient.warmstarts import Extrapolate, make_provider

SHORT = dataclasses.replace(SceneSpec.thesis(), steps=120)


def mean_iterations(name, spec=SHORT):
    return run_simulation(spec, 901, make_provider(name))["summary"]["mean_velocity_iterations"]


def test_the_thesis_ordering_of_simple_warm_starts():
    # Builtin pulls ahead of none once the pile has formed: whole thesis runs for those two.
    its = {name: mean_iterations(name, SceneSpec.thesis()) for name in ("none", "builtin")}
    its.update({name: mean_iterations(name) for name in ("copy", "copy2")})
    assert its["copy"] <= 2.0  # the oracle: about one sweep
    assert its["copy"] < its["copy2"] < its["builtin"] < its["none"]


def test_extrapolate_uses_the_last_two_impulses_of_persisting_points():
    ex = Extrapolate()
    keys = np.array([5, 7, 9], np.uint64)
    before = np.zeros(3, dtype=[("key", "<u8"), ("builtin", "<f4", (2,))])
    before["key"], before["builtin"] = keys, [[1.0, 0.1], [0.0, 0.0], [2.0, -0.2]]  # J(t-2); key 7 new then
    ex.observe(before)
    now = np.zeros(4, dtype=[("key", "<u8"), ("builtin", "<f4", (2,))])
    now["key"] = [5, 7, 9, 11]
    now["builtin"] = [[1.5, 0.1], [0.5, 0.0], [1.0, -0.1], [0.0, 0.0]]  # J(t-1)
    normal, tangent = ex.warm_start(None, None, now, 0)
    np.testing.assert_allclose(normal, [2.0, 0.5, 0.0, 0.0])  # 2*J(t-1) - J(t-2) where both exist
    np.testing.assert_allclose(tangent, [0.1, 0.0, 0.0, 0.0], atol=1e-7)


def test_unknown_warm_starts_are_refused():
    with pytest.raises(ValueError, match="unknown warm start"):
        make_provider("magic")
    with pytest.raises(ValueError, match="model name"):
        make_provider("server:")
    assert make_provider("server:default").models == ("default",)


def test_a_registered_name_or_prefix_makes_its_provider_and_says_so_in_the_help():
    from simclient import warmstarts
    from simclient.provider import Composite

    made = []
    warmstarts.register_name("test-zero", lambda: made.append("name") or warmstarts.NoWarmStart(), "zeros, for a test")
    warmstarts.register_prefix("test-over:", lambda name: made.append(name) or Composite(
        [make_provider(n) for n in name.partition(":")[2].split("+")]), "a composite, for a test",
        usage="test-over:W1+W2", composite=True)
    try:
        assert make_provider("test-zero").name == "none" and made == ["name"]
        over = make_provider("test-over:copy+server:a")
        assert over.picks and over.uses_server and over.models == ("a",) and made[-1] == "test-over:copy+server:a"
        assert over.labels == ["builtin", "copy", "server:a"]
        assert warmstarts.composite_parts("test-over:copy+server:a") == ("test-over", ["copy", "server:a"])
        assert warmstarts.composite_parts("server:a") is None and warmstarts.composite_parts("copy") is None
        assert "test-zero" in warmstarts.usage() and "test-over:W1+W2" in warmstarts.usage()
        assert __name__ in warmstarts.extensions() and "simclient.warmstarts" not in warmstarts.extensions()
    finally:
        for key in (("name", "test-zero"), ("prefix", "test-over:")):
            warmstarts._ORDER.pop(key)
        warmstarts._NAMES.pop("test-zero")
        warmstarts._PREFIXES.pop("test-over:")
    with pytest.raises(ValueError, match="unknown warm start"):
        make_provider("test-zero")


def test_the_product_alone_knows_its_own_warm_starts_and_not_the_labs():
    # A fresh interpreter: in this one another test may have imported lab.
    code = ("import sys; from simclient import warmstarts; print(warmstarts.usage()); "
            "print(warmstarts.extensions()); print('lab' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    assert out == ["none, builtin, copy, copy2, copy0, extrapolate, server:NAME", "()", "False"]


def test_the_oracle_start_keeps_box2ds_own_where_no_awake_island_solves():
    # A box asleep on the ground beside a disc that rolls on, never sleeping: the step's oracle
    # solves the disc's island alone, and the box's points keep Box2D's start, finite.
    import Box2D

    from simclient.engine import Engine
    from simclient.warmstarts import Copy

    world = Box2D.b2World(gravity=(0, -9.8))
    world.CreateStaticBody(shapes=Box2D.b2EdgeShape(vertices=[(-100, 0), (100, 0)]))
    box = world.CreateDynamicBody(position=(0, 0.5))
    box.CreatePolygonFixture(box=(0.5, 0.5), density=1.0, friction=0.5)
    disc = world.CreateDynamicBody(position=(5, 0.5), linearVelocity=(2, 0), angularVelocity=-4)
    disc.CreateCircleFixture(radius=0.5, density=1.0, friction=0.5)
    engine, copy = Engine(world), Copy("copy", None)
    for step in range(120):
        engine.collide()
        points = engine.contacts()
        normal, tangent = copy.warm_start(engine, engine.bodies(), points, step)
        engine.set_warm_start(normal, tangent)
        engine.solve()
    assert not box.awake and disc.awake
    on_box = (points["body_a"] == 1) | (points["body_b"] == 1)
    assert on_box.any() and (~on_box).any()
    assert np.isfinite(normal).all() and np.isfinite(tangent).all()
    np.testing.assert_array_equal(normal[on_box], points["builtin"][on_box, 0])
