"""lab.scaled_worlds: the thesis world scaled in one quantity, and the stopping rule scaled with it."""

from __future__ import annotations

import numpy as np
import pytest

from lab.scaled_worlds import SCALINGS, density_10, reference, relative_tolerance


def test_the_relative_stopping_rule_scales_as_the_steps_impulses():
    assert relative_tolerance("reference") == pytest.approx(1e-4)
    assert relative_tolerance("density_10") == pytest.approx(1e-3)
    assert relative_tolerance("gravity_2") == pytest.approx(1e-4 * 2 / 9.8)
    assert relative_tolerance("dt_1_30") == pytest.approx(1e-4 * (1 / 30) / 0.01)
    assert set(SCALINGS) >= {"density_0p5", "gravity_20", "dt_1_120"}
    with pytest.raises(KeyError):
        relative_tolerance("no-such-world")


def test_a_denser_world_is_the_thesis_world_with_every_mass_scaled():
    (dense, dt_dense), (thesis, dt) = density_10(901), reference(901)
    assert dt_dense == dt == 0.01
    masses = np.array([b.mass for b in thesis.bodies if b.mass > 0])
    np.testing.assert_allclose([b.mass for b in dense.bodies if b.mass > 0], 10.0 * masses, rtol=1e-5)
    np.testing.assert_allclose([tuple(b.position) for b in dense.bodies], [tuple(b.position) for b in thesis.bodies])


def test_a_world_similar_in_time_passes_through_the_thesis_worlds_positions_step_by_step():
    # Gravity 2 m/s^2 with the time step sqrt(9.8 / 2) times the thesis world's: ten free-fall
    # steps take every body to the same places (Box2D's semi-implicit Euler is exact in this
    # scaling: v += g dt, x += v dt both scale with g dt^2).
    from lab.scaled_worlds import similar_gravity_2

    (similar, dt_similar), (thesis, dt) = similar_gravity_2(901), reference(901)
    assert dt_similar == pytest.approx(0.01 * np.sqrt(9.8 / 2.0))
    assert relative_tolerance("similar_gravity_2") == pytest.approx(1e-4 * np.sqrt(2.0 / 9.8))
    for world, step in ((similar, dt_similar), (thesis, dt)):
        for _ in range(10):
            world.Step(step, 8, 3)
    np.testing.assert_allclose([tuple(b.position) for b in similar.bodies], [tuple(b.position) for b in thesis.bodies],
                               atol=1e-4)
