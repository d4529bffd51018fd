"""Networks whose rounds read the contact problem's operator (training.graph_model, `probes`),
and the screen that trains them beside a plain control (lab.probe_screen)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from training.contact_graph import GRAPH_INPUTS, build_graph_set


@pytest.fixture(scope="module")
def graphs(data):
    return build_graph_set(data / "train.h5", max_steps=12)


def test_a_probe_reads_what_each_trial_impulse_does_at_every_point(graphs):
    from training.graph_loss import apply_delassus
    from training.graph_model import ContactGraphNet, GraphConfig

    steps = [3, 5]
    _, _, ends, _ = graphs.batch(steps)
    geometry, masses, inverse = graphs.solver_batch(steps)
    trials = np.random.default_rng(0).normal(size=(len(ends), 4)).astype(np.float32)  # normal parts, then tangent
    a, b = ends[:, 0], ends[:, 1]
    for incidence in ("segments", "matmul", "scatter"):  # training's sums and both exports' give one answer
        net = ContactGraphNet(GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=1, probes=2),
                              incidence=incidence)
        at_a, at_b = (np.eye(len(inverse), dtype=np.float32)[a], np.eye(len(inverse), dtype=np.float32)[b]) \
            if incidence == "matmul" else (None, None)
        got = net._probe(trials, a, b, at_a, at_b, geometry, masses, inverse).numpy()
        for k in range(2):  # each trial alone through m_eff * J M^-1 J^T
            alone = (masses * apply_delassus(trials[:, [k, 2 + k]], ends, geometry, inverse)).numpy()
            np.testing.assert_allclose(got[:, [k, 2 + k]], alone, rtol=1e-4, atol=1e-5)


def test_a_network_with_probes_needs_its_physics_and_cards_without_them_read_as_before(graphs):
    from training.graph_model import ContactGraphNet, GraphConfig, config_to_dict

    x, _, e, d = graphs.batch([3])
    net = ContactGraphNet(GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, probes=3))
    with pytest.raises(ValueError, match="physics"):
        net(x, e, d)
    y = net(x, e, d, physics=graphs.solver_batch([3]))
    assert y.shape == (len(x), 2)
    assert "probes" not in config_to_dict(GraphConfig(in_channels=14))
    assert config_to_dict(net.config)["probes"] == 3


def test_the_screen_trains_the_control_and_the_probed_network_the_same_way(data, tmp_path, capsys):
    from lab.probe_screen import main

    out = tmp_path / "screen.json"
    assert main(["--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--probes", "0,2", "--epochs", "2",
                 "--width", "8", "--rounds", "2", "--batch-size", "4", "--cache", str(tmp_path / "cache"),
                 "--json", str(out), "--quiet"]) == 0
    control, probed = json.loads(out.read_text())["networks"]
    assert (control["probes"], probed["probes"]) == (0, 2)
    assert probed["weights"] == control["weights"] + 2 * (8 * 4 + 4) + 2 * (4 * 8)  # the probe layers and their reads
    assert [h[0] for h in control["history"]] == [h[0] for h in probed["history"]] == [1, 2]
    assert "| 2 |" in capsys.readouterr().out


def test_a_body_state_is_kept_by_the_bodies_that_take_impulses_only(graphs):
    from training.graph_model import ContactGraphNet, GraphConfig, config_to_dict, init_weights

    plain = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2)
    kept = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, body_state=True)
    rng = np.random.default_rng(0)
    weights = {k: (0.5 * rng.standard_normal(v.shape)).astype(np.float32) for k, v in init_weights(kept).items()}
    x, _, e, d = graphs.batch([3])
    with_state = ContactGraphNet(kept, weights)
    without = ContactGraphNet(plain, {k: v for k, v in weights.items() if "_body" not in k})
    assert not np.allclose(with_state(x, e, d).numpy(), without(x, e, d).numpy())
    # Where every body is static no body keeps anything, so the state changes nothing.
    static = np.zeros_like(d)
    np.testing.assert_allclose(with_state(x, e, static).numpy(), without(x, e, static).numpy(), rtol=1e-5, atol=1e-6)
    assert "body_state" not in config_to_dict(plain) and config_to_dict(kept)["body_state"] is True
    assert sum(w.size for w in weights.values()) - sum(w.size for w in without.weights().values()) \
        == 2 * ((2 * 8 * 8 + 8) + (8 * 8 + 8))  # each round's two layers that update the state


def one_network_screened(data, tmp_path, *flags: str) -> dict:
    """The screen's row for one small network (width 8, two rounds, one epoch) trained with `flags`."""
    from lab.probe_screen import main

    out = tmp_path / "screen.json"
    assert main(["--train", str(data / "train.h5"), "--val", str(data / "val.h5"), *flags, "--epochs", "1",
                 "--width", "8", "--rounds", "2", "--batch-size", "4", "--cache", str(tmp_path / "cache"),
                 "--json", str(out), "--quiet"]) == 0
    (row,) = json.loads(out.read_text())["networks"]
    return row


def test_the_screen_with_a_body_state_records_it_beside_the_probes(data, tmp_path, capsys):
    row = one_network_screened(data, tmp_path, "--probes", "0", "--body-state", "--price-steps", "0")
    assert row["body_state"] is True and row["probes"] == 0
    assert "| 0 | yes |" in capsys.readouterr().out


def test_the_screen_with_a_graph_wide_summary_prices_each_step_by_its_own(data, tmp_path, capsys):
    row = one_network_screened(data, tmp_path, "--probes", "2", "--pooled", "--price-steps", "4")
    assert row["pooled"] is True and row["body_state"] is False
    # Each round's update reads one more state: the step's mean, W more rows.
    assert row["weights"] == 8 * 14 + 8 + 8 * 8 + 8 + 2 * (3 * (8 * 8 + 8) + (8 * 4 + 4) + ((4 * 8 + 4) * 8 + 8)) \
        + (8 * 8 + 8) + (8 * 2 + 2)
    assert row["price"]["steps"] == 4 and row["price"]["sweeps"] > 0
    assert "| 2 | no | yes |" in capsys.readouterr().out


def test_a_state_per_step_is_each_steps_own_and_the_screen_offers_it(graphs, data, tmp_path, capsys):
    from training.graph_model import ContactGraphNet, GraphConfig, config_to_dict

    with pytest.raises(ValueError, match="pooled"):
        ContactGraphNet(GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, global_state=True))
    config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, pooled=True, global_state=True)
    net = ContactGraphNet(config, seed=1)
    net.variables["decode1/kernel"].assign(np.random.default_rng(0).normal(size=(8, 2)).astype(np.float32))
    x, _, e, d = graphs.batch([3, 5])
    step_of = np.repeat([0, 1], np.diff(graphs.point_offsets)[[3, 5]]).astype(np.int32)
    alone = np.concatenate([net(*graphs.batch([k])[::2], graphs.batch([k])[3]).numpy() for k in (3, 5)])
    np.testing.assert_allclose(net(x, e, d, step_of).numpy(), alone, rtol=1e-4, atol=1e-5)  # one batch, two steps
    assert config_to_dict(config)["global_state"] is True and "global_state" not in config_to_dict(
        GraphConfig(in_channels=14, pooled=True))
    row = one_network_screened(data, tmp_path, "--probes", "0", "--global-state", "--price-steps", "0")
    assert row["global_state"] is True and row["pooled"] is True
    assert "| 0 | no | a state |" in capsys.readouterr().out


def test_attention_weighs_its_steps_points_and_with_equal_weights_is_the_steps_mean(graphs, data, tmp_path, capsys):
    from training.graph_model import ContactGraphNet, GraphConfig, config_to_dict, init_weights, to_onnx

    with pytest.raises(ValueError, match="divide"):
        ContactGraphNet(GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, attention=3))
    config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, attention=2)
    rng = np.random.default_rng(0)
    weights = {k: (0.5 * rng.standard_normal(v.shape)).astype(np.float32) for k, v in init_weights(config).items()}
    net = ContactGraphNet(config, weights)
    x, _, e, d = graphs.batch([3, 5])
    step_of = np.repeat([0, 1], np.diff(graphs.point_offsets)[[3, 5]]).astype(np.int32)
    alone = np.concatenate([net(*graphs.batch([k])[::2], graphs.batch([k])[3]).numpy() for k in (3, 5)])
    np.testing.assert_allclose(net(x, e, d, step_of).numpy(), alone, rtol=1e-4, atol=1e-5)  # one batch, two steps
    # Queries and keys that match every point equally read the step's plain mean: the pooled network.
    flat = {k: (np.zeros_like(v) if "_query" in k or "_key" in k else v) for k, v in weights.items()}
    attending = ContactGraphNet(config, flat)
    x1, _, e1, d1 = graphs.batch([3])
    h = attending._dense(attending._dense(x1, "encode0"), "encode1")
    np.testing.assert_allclose(attending._attend(h, None, "round0").numpy(),
                               np.broadcast_to(attending._dense(h, "round0_value", relu=False).numpy().mean(axis=0),
                                               h.shape), rtol=1e-4, atol=1e-5)
    # Exported, it answers one step as TensorFlow does.
    import onnxruntime as ort

    session = ort.InferenceSession(to_onnx(net), providers=["CPUExecutionProvider"])
    (got,) = session.run(None, {"points": x1, "ends": e1, "dynamic": d1})
    np.testing.assert_allclose(got, net(x1, e1, d1).numpy(), rtol=1e-4, atol=1e-4)
    # Far-out inputs drive some queries' feature maps to 0 (elu + 1 underflows): the step still
    # gets finite answers, where an unguarded 0 / 0 would spread NaN to every point of it.
    (far,) = session.run(None, {"points": x1 * 1e3, "ends": e1, "dynamic": d1})
    assert np.isfinite(far).all()
    assert config.reads_whole_step and config_to_dict(config)["attention"] == 2
    assert "attention" not in config_to_dict(GraphConfig(in_channels=14))
    row = one_network_screened(data, tmp_path, "--probes", "0", "--attention", "2", "--price-steps", "0")
    assert row["attention"] == 2 and row["weights"] == sum(v.size for v in init_weights(config).values())
    assert "| 0 | no | no | 2 |" in capsys.readouterr().out
