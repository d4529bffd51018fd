"""GridSpec: geometry, validation, JSON round trip, walls, normalization."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from deepcontact.channels import DEFAULT_INPUTS, DEFAULT_TARGETS
from deepcontact.gridspec import SPEC_VERSION, GridSpec

def test_thesis_grid_is_61_by_61_and_includes_both_ends():
    spec = GridSpec.for_domain((0.0, 0.0), (15.0, 15.0), resolution=0.25, h=0.5)
    assert spec.shape == (61, 61)
    assert spec.upper == (15.0, 15.0)
    assert spec == GridSpec.thesis()
    nodes = spec.node_positions()
    assert nodes.shape == (61, 61, 2)
    # Node (iy, ix) sits at (x0 + ix dx, y0 + iy dx): x varies along axis 1.
    assert tuple(nodes[0, 0]) == (0.0, 0.0)
    assert tuple(nodes[0, 1]) == (0.25, 0.0)
    assert tuple(nodes[2, 0]) == (0.0, 0.5)
    assert tuple(nodes[-1, -1]) == (15.0, 15.0)


def test_defaults_follow_the_thesis():
    spec = GridSpec.thesis()
    assert spec.kernel == "poly6" and spec.h == 0.5 and spec.resolution == 0.25
    assert spec.inputs == ("mass", "vx", "vy", "omega", "normal_x", "normal_y") == DEFAULT_INPUTS
    assert spec.targets == ("impulse_normal", "impulse_tangent") == DEFAULT_TARGETS
    assert spec.wall_mass == 100.0 and spec.walls == ("bottom", "left", "right")


def test_non_square_domain_and_domain_not_a_whole_number_of_cells():
    spec = GridSpec.for_domain((-1.0, 2.0), (3.0, 4.0), resolution=0.5, h=1.0)
    assert spec.shape == (5, 9)  # (ny, nx)
    assert spec.upper == (3.0, 4.0)
    # 1.1 m at 0.5 m: the grid grows to cover the whole domain.
    spec = GridSpec.for_domain((0.0, 0.0), (1.1, 1.0), resolution=0.5, h=1.0)
    assert spec.shape == (3, 4) and spec.upper[0] >= 1.1


def test_json_round_trip_is_exact():
    spec = GridSpec.for_domain(
        (0.1, -0.3), (7.35, 2.2), resolution=0.05, h=0.1 + 0.2,  # 0.30000000000000004: exact repr matters
        kernel="gaussian",
        inputs=("mass", "omega", "separation", "builtin_normal"),
        targets=("impulse_tangent",),
        normalization={"mass": (0.785, 2.5), "impulse_tangent": (-1e-3, 3.0000000000000004)},
        wall_mass=0.0,
        walls=("bottom",),
    )
    text = spec.to_json()
    again = GridSpec.from_json(text)
    assert again == spec
    assert again.to_json() == text
    assert GridSpec.from_dict(json.loads(json.dumps(spec.to_dict()))) == spec
    assert json.loads(text)["version"] == SPEC_VERSION


def test_spec_is_frozen_and_hashable():
    spec = GridSpec.thesis(normalization={"mass": (1.0, 2.0)})
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.h = 1.0
    with pytest.raises(TypeError):
        spec.normalization["mass"] = (0.0, 1.0)  # read-only view
    assert {spec: 1}[GridSpec.from_json(spec.to_json())] == 1


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(kernel="cubic"), "unknown kernel"),
        (dict(h=0.0), "support radius h must be > 0"),
        (dict(h=-0.5), "support radius h must be > 0"),
        (dict(h=float("nan")), "h must be finite"),
        (dict(resolution=0.0), "resolution must be > 0"),
        (dict(resolution=float("inf")), "resolution must be finite"),
        (dict(origin=(0.0, float("nan"))), "origin\\[1\\] must be finite"),
        (dict(shape=(0, 61)), "shape must be two positive integers"),
        (dict(inputs=("mass", "colour")), "unknown channel 'colour'"),
        (dict(inputs=("mass", "mass")), "duplicate channel"),
        (dict(targets=("mass",)), "targets must be contact-point channels"),
        (dict(normalization={"vx": (0.0, 0.0)}), "std must be > 0"),
        (dict(normalization={"separation": (0.0, 1.0)}), "neither an input nor a target"),
        (dict(wall_mass=float("inf")), "wall_mass must be finite"),
        (dict(walls=("ceiling",)), "unknown side"),
        (dict(version=99), "unsupported GridSpec version"),
    ],
)
def test_bad_values_raise_clear_errors(kwargs, message):
    base = GridSpec.thesis().to_dict()
    base.update({k: (list(v) if isinstance(v, tuple) else v) for k, v in kwargs.items()})
    with pytest.raises(ValueError, match=message):
        GridSpec.from_dict(base)


def test_for_domain_rejects_bad_arguments():
    with pytest.raises(ValueError, match="resolution must be > 0"):
        GridSpec.for_domain((0, 0), (15, 15), resolution=-0.25, h=0.5)
    with pytest.raises(ValueError, match="above and to the right"):
        GridSpec.for_domain((0, 0), (0, 15), resolution=0.25, h=0.5)
    with pytest.raises(ValueError, match="unknown kernel"):
        GridSpec.for_domain((0, 0), (15, 15), resolution=0.25, h=0.5, kernel="Poly6")


def test_from_json_rejects_malformed_and_unknown_keys():
    with pytest.raises(ValueError, match="malformed"):
        GridSpec.from_json("{not json")
    data = GridSpec.thesis().to_dict()
    with pytest.raises(ValueError, match="unknown keys \\['colour'\\]"):
        GridSpec.from_dict({**data, "colour": "red"})
    del data["h"]
    with pytest.raises(ValueError, match="missing keys \\['h'\\]"):
        GridSpec.from_dict(data)
    with pytest.raises(ValueError, match="h must be finite"):
        GridSpec.from_json(GridSpec.thesis().to_json().replace('"h": 0.5', '"h": NaN'))


def test_wall_mask_is_bottom_row_and_side_columns_without_top():
    spec = GridSpec.for_domain((0, 0), (2, 1), resolution=0.5, h=0.5)  # 3 x 5 nodes
    expected = np.array(
        [
            [1, 1, 1, 1, 1],  # bottom row, y = 0
            [1, 0, 0, 0, 1],
            [1, 0, 0, 0, 1],  # top row: open
        ],
        dtype=bool,
    )
    np.testing.assert_array_equal(spec.wall_mask(), expected)
    grid = np.zeros((3, 5, 6), dtype=np.float32)
    spec.add_wall_mass(grid)
    np.testing.assert_array_equal(grid[..., 0], 100.0 * expected)  # the mass channel
    assert not grid[..., 1:].any()


def test_normalize_and_denormalize_invert_each_other():
    spec = GridSpec.thesis(normalization={"mass": (0.5, 2.0), "impulse_normal": (0.1, 0.2)})
    rng = np.random.default_rng(0)
    x = rng.normal(size=(61, 61, 6)).astype(np.float32)
    z = spec.normalize(x)
    np.testing.assert_allclose(z[..., 0], (x[..., 0] - 0.5) / 2.0, rtol=1e-6)
    np.testing.assert_array_equal(z[..., 1:], x[..., 1:])  # not listed: unchanged
    y = rng.normal(size=(4, 61, 61, 2)).astype(np.float32)  # a batch works too
    np.testing.assert_allclose(spec.denormalize(spec.normalize(y, "targets"), "targets"), y, rtol=1e-6, atol=1e-6)
