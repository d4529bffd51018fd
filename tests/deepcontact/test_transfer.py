"""P2G / G2P: conservation, lost particles, edges, symmetry, bilinear, bad input.

The reference below is thesis Algorithms 1 and 2 written the obvious way, with
a dense (particles x nodes) matrix of full kernel values; the vectorized
implementation must agree with it.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from deepcontact.gridspec import GridSpec
from deepcontact.transfer import (
    DOMAIN_TOLERANCE,
    TransferPlan,
    g2p,
    kernel,
    kernel_shape,
    p2g,
    p2g_batch,
    plan,
)

THESIS = GridSpec.thesis()  # 15 m x 15 m at 0.25 m, h = 0.5 m: 61 x 61
SMALL = GridSpec.for_domain((0.0, 0.0), (3.0, 2.0), resolution=0.25, h=0.5)  # 9 x 13


def dense_weights(spec: GridSpec, positions: np.ndarray) -> np.ndarray:
    """(N, ny * nx) full kernel values W(|node - particle|, h)."""
    nodes = spec.node_positions().reshape(-1, 2)
    r = np.linalg.norm(np.asarray(positions, float)[:, None, :] - nodes[None, :, :], axis=-1)
    return kernel(r, spec.h, spec.kernel)


def reference_p2g(spec, positions, values):
    w = dense_weights(spec, positions)
    total = w.sum(axis=1, keepdims=True)
    w = np.divide(w, total, out=np.zeros_like(w), where=total > 0)  # normalize per particle
    return (w.T @ values).reshape(spec.ny, spec.nx, -1)


def reference_g2p(spec, grid, positions):
    w = dense_weights(spec, positions)
    total = w.sum(axis=0, keepdims=True)
    w = np.divide(w, total, out=np.zeros_like(w), where=total > 0)  # normalize per node
    return w @ grid.reshape(spec.n_nodes, -1)


def random_particles(rng, spec, n, channels):
    lo, hi = np.array(spec.lower), np.array(spec.upper)
    return rng.uniform(lo, hi, size=(n, 2)), rng.normal(size=(n, channels))


# --------------------------------------------------------------------------- #
# P2G
# --------------------------------------------------------------------------- #


def test_p2g_conserves_every_channel():
    rng = np.random.default_rng(1)
    positions, values = random_particles(rng, THESIS, 300, 4)
    grid, report = p2g(positions, values, THESIS)
    assert grid.shape == (61, 61, 4) and grid.dtype == np.float32
    np.testing.assert_allclose(grid.sum(axis=(0, 1), dtype=np.float64), values.sum(axis=0), rtol=1e-5, atol=1e-4)
    assert report.n_particles == 300 and report.n_lost == 0 and report.n_outside == 0


@pytest.mark.parametrize("kernel_name", ["poly6", "spiky", "gaussian"])
@pytest.mark.parametrize("resolution, h", [(0.25, 0.5), (0.5, 0.5), (0.25, 0.3), (0.5, 1.2)])
def test_p2g_and_sph_g2p_match_the_algorithms(kernel_name, resolution, h):
    spec = GridSpec.for_domain((0.0, 0.0), (3.0, 2.0), resolution, h, kernel=kernel_name)
    rng = np.random.default_rng(2)
    positions, values = random_particles(rng, spec, 40, 3)
    grid, _ = p2g(positions, values, spec)
    np.testing.assert_allclose(grid, reference_p2g(spec, positions, values), rtol=1e-5, atol=1e-6)
    back, _ = g2p(grid, positions, spec)
    np.testing.assert_allclose(back, reference_g2p(spec, grid, positions), rtol=1e-5, atol=1e-6)


def test_particle_with_no_node_in_range_is_lost_and_reported():
    spec = GridSpec.for_domain((0.0, 0.0), (2.0, 2.0), resolution=0.5, h=0.125)
    positions = np.array([[0.25, 0.25], [1.0, 1.0], [1.30, 0.75]])  # a cell centre, a node, 0.2 m from a node
    values = np.array([[2.0, -1.0], [3.0, 5.0], [7.0, 11.0]])
    grid, report = p2g(positions, values, spec)
    assert report.n_lost == 2 and report.lost.tolist() == [0, 2]
    np.testing.assert_allclose(report.lost_value, [9.0, 10.0])
    assert report.n_transferred == 1
    # Only the particle on a node arrived, all of it on that node.
    np.testing.assert_allclose(grid.sum(axis=(0, 1)), [3.0, 5.0])
    np.testing.assert_allclose(grid[2, 2], [3.0, 5.0])


def test_edges_and_corners_conserve_and_stay_on_the_grid():
    spec = SMALL
    x1, y1 = spec.upper
    corners_and_edges = np.array([[0.0, 0.0], [x1, y1], [x1, 0.0], [0.0, y1], [1.5, 0.0], [0.0, 1.1], [x1, 0.6]])
    values = np.arange(1.0, 8.0)[:, None]
    grid, report = p2g(corners_and_edges, values, spec, tolerance=0.0)  # exactly on the edge is inside
    assert report.n_lost == 0 and report.n_outside == 0
    np.testing.assert_allclose(grid.sum(), values.sum(), rtol=1e-6)
    np.testing.assert_allclose(grid, reference_p2g(spec, corners_and_edges, values), rtol=1e-5, atol=1e-6)
    # A lone particle on the lower-left corner: a quarter disc, symmetric in x and y.
    corner, _ = p2g([[0.0, 0.0]], [1.0], spec)
    patch = corner[:3, :3, 0]
    np.testing.assert_allclose(patch, patch.T, atol=1e-7)
    np.testing.assert_allclose(patch.sum(), 1.0, rtol=1e-6)


@settings(max_examples=40, deadline=None)
@given(
    points=st.lists(st.tuples(st.floats(0.0, 3.0), st.floats(0.0, 2.0)), min_size=1, max_size=30),
    kernel_name=st.sampled_from(["poly6", "spiky", "gaussian"]),
)
def test_p2g_conserves_for_any_particles_in_the_domain(points, kernel_name):
    # h = 2 dx: every point of the domain, edges and corners included, has nodes in range.
    spec = GridSpec.for_domain((0.0, 0.0), (3.0, 2.0), 0.25, 0.5, kernel=kernel_name)
    positions = np.array(points)
    values = np.arange(1.0, len(points) + 1.0)
    grid, report = p2g(positions, values, spec, tolerance=0.0)
    assert report.n_lost == 0 and report.n_outside == 0
    assert grid.sum(dtype=np.float64) == pytest.approx(values.sum(), rel=1e-5)
    back, _ = g2p(grid, positions, spec)
    assert back.sum(dtype=np.float64) == pytest.approx(values.sum(), rel=1e-5)  # every loaded node has a particle


def test_particle_on_a_node_gives_a_symmetric_splat():
    x, y = 1.5, 1.0  # node (iy, ix) = (4, 6)
    grid, _ = p2g([[x, y]], [[1.0]], SMALL)
    patch = grid[2:7, 4:9, 0]  # 5 x 5 around the node (h = 2 nodes)
    assert grid.sum() == pytest.approx(1.0)
    assert patch.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(patch, patch[::-1, :], atol=1e-7)
    np.testing.assert_allclose(patch, patch[:, ::-1], atol=1e-7)
    np.testing.assert_allclose(patch, patch.T, atol=1e-7)
    assert patch[2, 2] == patch.max()
    assert patch[0, 0] == 0.0  # corner at 2 sqrt(2) nodes: beyond h


def test_mirroring_positions_mirrors_the_grid():
    rng = np.random.default_rng(3)
    positions, values = random_particles(rng, SMALL, 25, 2)
    mirrored = positions.copy()
    mirrored[:, 0] = SMALL.upper[0] - positions[:, 0]  # x -> width - x
    grid, _ = p2g(positions, values, SMALL)
    grid_m, _ = p2g(mirrored, values, SMALL)
    np.testing.assert_allclose(grid_m, grid[:, ::-1], atol=1e-6)


def test_empty_inputs_give_zero_grids_and_empty_arrays():
    grid, report = p2g(np.zeros((0, 2)), np.zeros((0, 3)), THESIS)
    assert grid.shape == (61, 61, 3) and not grid.any() and report.n_particles == 0
    values, report = g2p(np.ones((61, 61, 2)), np.zeros((0, 2)), THESIS)
    assert values.shape == (0, 2) and values.dtype == np.float32
    assert report.n_nodes_lost == 61 * 61  # nobody to receive anything
    np.testing.assert_allclose(report.lost_value, [61 * 61, 61 * 61])
    values, _ = g2p(np.ones((61, 61, 2)), np.zeros((0, 2)), THESIS, method="bilinear")
    assert values.shape == (0, 2)


def test_p2g_batch_matches_one_world_at_a_time():
    rng = np.random.default_rng(4)
    worlds = [random_particles(rng, SMALL, n, 2) for n in (5, 0, 17, 1)]
    grids, reports = p2g_batch([p for p, _ in worlds], [v for _, v in worlds], SMALL)
    assert grids.shape == (4, SMALL.ny, SMALL.nx, 2)
    for (positions, values), grid, report in zip(worlds, grids, reports):
        alone, alone_report = p2g(positions, values, SMALL)
        np.testing.assert_allclose(grid, alone, atol=1e-6)
        assert report.n_particles == alone_report.n_particles == len(positions)


def test_large_inputs_match_the_algorithms():
    rng = np.random.default_rng(5)
    positions, values = random_particles(rng, SMALL, 2500, 2)
    grid, _ = p2g(positions, values, SMALL)
    np.testing.assert_allclose(grid, reference_p2g(SMALL, positions, values), rtol=1e-5, atol=1e-5)
    back, _ = g2p(grid, positions, SMALL)
    np.testing.assert_allclose(back, reference_g2p(SMALL, grid, positions), rtol=1e-5, atol=1e-6)
    grids, _ = p2g_batch([positions[:1500], positions[1500:]], [values[:1500], values[1500:]], SMALL)
    np.testing.assert_allclose(grids.sum(axis=0), grid, atol=1e-5)


@pytest.mark.parametrize("channels", [1, 3, 5, 17, 40])
def test_any_number_of_channels_matches_the_algorithms(channels):
    # The compiled loops work through channels in blocks (4 in G2P, 16 in P2G).
    rng = np.random.default_rng(channels)
    positions, values = random_particles(rng, SMALL, 60, channels)
    grid, _ = p2g(positions, values, SMALL)
    np.testing.assert_allclose(grid, reference_p2g(SMALL, positions, values), rtol=1e-5, atol=1e-5)
    back, _ = g2p(grid, positions, SMALL)
    np.testing.assert_allclose(back, reference_g2p(SMALL, grid, positions), rtol=1e-5, atol=1e-5)
    back64, _ = g2p(grid.astype(np.float64), positions, SMALL)
    np.testing.assert_allclose(back64, back, rtol=1e-6, atol=1e-7)


def test_compiled_kernels_refuse_wrong_sizes_and_node_indices():
    # deepcontact/_transfer.c is only called by this module, with arrays it
    # made; still, a wrong call raises instead of writing out of bounds.
    from deepcontact import _transfer

    nodes = np.array([[0, 1], [2, 99]], dtype=np.int32)  # 99: not one of the 4 nodes
    weights = np.ones((2, 2))
    divisor = np.full(2, 2.0)
    values = np.ones((2, 3))
    with pytest.raises(IndexError, match="node index 99"):
        _transfer.splat(nodes, weights, divisor, values, 4, np.empty((4, 3), np.float32))
    with pytest.raises(IndexError, match="node index 99"):
        _transfer.gather(nodes, weights, np.ones((4, 3), np.float32), False, np.empty((2, 3), np.float32),
                         np.empty(4), np.empty((4, 3), np.float32))
    with pytest.raises(ValueError, match="values holds 48 bytes, expected 32"):  # out has 2 channels, values 3
        _transfer.splat(nodes % 4, weights, divisor, values, 4, np.empty((4, 2), np.float32))
    with pytest.raises(ValueError, match="not C-contiguous"):  # a strided view is no flat buffer
        _transfer.splat(nodes % 4, weights, divisor, np.ones((2, 6))[:, ::2], 4, np.empty((4, 3), np.float32))


# --------------------------------------------------------------------------- #
# G2P
# --------------------------------------------------------------------------- #


def test_sph_g2p_conserves_the_nodes_it_reaches():
    rng = np.random.default_rng(6)
    grid = rng.normal(size=(61, 61, 2)).astype(np.float32)
    positions = rng.uniform(0, 15, size=(200, 2))
    values, report = g2p(grid, positions, THESIS)
    assert values.shape == (200, 2) and values.dtype == np.float32
    reached = (dense_weights(THESIS, positions) > 0).any(axis=0).reshape(61, 61)
    np.testing.assert_allclose(values.sum(axis=0), grid[reached].sum(axis=0), rtol=1e-4, atol=1e-3)
    # What no particle could take is reported, not silently dropped.
    np.testing.assert_allclose(report.lost_value, grid[~reached].sum(axis=0), rtol=1e-4, atol=1e-3)
    assert report.n_nodes_lost == (~reached).sum()


def test_sph_round_trip_of_one_particle_returns_its_value():
    grid, _ = p2g([[7.3, 2.1]], [[0.785, -2.0]], THESIS)
    back, report = g2p(grid, [[7.3, 2.1]], THESIS)
    np.testing.assert_allclose(back, [[0.785, -2.0]], rtol=1e-5)
    assert report.n_lost == 0 and report.n_nodes_lost == 0


def test_g2p_particle_with_no_node_in_range_gets_zero():
    spec = GridSpec.for_domain((0.0, 0.0), (2.0, 2.0), resolution=0.5, h=0.125)
    values, report = g2p(np.ones((5, 5)), [[0.25, 0.25], [1.0, 1.0]], spec)
    np.testing.assert_array_equal(values[:, 0], [0.0, 1.0])
    assert report.lost.tolist() == [0]
    assert report.n_nodes_lost == 24 and report.lost_value.tolist() == [24.0]


def test_bilinear_reproduces_a_linear_field_exactly():
    nodes = THESIS.node_positions()
    field = 0.3 + 1.7 * nodes[..., 0] - 0.9 * nodes[..., 1]
    grid = np.stack([field, 2 * field], axis=-1)
    rng = np.random.default_rng(7)
    positions = np.vstack([rng.uniform(0, 15, size=(100, 2)), [[0, 0], [15, 15], [15, 0], [7.5, 15]]])
    values, report = g2p(grid, positions, THESIS, method="bilinear")
    expected = 0.3 + 1.7 * positions[:, 0] - 0.9 * positions[:, 1]
    np.testing.assert_allclose(values[:, 0], expected, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(values[:, 1], 2 * expected, rtol=1e-5, atol=1e-4)
    assert report.n_lost == 0


# --------------------------------------------------------------------------- #
# Bad input and the domain
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda: p2g([[1.0, np.nan]], [1.0], THESIS), "positions contain NaN"),
        (lambda: p2g([[1.0, 1.0]], [[np.inf]], THESIS), "values contain NaN or infinite"),
        (lambda: p2g([[1.0, 1.0, 1.0]], [1.0], THESIS), "shape \\(N, 2\\)"),
        (lambda: p2g([[1.0, 1.0]], [1.0, 2.0], THESIS), "N = 1 particles"),
        (lambda: p2g([[16.0, 1.0]], [1.0], THESIS), "1 particles outside the grid domain"),
        (lambda: p2g([[1.0, 1.0]], [1.0], THESIS, outside="clip"), "outside must be one of"),
        (lambda: p2g([[1.0, 1.0]], [1.0], THESIS, tolerance=-1.0), "tolerance"),
        (lambda: g2p(np.zeros((61, 61, 1)), [[np.inf, 1.0]], THESIS), "positions contain NaN or infinite"),
        (lambda: g2p(np.full((61, 61, 1), np.nan), [[1.0, 1.0]], THESIS), "grid contains NaN"),
        (lambda: g2p(np.zeros((60, 61, 1)), [[1.0, 1.0]], THESIS), "grid must have shape"),
        (lambda: g2p(np.zeros((61, 61, 1)), [[1.0, 1.0]], THESIS, method="nearest"), "method must be one of"),
        (lambda: g2p(np.zeros((61, 61, 1)), [[-1.0, 1.0]], THESIS), "outside the grid domain"),
    ],
)
def test_bad_input_raises_value_error(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_outside_particles_are_dropped_and_counted_on_request():
    positions = np.array([[1.0, 1.0], [15.5, 3.0], [2.0, -0.2]])
    values = np.array([[1.0], [10.0], [100.0]])
    grid, report = p2g(positions, values, THESIS, outside="drop")
    assert report.n_outside == 2 and report.outside.tolist() == [1, 2]
    assert report.lost_value.tolist() == [110.0]
    assert grid.sum() == pytest.approx(1.0)
    back, report = g2p(grid, positions, THESIS, outside="drop")
    assert report.outside.tolist() == [1, 2]
    np.testing.assert_allclose(back[:, 0], [1.0, 0.0, 0.0], rtol=1e-6)


def test_points_a_little_past_a_wall_are_within_tolerance():
    # A contact point against the floor can sit a few mm below y = 0.
    grid, report = p2g([[3.0, -0.004]], [2.0], THESIS)
    assert report.n_outside == 0 and grid.sum() == pytest.approx(2.0)
    with pytest.raises(ValueError, match="outside"):
        p2g([[3.0, -0.004]], [2.0], THESIS, tolerance=0.0)
    assert DOMAIN_TOLERANCE == 0.01


def test_kernel_shape_is_proportional_to_the_kernel():
    r = np.linspace(0.0, 0.6, 61)
    for name in ("poly6", "spiky", "gaussian"):
        full = kernel(r, 0.5, name)
        shape = kernel_shape((r / 0.5) ** 2, name)
        inside = r < 0.5
        ratio = full[inside] / shape[inside]
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-9)
        assert not shape[r > 0.5].any()
    # The Gaussian is truncated at h (where it is still exp(-4.5) of its peak).
    assert kernel(np.array([0.5]), 0.5, "gaussian")[0] > 0 and kernel(np.array([0.5001]), 0.5, "gaussian")[0] == 0


# --------------------------------------------------------------------------- #
# The two commands, on tiny settings (real engine)
# --------------------------------------------------------------------------- #


def test_transfer_table_command(tmp_path, capsys):
    import json

    from commands import main

    out = tmp_path / "table.json"
    assert main(["transfer-table", "--worlds", "1", "--steps", "20", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["resolution"], r["h"]) for r in rows] == [(r, h) for r in (0.125, 0.25, 0.5) for h in (0.125, 0.25, 0.5)]
    chosen = rows[5]  # 0.25 m, h = 0.5 m: nothing lost, bodies come back exactly
    assert chosen["body_lost_p2g"] == 0 and chosen["body_avg_diff"] < 1e-5
    assert rows[6]["body_lost_p2g"] > 0  # 0.5 m with h = 0.125 m loses bodies
    assert "Avg contact diff" in capsys.readouterr().out


def test_bench_transfer_command(tmp_path):
    import json

    from commands import main

    out = tmp_path / "bench.json"
    assert main(["bench", "transfer", "--repeats", "5", "--settle-steps", "20", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["timings_us"]) >= {"p2g_inputs", "g2p_sph"}
    assert result["input_shape"] == [61, 61, 6] and result["target_shape"] == [61, 61, 2]


# --------------------------------------------------------------------------- #
# Plans: weights computed once for P2G and G2P
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("kernel_name", ["poly6", "spiky", "gaussian"])
def test_a_plan_transfers_exactly_like_p2g_and_g2p(kernel_name):
    spec = GridSpec.for_domain((0.0, 0.0), (3.0, 2.0), 0.25, 0.5, kernel=kernel_name)
    rng = np.random.default_rng(8)
    positions, values = random_particles(rng, spec, 60, 3)
    positions[:3] = [[-0.5, 1.0], [1.0, 2.7], [3.005, 0.0]]  # two outside, one within the tolerance
    pl = plan(positions, spec, outside="drop")
    assert isinstance(pl, TransferPlan) and pl.n_particles == 60 and pl.outside.tolist() == [0, 1]
    grid, report = pl.p2g(values)
    expected, expected_report = p2g(positions, values, spec, outside="drop")
    np.testing.assert_array_equal(grid, expected)
    assert report.to_dict() == expected_report.to_dict()
    back, report = pl.g2p(grid)
    expected, expected_report = g2p(grid, positions, spec, outside="drop")
    np.testing.assert_array_equal(back, expected)
    assert report.to_dict() == expected_report.to_dict()
    with pytest.raises(ValueError, match="outside"):
        plan(positions, spec)  # outside="raise" by default, as p2g


def test_the_g2p_operator_is_the_plans_g2p_as_a_sparse_matrix():
    rng = np.random.default_rng(12)
    positions = np.concatenate([rng.uniform(0, 15, size=(200, 2)), [[16.0, 3.0]]])  # the last one is outside
    pl = plan(positions, THESIS, outside="drop")
    nodes, weights = pl.g2p_operator()
    grid = rng.normal(size=(61, 61, 3)).astype(np.float32)
    by_operator = (grid.reshape(-1, 3)[nodes] * weights[..., None]).sum(axis=1)
    np.testing.assert_allclose(by_operator, pl.g2p(grid)[0], rtol=1e-5, atol=1e-6)
    assert not weights[-1].any()


def test_plan_rows_transfer_like_a_plan_of_those_particles():
    rng = np.random.default_rng(9)
    positions, _ = random_particles(rng, SMALL, 40, 1)
    positions[[5, 30]] = [[-1.0, 0.5], [1.0, 9.0]]  # outside, dropped
    grid = rng.normal(size=(SMALL.ny, SMALL.nx, 2))
    whole = plan(positions, SMALL, outside="drop")
    for start, stop in [(0, 40), (0, 10), (10, 31), (31, 40), (7, 7)]:
        part = whole.rows(start, stop)
        alone = plan(positions[start:stop], SMALL, outside="drop")
        assert part.n_particles == stop - start and part.outside.tolist() == alone.outside.tolist()
        got, report = part.g2p(grid)
        expected, expected_report = alone.g2p(grid)
        np.testing.assert_array_equal(got, expected)
        assert report.to_dict() == expected_report.to_dict()


# --------------------------------------------------------------------------- #
# Stencils at the edges: windows moved inwards, grids smaller than a window
# --------------------------------------------------------------------------- #


@pytest.mark.parametrize("kernel_name", ["poly6", "spiky", "gaussian"])
@pytest.mark.parametrize(
    "upper, resolution, h",
    [((3.0, 2.0), 0.25, 0.5), ((1.0, 1.0), 0.5, 1.2), ((0.5, 2.0), 0.5, 0.9), ((2.0, 2.0), 1.0, 5.0)],
)
def test_edges_small_grids_and_far_particles_match_the_algorithms(kernel_name, upper, resolution, h):
    # Windows larger than the grid (3 x 3 nodes, h = 5 dx), and particles up
    # to 3 m outside (tolerance 3 m): every node in range is still found.
    spec = GridSpec.for_domain((0.0, 0.0), upper, resolution, h, kernel=kernel_name)
    rng = np.random.default_rng(11)
    positions = rng.uniform(np.array(spec.lower) - 3.0, np.array(spec.upper) + 3.0, size=(60, 2))
    values = rng.normal(size=(60, 2))
    grid, report = p2g(positions, values, spec, tolerance=3.0)
    np.testing.assert_allclose(grid, reference_p2g(spec, positions, values), rtol=1e-5, atol=1e-6)
    lost = ~(dense_weights(spec, positions) > 0).any(axis=1)
    assert report.lost.tolist() == np.flatnonzero(lost).tolist()
    back, _ = g2p(grid, positions, spec, tolerance=3.0)
    np.testing.assert_allclose(back, reference_g2p(spec, grid, positions), rtol=1e-5, atol=1e-6)
