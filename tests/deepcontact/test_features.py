"""Step records -> CNN grids (deepcontact.features): channels in order, walls, batches, the plan."""

from __future__ import annotations

import numpy as np
import pytest

from deepcontact.features import targets_to_grids, world_to_grids, worlds_to_grids
from deepcontact.gridspec import GridSpec
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from deepcontact.transfer import g2p

THESIS = GridSpec.thesis()


def small_world():
    bodies = np.zeros(3, dtype=BODY_DTYPE)
    bodies["type"] = [0, 2, 2]  # the static box is not a particle
    bodies["position"] = [[0.0, 0.0], [5.0, 0.5], [5.9, 0.5]]
    bodies["mass"] = [0.0, 0.785, 0.785]
    bodies["velocity"] = [[0, 0], [1.0, -2.0], [0.5, 0.0]]
    bodies["angular_velocity"] = [0.0, 3.0, -1.0]
    contacts = np.zeros(3, dtype=CONTACT_DTYPE)
    contacts["point"] = [[5.0, 0.0075], [5.9, 0.0075], [5.45, 0.5]]
    contacts["normal"] = [[0, -1], [0, -1], [1, 0]]
    contacts["impulse"] = [[0.04, 0.001], [0.05, -0.002], [0.01, 0.0]]
    return bodies, contacts


def test_world_to_grids_builds_the_input_channels_in_order():
    bodies, contacts = small_world()
    grid, reports = world_to_grids(bodies, contacts, THESIS, return_report=True)
    assert grid.shape == (61, 61, 6) and grid.dtype == np.float32
    sums = grid.sum(axis=(0, 1), dtype=np.float64)
    walls = THESIS.wall_mask().sum() * THESIS.wall_mass  # thesis §8.1: the box's edges weigh 100
    np.testing.assert_allclose(sums, [1.57 + walls, 1.5, -2.0, 2.0, 1.0, -2.0], rtol=1e-5)
    assert grid[0, 30, 0] >= 100.0 and grid[30, 0, 0] == 100.0 and grid[60, 30, 0] == 0.0  # no top wall
    assert reports["bodies"].n_particles == 2 and reports["contacts"].n_particles == 3
    bare = world_to_grids(bodies, contacts, THESIS, walls=False)
    np.testing.assert_allclose(bare.sum(axis=(0, 1))[0], 1.57, rtol=1e-5)
    np.testing.assert_array_equal(bare[..., 1:], grid[..., 1:])


def test_targets_to_grids_and_back_to_the_contacts():
    _, contacts = small_world()
    target = targets_to_grids(contacts, THESIS)
    assert target.shape == (61, 61, 2)
    np.testing.assert_allclose(target.sum(axis=(0, 1)), contacts["impulse"].sum(axis=0), rtol=1e-5)
    back, report = g2p(target, contacts["point"], THESIS)
    assert report.n_lost == 0
    np.testing.assert_allclose(back.sum(axis=0), contacts["impulse"].sum(axis=0), rtol=1e-5)


def test_worlds_to_grids_stacks_a_batch():
    bodies, contacts = small_world()
    grids, reports = worlds_to_grids([(bodies, contacts), (bodies[:1], contacts[:0])], THESIS)
    assert grids.shape == (2, 61, 61, 6) and len(reports) == 2
    np.testing.assert_array_equal(grids[0], world_to_grids(bodies, contacts, THESIS))
    assert reports[1]["bodies"].n_particles == 0 and reports[1]["contacts"].n_particles == 0
    assert grids[1][..., 1:].sum() == 0.0  # an empty world: only the walls' mass


def test_world_values_are_checked():
    bodies, contacts = small_world()
    contacts["normal"][1, 0] = np.nan
    with pytest.raises(ValueError, match="contacts values contain NaN.*normal_x"):
        world_to_grids(bodies, contacts, THESIS)


def test_world_to_grids_hands_back_the_contact_points_plan():
    bodies, contacts = small_world()
    contacts = np.concatenate([contacts, contacts[:1]])
    contacts["point"][-1] = [16.0, 3.0]  # outside the domain: dropped
    grid, pl = world_to_grids(bodies, contacts, THESIS, outside="drop", return_plan=True)
    grid2, reports, pl2 = world_to_grids(bodies, contacts, THESIS, outside="drop", return_report=True, return_plan=True)
    np.testing.assert_array_equal(grid, world_to_grids(bodies, contacts, THESIS, outside="drop"))
    np.testing.assert_array_equal(grid2, grid)
    assert reports["contacts"].outside.tolist() == [3] and pl.outside.tolist() == [3]
    out = np.random.default_rng(10).normal(size=(61, 61, 2)).astype(np.float32)
    expected, expected_report = g2p(out, contacts["point"], THESIS, outside="drop")
    for p in (pl, pl2):
        got, report = p.g2p(out)
        np.testing.assert_array_equal(got, expected)
        assert report.to_dict() == expected_report.to_dict()
    # Inputs that read no contact point still give the contact points' plan.
    spec = GridSpec.thesis(inputs=("mass", "vx"))
    _, pl = world_to_grids(bodies, contacts, spec, outside="drop", return_plan=True)
    np.testing.assert_array_equal(pl.g2p(out)[0], expected)


@pytest.mark.parametrize("walls", [("bottom", "left", "right"), ("bottom", "left", "right", "top"), ("left",), ()])
def test_wall_mass_goes_where_gridspec_puts_it(walls):
    spec = GridSpec.thesis(walls=walls)
    bodies, contacts = small_world()
    bare, _ = worlds_to_grids([(bodies, contacts), (bodies, contacts[:1])], spec, walls=False)
    grids, _ = worlds_to_grids([(bodies, contacts), (bodies, contacts[:1])], spec)
    np.testing.assert_array_equal(grids, spec.add_wall_mass(bare.copy()))
