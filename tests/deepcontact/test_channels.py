"""Channels (deepcontact.channels): plain definitions read from a step's records."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.channels import (CHANNELS, NEEDS, SOURCES, Step, channel_values, mirror_signs, needs,
                                  particle_positions)
from deepcontact.kinematics import Physics
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from tests.conftest import reflected


def two_bodies_on_the_floor():
    """The static box (row 0) and two discs of 1 kg at rest, one contact each with the floor."""
    bodies = np.zeros(3, BODY_DTYPE)
    bodies["type"] = [0, 2, 2]
    bodies["position"] = [[0, 0], [1, 0.5], [3, 0.5]]
    bodies["mass"] = [0, 1.0, 1.0]
    bodies["inertia"] = [0, 0.125, 0.125]
    bodies["velocity"] = [[9, 9], [1, 2], [3, 4]]  # a static body's velocity is never read
    contacts = np.zeros(2, CONTACT_DTYPE)
    contacts["body_a"], contacts["body_b"] = 0, [1, 2]
    contacts["point"] = [[1, 0], [3, 0]]
    contacts["normal"] = [0, 1]  # from the floor (A) up into the disc (B)
    contacts["builtin"] = [[0.098, 0.0], [0.0, 0.0]]  # the second point is new this step
    contacts["separation"] = [-0.01, 0.002]
    return bodies, contacts


def test_body_channels_skip_static_bodies():
    bodies, contacts = two_bodies_on_the_floor()
    step = Step(bodies, contacts)
    np.testing.assert_array_equal(channel_values(["mass", "vy"], step), [[1.0, 2.0], [1.0, 4.0]])
    np.testing.assert_array_equal(particle_positions("bodies", step), [[1, 0.5], [3, 0.5]])
    with pytest.raises(ValueError, match="several sources"):
        channel_values(["mass", "normal_x"], step)


def test_contact_channels_read_the_records_and_what_follows_from_them():
    bodies, contacts = two_bodies_on_the_floor()
    bodies["velocity"][1:] = 0.0
    step = Step(bodies, contacts, physics=Physics(0.01, (0.0, -9.8)))
    values = channel_values(["separation", "new_point", "vn", "vn_builtin"], step)
    np.testing.assert_allclose(values[:, 0], [-0.01, 0.002], rtol=1e-6)
    np.testing.assert_array_equal(values[:, 1], [0.0, 1.0])
    # Gravity brings both discs towards the floor at 0.098 m/s; the first one's
    # builtin impulse of 0.098 N s on 1 kg cancels that exactly.
    np.testing.assert_allclose(values[:, 2], [-0.098, -0.098], atol=1e-6)
    np.testing.assert_allclose(values[:, 3], [0.0, -0.098], atol=1e-6)


def test_oracle_targets_need_the_oracle():
    bodies, contacts = two_bodies_on_the_floor()
    with pytest.raises(ValueError, match="--oracle"):
        channel_values(["oracle_correction_normal"], Step(bodies, contacts))
    oracle = np.array([[0.1, 0.0], [0.05, 0.01]], np.float32)
    got = channel_values(["oracle_correction_normal", "oracle_tangent"], Step(bodies, contacts, oracle=oracle))
    np.testing.assert_allclose(got, [[0.002, 0.0], [0.05, 0.01]], atol=1e-7)


def test_face_targets_write_the_recorded_solves_labels_as_impulses_less_builtin():
    # The first point presses and sticks, the second presses and slides along -t (friction 0.5):
    # written as 1 N s along the normal, and 0 or -1 N s along the tangent, less Box2D's warm start.
    bodies, contacts = two_bodies_on_the_floor()
    contacts["impulse"] = [[0.098, 0.01], [0.2, -0.1]]
    got = channel_values(["face_correction_normal", "face_correction_tangent"], Step(bodies, contacts))
    np.testing.assert_allclose(got, [[1 - 0.098, 0.0], [1.0, -1.0]], atol=1e-7)
    contacts["impulse"] = 0.0  # both let go
    got = channel_values(["face_correction_normal", "face_correction_tangent"], Step(bodies, contacts))
    np.testing.assert_allclose(got, [[-0.098, 0.0], [0.0, 0.0]], atol=1e-7)


def test_the_friction_channel_reads_each_points_friction_and_face_targets_read_their_slides_at_it():
    # The second point's friction (0.1 N s of 0.2) is at the limit of friction 0.5, inside that of 0.8.
    bodies, contacts = two_bodies_on_the_floor()
    contacts["impulse"] = [[0.098, 0.01], [0.2, -0.1]]
    with pytest.raises(ValueError, match="needs each point's friction"):
        channel_values(["friction"], Step(bodies, contacts))
    step = Step(bodies, contacts, friction=np.array([0.5, 0.8]))
    np.testing.assert_array_equal(channel_values(["friction"], step)[:, 0], [0.5, 0.8])
    got = channel_values(["face_correction_normal", "face_correction_tangent"], step)
    np.testing.assert_allclose(got, [[1 - 0.098, 0.0], [1.0, 0.0]], atol=1e-7)  # the second one sticks
    assert needs(["friction"]) == ("point_friction",)


def test_previous_channels_read_the_last_steps_points_and_are_empty_without_them():
    bodies, contacts = two_bodies_on_the_floor()
    assert len(channel_values(["previous_builtin_normal"], Step(bodies, contacts))) == 0
    step = Step(bodies, contacts, previous=contacts[:1])
    np.testing.assert_allclose(channel_values(["previous_builtin_normal"], step)[:, 0], [0.098])
    np.testing.assert_array_equal(particle_positions("previous", step), [[1, 0]])


def test_every_channel_has_a_known_source_a_unit_and_a_description():
    for name, channel in CHANNELS.items():
        assert channel.name == name and channel.source in SOURCES
        assert channel.unit and channel.description and set(channel.needs) <= set(NEEDS)
    assert [n for n, c in CHANNELS.items() if c.walls] == ["mass"]


def test_what_requests_must_carry_follows_from_the_channels():
    assert needs(("mass", "vx", "normal_x")) == ()
    assert needs(("vn",)) == ("physics", "point_bodies")
    assert needs(("vn_builtin", "separation")) == ("body_inertia", "builtin", "physics", "point_bodies",
                                                   "point_separation")


def test_last_correction_is_builtin_minus_last_steps_builtin_at_the_same_key():
    bodies, contacts = two_bodies_on_the_floor()
    contacts["key"] = [7, 9]
    assert not channel_values(["last_correction_normal"], Step(bodies, contacts)).any()  # no previous step
    previous = np.zeros(3, CONTACT_DTYPE)
    previous["key"] = [9, 5, 7]  # any order; key 5 has let go
    previous["builtin"] = [[0.0, 0.0], [1.0, 1.0], [0.090, 0.004]]
    got = channel_values(["last_correction_normal", "last_correction_tangent"], Step(bodies, contacts, previous))
    # Key 7: this step's builtin (last step's final impulse) minus where last step started.
    # Key 9 was there with no impulse and still has none.
    np.testing.assert_allclose(got, [[0.008, -0.004], [0.0, 0.0]], atol=1e-7)
    contacts["key"][1] = 11  # a point that was not there last step reads 0
    got = channel_values(["last_correction_normal"], Step(bodies, contacts, previous))
    np.testing.assert_allclose(got[:, 0], [0.008, 0.0], atol=1e-7)
    assert needs(("last_correction_normal",)) == ("builtin", "point_keys")


def test_asinh_channels_resolve_velocities_near_the_solvers_tolerance():
    bodies, contacts = two_bodies_on_the_floor()
    bodies["velocity"][1:] = 0.0
    contacts["builtin"][0, 0] = 0.098 + 2e-4  # the first disc pushed up at 2e-4 m/s: nearly at rest
    step = Step(bodies, contacts, physics=Physics(0.01, (0.0, -9.8)))
    fine = channel_values(["vn_builtin", "vn_builtin_asinh", "jacobi_normal", "jacobi_normal_asinh"], step)
    np.testing.assert_allclose(fine[:, 1], np.arcsinh(fine[:, 0] / 1e-4), rtol=1e-6)
    np.testing.assert_allclose(fine[:, 3], np.arcsinh(fine[:, 2] / 1e-4), rtol=1e-6)
    # 2e-4 m/s and 0.098 m/s are 2e-3 apart linearly and under a factor of 4 apart on this scale;
    # the sign stays (the disc at rest is pushed apart, the new one falls in).
    assert fine[0, 1] == pytest.approx(np.arcsinh(2.0), rel=1e-3) and fine[1, 1] < -np.arcsinh(900.0)


def test_each_channel_changes_sign_under_a_reflection_as_its_mirror_says():
    from simclient.scene import SceneSpec, build_world

    spec = SceneSpec.thesis()
    engine = build_world(spec, 901)
    for _ in range(80):  # a pile, with persisting points and friction
        engine.step()
    engine.collide()
    before = engine.contacts()
    engine.solve()
    engine.collide()
    bodies, contacts = engine.bodies(), engine.contacts()
    contacts["impulse"] = contacts["builtin"] * 0.5  # recorded data carries it; any values do here
    mu = np.full(len(contacts), 0.5)
    step = Step(bodies, contacts, before, spec.physics, friction=mu)
    mirror = Step(*reflected(bodies, contacts), reflected(bodies, before)[1], spec.physics, friction=mu)
    assert len(contacts) > 20 and np.abs(contacts["builtin"][:, 1]).max() > 1e-3
    for source in SOURCES:
        names = [n for n, c in CHANNELS.items() if c.source == source and not n.startswith("oracle")]
        got, want = channel_values(names, mirror), channel_values(names, step) * mirror_signs(names)
        for i, name in enumerate(names):
            np.testing.assert_allclose(got[:, i], want[:, i], rtol=1e-6, atol=1e-9, err_msg=name)


def test_the_scaled_channels_read_a_heavier_world_as_the_same_problem():
    from deepcontact.kinematics import Physics

    rng = np.random.default_rng(0)
    bodies = np.zeros(3, BODY_DTYPE)
    bodies["type"] = [0, 2, 2]
    bodies["mass"], bodies["inertia"] = [0.0, 2.0, 3.0], [0.0, 0.5, 0.9]
    bodies["position"] = [[0, 0], [0, 1], [1, 1]]
    bodies["velocity"] = rng.normal(size=(3, 2)) * [[0], [1], [1]]
    contacts = np.zeros(2, CONTACT_DTYPE)
    contacts["body_a"], contacts["body_b"] = [0, 1], [1, 2]
    contacts["point"], contacts["normal"] = [[0, 0.5], [0.5, 1]], [[0, 1], [1, 0]]
    contacts["builtin"] = [[0.3, 0.01], [0.1, -0.02]]
    physics = Physics(1 / 60, (0.0, -9.8))
    names = ["builtin_normal_scaled", "vn_scaled", "vt_builtin_scaled", "normal_mass_scaled", "jacobi_normal_scaled"]
    light = channel_values(names, Step(bodies, contacts, physics=physics))
    heavy_bodies, heavy_contacts = bodies.copy(), contacts.copy()
    heavy_bodies["mass"] *= 8.0
    heavy_bodies["inertia"] *= 8.0
    heavy_contacts["builtin"] *= 8.0  # every impulse of a world eight times as dense
    heavy = channel_values(names, Step(heavy_bodies, heavy_contacts, physics=physics))
    np.testing.assert_allclose(heavy, light, rtol=1e-5)
    # The scales: the dynamic bodies' median mass, and the velocity gravity adds in a step.
    assert Step(bodies, contacts, physics=physics).scales() == pytest.approx((2.5, 9.8 / 60))
    vn = channel_values(["vn"], Step(bodies, contacts, physics=physics))[:, 0]
    np.testing.assert_allclose(light[:, 1], vn / (9.8 / 60))
