"""Scenes: the thesis world, the family flags, determinism, bad parameters."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import pytest

from simclient.scene import (SceneSpec, add_scene_arguments, body_friction, build_world, settled_world, spec_from_args,
                             spec_from_dict, spec_to_dict)


def parse(*argv: str) -> SceneSpec:
    parser = argparse.ArgumentParser()
    add_scene_arguments(parser)
    return spec_from_args(parser.parse_args(list(argv)))


def test_thesis_world_matches_section_8_1():
    spec = SceneSpec.thesis()
    engine = build_world(spec, seed=1)
    bodies = engine.bodies()
    assert len(bodies) == 101  # the static box, then 100 circles
    assert bodies["type"][0] == 0 and (bodies["type"][1:] == 2).all()
    np.testing.assert_allclose(bodies["radius"][1:], 0.5)
    np.testing.assert_allclose(bodies["mass"][1:], np.pi * 0.25, rtol=1e-6)  # density 1
    assert engine.world.gravity == (0, -9.8)
    assert not engine.world.GetAllowSleeping() and not engine.world.continuousPhysics
    assert (spec.steps, spec.solver.dt, spec.solver.velocity_iterations, spec.solver.velocity_threshold) == (
        250, 0.01, 1000, 1e-4)
    # Placed inside the box, without overlap.
    p = bodies["position"][1:]
    assert (p > 0.5).all() and (p < 14.5).all()
    d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(100) * 10
    assert d.min() >= 1.0


def test_no_body_ever_sleeps_so_every_contact_point_is_solved():
    engine = build_world(SceneSpec.thesis(), 905)
    for _ in range(220):
        engine.collide()
        stats = engine.solve()
        points = engine.contacts()
        assert stats.contact_points == len(points)
        assert np.isfinite(points["impulse"]).all()
    assert all(b.awake for b in engine.world.bodies[1:])


def test_same_seed_same_world_bit_for_bit():
    a, b = build_world(SceneSpec.thesis(), 7), build_world(SceneSpec.thesis(), 7)
    for _ in range(50):
        a.step()
        b.step()
    assert a.bodies().tobytes() == b.bodies().tobytes()
    assert build_world(SceneSpec.thesis(), 8).bodies().tobytes() != build_world(SceneSpec.thesis(), 7).bodies().tobytes()


def test_family_flags_override_the_thesis_values():
    spec = parse("--bodies", "40", "--box-size", "20", "10", "--radius", "0.3", "0.6",
                 "--polygons", "0.5", "--friction", "0.2", "0.8", "--steps", "30")
    assert (spec.bodies, spec.box_size, spec.radius, spec.polygons, spec.friction, spec.steps) == (
        40, (20.0, 10.0), (0.3, 0.6), 0.5, (0.2, 0.8), 30)
    bodies = build_world(spec, 3).bodies()[1:]
    assert set(bodies["shape"]) == {0, 2}  # circles and boxes
    assert parse() == SceneSpec.thesis()


def test_each_bodys_friction_follows_from_the_scene_and_seed_without_a_world():
    # What recorded data, which carries no friction, is read with (training.grids.iter_steps).
    spec = parse("--radius", "0.3", "0.55", "--friction", "0.2", "0.8")
    for seed in (3, 4):
        np.testing.assert_array_equal(body_friction(spec, seed), build_world(spec, seed).body_friction())
    assert set(body_friction(SceneSpec.thesis(), 3).tolist()) == {0.5}


def test_spec_round_trips_through_json_dict():
    spec = parse("--bodies", "10", "--radius", "0.2", "0.4")
    assert spec_from_dict(spec_to_dict(spec)) == spec


@pytest.mark.parametrize("argv, message", [
    (("--bodies", "1000"), "no room"),
    (("--radius", "-1", "0.5"), "radius"),
    (("--box-size", "0.5", "0.5"), "do not fit"),
    (("--polygons", "1.5"), "polygons"),
    (("--friction", "0.5", "0.1"), "friction"),
    (("--steps", "0"), "steps"),
    (("--tolerance", "0"), "--tolerance"),
    (("--max-iterations", "0"), "--max-iterations"),
])
def test_impossible_scenes_fail_before_any_work(argv, message):
    with pytest.raises(ValueError, match=message):
        parse(*argv)


def test_thesis_placement_is_unchanged_bit_for_bit():
    # Digests of the initial bodies as placed since round 1: dense-world
    # spawning must not move a single thesis body.
    import hashlib

    for seed, digest in ((1, "e9a156f838d8ef6c"), (901, "3f2e3498178759ae")):
        assert hashlib.sha256(build_world(SceneSpec.thesis(), seed).bodies().tobytes()).hexdigest()[:16] == digest


def test_a_dense_world_is_spawned_above_the_box_and_falls_into_it():
    spec = parse("--radius", "0.5", "0.7", "--steps", "300")  # 68 % of the box at the largest radius
    assert spec.spawn_height > spec.box_size[1]
    np.testing.assert_allclose(spec.walls()[1:, 3], spec.spawn_height)  # the side walls form a chute
    engine = build_world(spec, 3)
    start = engine.bodies()["position"][1:]
    assert (start[:, 1] > spec.box_size[1]).any()  # some bodies start above the box
    for _ in range(spec.steps):
        engine.step()
    end = engine.bodies()["position"][1:]
    assert (end[:, 1] < spec.box_size[1]).all() and (end[:, 0] > 0).all() and (end[:, 0] < spec.box_size[0]).all()


def test_a_world_that_cannot_fit_in_its_box_is_refused_with_the_reason():
    with pytest.raises(ValueError, match=r"cover 101% of it, and a pile of discs covers at most about 80%"):
        parse("--bodies", "200", "--radius", "0.6", "0.6")


def test_unknown_scene_is_refused_by_the_parser():
    with pytest.raises(SystemExit):
        parse("--scene", "moon")


def test_solver_settings_travel_with_the_spec():
    spec = dataclasses.replace(SceneSpec.thesis(), solver=dataclasses.replace(SceneSpec.thesis().solver, dt=0.02))
    assert build_world(spec, 1).config.dt == 0.02


def test_the_solver_flags_set_the_stopping_rule_and_the_cap():
    spec = parse("--tolerance", "1e-3", "--max-iterations", "50")
    assert (spec.solver.velocity_threshold, spec.solver.velocity_iterations) == (1e-3, 50)
    assert spec_from_dict(spec_to_dict(spec)) == spec
    loose, tight = (settled_world(dataclasses.replace(spec, steps=1), 901, 150),
                    settled_world(SceneSpec.thesis(), 901, 150))
    loose_step, tight_step = loose.step(), tight.step()
    assert tight_step.velocity_iterations > loose_step.velocity_iterations  # a looser rule stops sooner
    assert loose_step.velocity_iterations <= 50
