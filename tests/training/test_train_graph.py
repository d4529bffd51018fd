"""The contact-graph model: its data, its solver loss, training and export, end to end."""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest

from commands import main
from tests.training.conftest import SMALL
from training.contact_graph import GRAPH_INPUTS, GraphSet, build_graph_set


@pytest.fixture(scope="module")
def graphs(data):
    return build_graph_set(data / "train.h5", max_steps=12)


def test_a_batch_is_the_disjoint_union_of_its_steps(graphs, tmp_path):
    assert len(graphs) == 12 and graphs.features.shape[1] == len(GRAPH_INPUTS)
    features, targets, ends, dynamic = graphs.batch([3, 5])
    n3 = graphs.point_offsets[4] - graphs.point_offsets[3]
    b3 = graphs.body_offsets[4] - graphs.body_offsets[3]
    assert len(features) == len(targets) == len(ends) == n3 + graphs.point_offsets[6] - graphs.point_offsets[5]
    assert len(dynamic) == b3 + graphs.body_offsets[6] - graphs.body_offsets[5]
    # The second step's points name the second step's bodies, moved past the first step's.
    np.testing.assert_array_equal(ends[n3:], graphs.batch([5])[2] + b3)
    assert ends.max() < len(dynamic) and dynamic[ends[:, 1], 0].all()  # body B is always dynamic here
    # Saved without pickle and read back the same.
    path = graphs.save(tmp_path / "g.npz")
    again = GraphSet.load(path)
    np.testing.assert_array_equal(again.features, graphs.features)
    assert again.inputs == graphs.inputs


@pytest.mark.parametrize("extra", [(), ("last_correction_normal",)])
def test_steps_read_many_at_a_time_give_each_steps_own_values_bit_for_bit(data, monkeypatch, extra):
    from training import contact_graph

    inputs = GRAPH_INPUTS + extra  # a temporal channel is read one step at a time
    monkeypatch.setattr(contact_graph, "STEPS_AT_ONCE", 5)  # 12 steps: 5, 5 and 2 at a time
    many = build_graph_set(data / "train.h5", inputs, max_steps=12)
    monkeypatch.setattr(contact_graph, "STEPS_AT_ONCE", 1)
    one = build_graph_set(data / "train.h5", inputs, max_steps=12)
    for name in ("features", "targets", "ends", "dynamic", "point_offsets", "body_offsets", "builtin",
                 "geometry", "masses", "inverse", "speed"):
        np.testing.assert_array_equal(getattr(many, name), getattr(one, name), err_msg=name)


def test_the_solver_loss_sees_no_error_in_the_exact_correction_and_decays_the_rest(graphs):
    import tensorflow as tf

    from training.graph_loss import apply_delassus, residuals_after

    steps = np.arange(len(graphs))
    _, targets, ends, _ = graphs.batch(steps)
    geometry, masses, inverse = graphs.solver_batch(steps)
    # diag(A) = 1 / effective mass: a unit error at one point, alone, moves it by 1/m_eff.
    unit = np.zeros_like(targets)
    unit[4, 0] = 1.0
    velocity = apply_delassus(tf.constant(unit), ends, geometry, inverse).numpy()
    assert velocity[4, 0] * masses[4, 0] == pytest.approx(1.0, rel=1e-5)
    zero = residuals_after(tf.zeros_like(targets), ends, geometry, masses, inverse, sweeps=(0, 8), omega=0.5)
    assert all(float(tf.reduce_max(tf.abs(r))) == 0.0 for r in zero)
    builtin = residuals_after(tf.constant(-targets), ends, geometry, masses, inverse, sweeps=(0, 8, 32), omega=0.5)
    sizes = [float(tf.reduce_mean(tf.square(r))) for r in builtin]
    assert sizes[0] > sizes[1] > sizes[2] > 0


def test_projected_sweeps_keep_the_limits_and_leave_the_recorded_solution_nearly_alone(graphs):
    import tensorflow as tf

    from training.graph_loss import friction_bounds, projected_changes_after, projected_sweep

    steps = np.arange(len(graphs))
    features, targets, ends, _ = graphs.batch(steps)
    geometry, masses, inverse = graphs.solver_batch(steps)
    column = {n: j for j, n in enumerate(graphs.inputs)}
    builtin = features[:, [column["builtin_normal"], column["builtin_tangent"]]]
    v_free = features[:, [column["vn"], column["vt"]]]  # m/s after gravity, before any impulse
    step_of = np.repeat(steps.astype(np.int32), np.diff(graphs.point_offsets))
    solution = tf.constant(builtin + targets)  # what the solver ended at
    mu = friction_bounds(solution, step_of)
    assert float(tf.reduce_min(mu)) >= 0.0
    # Any start, however wrong, comes out of one sweep inside the limits.
    wild = tf.constant(np.random.default_rng(0).normal(0, 5, targets.shape).astype(np.float32))
    after = projected_sweep(wild, v_free, mu, ends, geometry, masses, inverse, omega=0.5).numpy()
    assert (after[:, 0] >= 0).all() and (np.abs(after[:, 1]) <= mu.numpy() * after[:, 0] + 1e-6).all()
    # The recorded solution is a fixed point to about the solver's threshold (1e-4 N s);
    # Box2D's warm start is not.
    kept = projected_changes_after(solution, v_free, mu, ends, geometry, masses, inverse, sweeps=(0,), omega=0.5)[0]
    moved = projected_changes_after(tf.constant(builtin), v_free, mu, ends, geometry, masses, inverse, sweeps=(0,),
                                    omega=0.5)[0]
    assert float(tf.reduce_max(tf.abs(kept))) < 0.01 < float(tf.reduce_max(tf.abs(moved)))


def test_a_reflected_step_is_solved_as_the_reflection_of_the_step(graphs):
    # --mirror-augment's reflection (Scaling.batch(reflect=...)) is the same problem seen in a
    # mirror: the solver's sweeps from reflected impulses end at the reflected impulses.
    import tensorflow as tf

    from training.graph_loss import friction_bounds, projected_changes_after
    from training.train_graph import Scaling

    zero = (np.zeros(len(graphs.inputs), np.float32), np.ones(len(graphs.inputs), np.float32),
            np.zeros(2, np.float32), np.ones(2, np.float32))
    scaling = Scaling(*zero)  # no normalization: raw values in, raw values out
    steps = np.arange(len(graphs))
    column = {n: j for j, n in enumerate(graphs.inputs)}
    swept = []
    for reflect in (np.zeros(len(steps), bool), np.ones(len(steps), bool)):
        features, ends, _, targets, geometry, masses, inverse, step_of, _, _ = scaling.batch(graphs, steps,
                                                                                            reflect=reflect)
        builtin = features[:, [column["builtin_normal"], column["builtin_tangent"]]]
        v_free = features[:, [column["vn"], column["vt"]]]
        mu = friction_bounds(tf.constant(builtin + targets), step_of)
        swept.append(projected_changes_after(tf.constant(builtin), v_free, mu, ends, geometry, masses, inverse,
                                             sweeps=(4,), omega=0.5)[0].numpy())
        if reflect.all():
            plain = scaling.batch(graphs, steps)
            np.testing.assert_array_equal(targets[:, 1], -plain[3][:, 1])  # the tangent's sign changes
            np.testing.assert_array_equal(features[:, column["normal_y"]], plain[0][:, column["normal_y"]])
    assert np.abs(swept[0]).max() > 0.01  # Box2D's warm start is not where the sweeps end
    np.testing.assert_allclose(swept[1], swept[0] * [1.0, -1.0], atol=1e-5)


def test_a_symmetric_network_answers_a_reflected_step_with_the_reflection_of_its_answer(graphs):
    # --symmetric scores the mean of the network's answer and its mirror image's, so the answer
    # trained is the one `training.ensemble --mirror` serves: reflection-equivariant, whatever
    # the weights and the normalization.
    import argparse

    from deepcontact.channels import mirror_signs
    from training.graph_model import GraphConfig
    from training.train_graph import BatchLoss, Scaling

    rng = np.random.default_rng(5)
    n_in, n_out = len(graphs.inputs), len(graphs.target_names)
    scaling = Scaling(rng.normal(size=n_in).astype(np.float32), rng.uniform(0.5, 2, n_in).astype(np.float32),
                      rng.normal(size=n_out).astype(np.float32), rng.uniform(0.5, 2, n_out).astype(np.float32))
    net = _random_net(GraphConfig(in_channels=n_in, out_channels=n_out, width=8, rounds=2), rng)
    steps = np.arange(len(graphs))
    answers = {}
    for symmetric in (False, True):
        loss = BatchLoss(net, argparse.Namespace(loss="mse", tangent_weight=1.0, combine="residual",
                                                 symmetric=symmetric),
                         scaling, [], graphs.inputs, graphs.target_names)
        for reflect in (False, True):
            points, ends, dynamic, *_, step_of, _, _ = scaling.batch(graphs, steps,
                                                                     reflect=np.full(len(steps), reflect))
            normalized = np.asarray(loss.predict(points, ends, dynamic, step_of))
            answers[symmetric, reflect] = normalized * scaling.out_std + scaling.out_mean  # (P, 2) N s
    mirror = mirror_signs(graphs.target_names)
    np.testing.assert_allclose(answers[True, True], answers[True, False] * mirror, rtol=1e-4, atol=1e-4)
    # The network alone is not symmetric: the check above is not met by chance.
    assert np.abs(answers[False, True] - answers[False, False] * mirror).max() > 0.1


def test_the_self_stress_part_of_an_error_moves_no_body_and_leaves_a_body_motion_out(graphs):
    # The loss's split (TensorFlow, conjugate gradients) agrees with the engine-side one
    # (deepcontact.kinematics): a self-stress moves no body, and the impulses of a pure
    # body motion have none.
    import tensorflow as tf

    from training.graph_loss import _body_velocities, _relative_velocities, self_stress_part

    steps = np.arange(len(graphs))
    _, targets, ends, _ = graphs.batch(steps)
    geometry, masses, inverse = graphs.solver_batch(steps)
    dynamic = (inverse > 0).astype(np.float32)

    def moves(lam):  # |J^T lam|
        force, torque = _body_velocities(tf.constant(lam, tf.float32), ends, geometry, dynamic)
        return float(np.sqrt(np.sum(force.numpy() ** 2) + np.sum(torque.numpy() ** 2)))

    stress = self_stress_part(tf.constant(targets), ends, geometry, inverse, iterations=160).numpy()
    assert 0.0 < np.linalg.norm(stress) < np.linalg.norm(targets)
    assert moves(stress) < 0.02 * moves(targets)
    rng = np.random.default_rng(0)
    body = _relative_velocities(tf.constant(rng.normal(size=(len(inverse), 2)).astype(np.float32) * dynamic),
                                tf.constant(rng.normal(size=len(inverse)).astype(np.float32) * dynamic[:, 1]),
                                ends, geometry).numpy()  # J y: impulses that are all body motion
    left = self_stress_part(tf.constant(body), ends, geometry, inverse, iterations=160).numpy()
    assert np.linalg.norm(left) < 0.02 * np.linalg.norm(body)


def test_a_colour_holds_no_two_points_on_one_moving_body():
    from training.graph_loss import MAX_COLOURS, colour_points

    # Bodies 0-3 move, body 4 is the ground (static): the points on the ground share it freely.
    ends = np.array([[4, 0], [4, 1], [4, 2], [0, 1], [1, 2], [2, 3], [0, 3]], np.int32)
    inverse = np.array([[1.0, 2.0]] * 4 + [[0.0, 0.0]], np.float32)
    colour = colour_points(ends, inverse)
    moving = inverse.any(axis=1)
    for c in np.unique(colour):
        bodies = ends[colour == c].ravel()
        bodies = bodies[moving[bodies]]
        assert len(bodies) == len(np.unique(bodies))
    assert np.array_equal(colour, colour_points(ends, inverse))  # seeded: the same batch, the same colours
    # A body touched by more points than there are colours cannot be coloured, and says so.
    star = np.stack([np.zeros(MAX_COLOURS + 1, np.int32), np.arange(1, MAX_COLOURS + 2, dtype=np.int32)], axis=1)
    with pytest.raises(ValueError, match="colours"):
        colour_points(star, np.ones((MAX_COLOURS + 2, 2), np.float32))


def test_gauss_seidel_sweeps_update_one_point_after_another(graphs):
    """A colour updated at once equals its points updated one by one, each seeing the last."""
    import tensorflow as tf

    from training.graph_loss import colour_points, friction_bounds, gauss_seidel_changes_after

    steps = np.arange(len(graphs))
    features, targets, ends, _ = graphs.batch(steps)
    geometry, masses, inverse = graphs.solver_batch(steps)
    column = {n: j for j, n in enumerate(graphs.inputs)}
    builtin = features[:, [column["builtin_normal"], column["builtin_tangent"]]].astype(np.float64)
    v_free = features[:, [column["vn"], column["vt"]]]
    step_of = np.repeat(steps.astype(np.int32), np.diff(graphs.point_offsets))
    mu = friction_bounds(tf.constant(builtin + targets, tf.float32), step_of).numpy()
    colour = colour_points(ends, inverse)

    def point_by_point(lam, sweeps):  # the solver's loop, in colour order, in float64
        lam = lam.copy()
        v = np.zeros((len(inverse), 3))  # per body: vx, vy, w from the impulses so far
        n, t, r = geometry[:, 0:2], geometry[:, 2:4], (geometry[:, 4:6], geometry[:, 6:8])

        def push(p, d):
            impulse = d[0] * n[p] + d[1] * t[p]
            for end, sign in ((0, -1.0), (1, 1.0)):
                body, rr = ends[p, end], r[end][p]
                v[body, :2] += sign * impulse * inverse[body, 0]
                v[body, 2] += sign * (rr[0] * impulse[1] - rr[1] * impulse[0]) * inverse[body, 1]

        for p in range(len(lam)):
            push(p, lam[p])
        for _ in range(sweeps):
            for p in np.argsort(colour, kind="stable"):
                rel = np.zeros(2)
                for end, sign in ((0, -1.0), (1, 1.0)):
                    body, rr = ends[p, end], r[end][p]
                    rel += sign * (v[body, :2] + v[body, 2] * np.array([-rr[1], rr[0]]))
                step = lam[p] - masses[p] * (v_free[p] + [rel @ n[p], rel @ t[p]])
                normal = max(step[0], 0.0)
                new = np.array([normal, np.clip(step[1], -mu[p] * normal, mu[p] * normal)])
                push(p, new - lam[p])
                lam[p] = new
        return lam

    change = gauss_seidel_changes_after(tf.constant(builtin, tf.float32), v_free, mu, ends, geometry, masses,
                                        inverse, colour, sweeps=(2,))[0].numpy()
    expected = point_by_point(builtin, 3) - point_by_point(builtin, 2)
    assert np.abs(expected).max() > 1e-3
    np.testing.assert_allclose(change, expected, atol=1e-4 * np.abs(expected).max())


@pytest.mark.parametrize("loss", ["mse", "relative", "mse-self-stress", "mse-sticking", "mse-moving", "relative-moving",
                                  "solver", "solver-log",
                                  "solver-projected",
                                  "solver-projected-max", "solver-projected-sweeps"])
def test_train_graph_writes_a_model_that_onnx_runtime_runs_like_tensorflow(data, tmp_path, loss):
    out = tmp_path / "graph.onnx"
    order = "gauss-seidel" if loss == "solver-projected-max" else "jacobi"  # the one loss offered in both orders
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--epochs", "2", "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", loss,
                 "--sweeps", "0,4", "--order", order, "--self-stress-iterations", "8",
                 "--cache", str(tmp_path / "cache"), "--quiet"]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["kind"] == "graph" and card["combine"] == "residual" and card["input_name"] == "points"
    assert card["parity_max_abs_error"] < 1e-4
    if loss in ("solver-log", "solver-projected-max", "solver-projected-sweeps"):  # per step, log(model's / Box2D's)
        assert card["validation"]["loss_no_correction"] == 0.0 and abs(card["validation"]["loss"]) < 1.0
    else:
        assert card["validation"]["loss"] <= card["validation"]["loss_no_correction"] * 1.5
    assert card["training"]["settings"]["loss"] == loss and card["training"]["epochs_run"] == 2
    assert card["training"]["settings"]["order"] == order
    assert ("self_stress_weight" in card["training"]["settings"]) == (loss == "mse-self-stress")
    assert card["training"]["settings"]["omega"] == (1.0 if order == "gauss-seidel" else 0.5)
    assert {"cpu", "vector", "cores"} <= set(card["training"]["machine"])  # what a rebuild is checked against
    assert set(card["gridspec"]["normalization"]) == set(GRAPH_INPUTS) | {"correction_normal", "correction_tangent"}
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["points", "ends", "dynamic"]


def test_train_graph_refuses_what_it_cannot_use(data, tmp_path, capsys):
    base = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5")]
    assert main(base + ["--out", str(tmp_path / "m.json")]) == 2
    assert "must name a .onnx file" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--sweeps", "many"]) == 2
    assert "--sweeps" in capsys.readouterr().err
    assert main(["train-graph", "--train", str(tmp_path / "none.h5"), "--val", str(data / "val.h5"),
                 "--out", str(tmp_path / "m.onnx")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--attention", "3"]) == 2  # heads split the width, 32
    assert "--attention" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--omega", "1.5"]) == 2
    assert "--omega" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--omega", "1"]) == 2  # Jacobi's diverge undamped
    assert "--omega" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--loss", "mse", "--order", "gauss-seidel"]) == 2
    assert "--order gauss-seidel" in capsys.readouterr().err
    assert main(base + ["--out", str(tmp_path / "m.onnx"), "--loss", "solver-projected-sweeps", "--sweeps", "64"]) == 2
    assert "two or more" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # a 16-norm underflows float32: not offered
        main(base + ["--out", str(tmp_path / "m.onnx"), "--loss", "solver-projected-max", "--norm", "16"])
    assert "--norm" in capsys.readouterr().err


def test_oracle_targets_fit_the_correction_to_the_converged_solve(data, tmp_path, capsys):
    common = ["--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "1", "--loss", "mse",
              "--cache", str(tmp_path / "cache"), "--quiet", "--targets", "oracle"]
    out = tmp_path / "oracle.onnx"
    assert main(["train-graph", "--train", str(data / "train-oracle.h5"), "--val", str(data / "val-oracle.h5"),
                 "--out", str(out), *common]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["gridspec"]["targets"] == ["oracle_correction_normal", "oracle_correction_tangent"]
    assert card["combine"] == "residual"  # served as Builtin + the correction, like any residual model
    # A file recorded without the oracle cannot give these targets, and says how to get them.
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val-oracle.h5"),
                 "--out", str(tmp_path / "none.onnx"), *common]) == 2
    assert "--oracle" in capsys.readouterr().err
    assert not (tmp_path / "none.onnx").exists()


def test_face_targets_train_a_classifier_of_the_points_served_as_a_residual(data, tmp_path):
    out = tmp_path / "face.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "1", "--loss", "mse",
                 "--cache", str(tmp_path / "cache"), "--quiet", "--targets", "face"]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["gridspec"]["targets"] == ["face_correction_normal", "face_correction_tangent"]
    assert card["combine"] == "residual"  # Builtin + the model's answer: the labels, written as impulses


def test_scaled_inputs_and_face_labels_train_a_classifier_served_as_it_answers(data, tmp_path, capsys):
    from deepcontact.modelcard import ModelCard
    from server.predictors import GraphPredictor
    from training.contact_graph import SCALED_GRAPH_INPUTS

    out = tmp_path / "labels.onnx"
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--width", "8", "--rounds", "1", "--loss", "mse", "--cache", str(tmp_path / "cache"),
              "--quiet", "--inputs", "scaled", "--targets", "face-labels"]
    assert main(common + ["--out", str(tmp_path / "residual.onnx")]) == 2  # labels are not a correction
    assert "--combine replace" in capsys.readouterr().err and not (tmp_path / "residual.onnx").exists()
    assert main(common + ["--combine", "replace", "--out", str(out)]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    assert card["gridspec"]["inputs"] == list(SCALED_GRAPH_INPUTS) and card["combine"] == "replace"
    assert card["gridspec"]["targets"] == ["face_normal", "face_tangent"]
    assert card["training"]["settings"]["inputs"] == "scaled"
    # Served: the physics a request declares is read for the scales, and the answer is the labels'.
    predictor = GraphPredictor(ModelCard.load(out.with_suffix(".json")), out)
    assert "physics" in predictor.requires


def test_a_run_goes_on_from_an_earlier_runs_weights(data, tmp_path, capsys):
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--rounds", "1", "--loss", "mse", "--cache", str(tmp_path / "cache"), "--quiet"]
    assert main(common + ["--width", "8", "--out", str(tmp_path / "first.onnx")]) == 0
    weights = tmp_path / "cache" / "first.weights.npz"
    first = json.loads((tmp_path / "first.json").read_text())
    assert main(common + ["--width", "8", "--out", str(tmp_path / "more.onnx"), "--init", str(weights),
                          "--lr", "1e-12"]) == 0
    more = json.loads((tmp_path / "more.json").read_text())
    assert more["training"]["init"] == str(weights)
    # With a learning rate of nothing the weights stay the first run's, and so does the loss.
    assert more["validation"]["loss"] == pytest.approx(first["validation"]["loss"], rel=1e-4)
    capsys.readouterr()
    assert main(common + ["--width", "16", "--out", str(tmp_path / "wide.onnx"), "--init", str(weights)]) == 2
    assert "another network" in capsys.readouterr().err
    assert not (tmp_path / "wide.onnx").exists()


def test_a_network_with_a_body_state_is_exported_and_goes_on_only_from_a_network_that_has_one(data, tmp_path, capsys):
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse", "--cache", str(tmp_path / "cache"),
              "--quiet"]
    assert main(common + ["--body-state", "--out", str(tmp_path / "kept.onnx")]) == 0
    card = json.loads((tmp_path / "kept.json").read_text())
    assert card["architecture"]["config"]["body_state"] is True and card["parity_max_abs_error"] < 1e-4
    assert main(common + ["--body-state", "--out", str(tmp_path / "more.onnx"),
                          "--init", str(tmp_path / "cache" / "kept.weights.npz")]) == 0
    assert main(common + ["--out", str(tmp_path / "plain.onnx")]) == 0
    capsys.readouterr()
    assert main(common + ["--body-state", "--out", str(tmp_path / "grown.onnx"),
                          "--init", str(tmp_path / "cache" / "plain.weights.npz")]) == 2
    assert "--body-state" in capsys.readouterr().err
    assert not (tmp_path / "grown.onnx").exists()


def test_a_body_state_read_beside_the_sums_grows_from_a_plain_network_as_exactly_that_network(data, tmp_path):
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse", "--cache", str(tmp_path / "cache"),
              "--quiet"]
    assert main(common + ["--out", str(tmp_path / "plain.onnx")]) == 0
    # With a learning rate of nothing the grown network stays where it starts: the plain one.
    assert main(common + ["--body-state", "sums", "--out", str(tmp_path / "grown.onnx"), "--lr", "1e-12",
                          "--init", str(tmp_path / "cache" / "plain.weights.npz")]) == 0
    plain, grown = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("plain", "grown"))
    assert grown["architecture"]["config"]["body_plus_sums"] is True and grown["parity_max_abs_error"] < 1e-4
    assert grown["validation"]["loss"] == pytest.approx(plain["validation"]["loss"], rel=1e-4)
    assert grown["parameters"] == plain["parameters"] + 2 * ((2 * 8 * 8 + 8) + (8 * 8 + 8))


def test_a_pooled_network_starts_as_the_plain_one_and_pools_each_step_alone(graphs, data, tmp_path):
    from training.graph_model import ContactGraphNet, GraphConfig, init_weights

    plain_config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2)
    pooled_config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, pooled=True)
    plain = init_weights(plain_config, seed=1)
    plain["decode1/kernel"] = np.random.default_rng(2).normal(size=plain["decode1/kernel"].shape).astype(np.float32)
    weights_file = tmp_path / "plain.weights.npz"
    np.savez(weights_file, **plain)
    from training.train_graph import initial_weights
    padded = initial_weights(weights_file, pooled_config)  # zero rows for the summary
    x, _, e, d = graphs.batch([3, 5])
    n3 = graphs.point_offsets[4] - graphs.point_offsets[3]
    step_of = np.repeat(np.int32([0, 1]), [n3, len(x) - n3]).astype(np.int32)
    np.testing.assert_allclose(ContactGraphNet(pooled_config, padded)(x, e, d, step_of).numpy(),
                               ContactGraphNet(plain_config, plain)(x, e, d).numpy(), rtol=1e-5, atol=1e-6)
    # With weights on the summary, a batch of two steps gives each step what it gets alone,
    # as the server runs it (one step, no step_of).
    trained = init_weights(pooled_config, seed=3)
    trained["decode1/kernel"] = plain["decode1/kernel"]
    net = ContactGraphNet(pooled_config, trained)
    together = net(x, e, d, step_of).numpy()
    x5, _, e5, d5 = graphs.batch([5])
    np.testing.assert_allclose(together[n3:], net(x5, e5, d5).numpy(), rtol=1e-4, atol=1e-5)
    assert not np.allclose(together[:n3], ContactGraphNet(plain_config, plain)(x, e, d).numpy()[:n3], atol=1e-3)


def test_a_network_grown_by_rounds_starts_as_the_one_it_grew_from_and_cut_back_is_it_again(graphs, tmp_path):
    from training.graph_model import ContactGraphNet, GraphConfig, init_weights
    from training.train_graph import initial_weights

    small_config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2)
    deep_config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=4)
    small = init_weights(small_config, seed=1)
    small["decode1/kernel"] = np.random.default_rng(2).normal(size=small["decode1/kernel"].shape).astype(np.float32)
    np.savez(tmp_path / "small.weights.npz", **small)
    grown = initial_weights(tmp_path / "small.weights.npz", deep_config)
    assert set(grown) == set(init_weights(deep_config))
    assert not grown["round3_update1/kernel"].any() and grown["round3_to_a/kernel"].any()  # a pass-through that learns
    x, _, e, d = graphs.batch([3, 5])
    np.testing.assert_allclose(ContactGraphNet(deep_config, grown)(x, e, d).numpy(),
                               ContactGraphNet(small_config, small)(x, e, d).numpy(), rtol=1e-6, atol=1e-6)
    # Fewer rounds than the weights hold keeps their first ones: here exactly the network it grew from.
    np.savez(tmp_path / "deep.weights.npz", **grown)
    cut = initial_weights(tmp_path / "deep.weights.npz", small_config)
    assert set(cut) == set(small) and all(np.array_equal(cut[k], small[k]) for k in small)
    # Another width is another network.
    with pytest.raises(ValueError, match="another network"):
        initial_weights(tmp_path / "deep.weights.npz", GraphConfig(in_channels=len(GRAPH_INPUTS), width=16, rounds=2))


def test_train_graph_pooled_from_a_plain_run_exports_a_model_onnx_runtime_runs_like_tensorflow(data, tmp_path):
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--rounds", "1", "--width", "8", "--loss", "mse", "--cache",
              str(tmp_path / "cache"), "--quiet"]
    assert main(common + ["--out", str(tmp_path / "plain.onnx")]) == 0
    assert main(common + ["--out", str(tmp_path / "pooled.onnx"), "--pooled", "--init",
                          str(tmp_path / "cache" / "plain.weights.npz")]) == 0
    card = json.loads((tmp_path / "pooled.json").read_text())
    assert card["architecture"]["config"]["pooled"] is True and card["parity_max_abs_error"] < 1e-4
    session = ort.InferenceSession(str(tmp_path / "pooled.onnx"), providers=["CPUExecutionProvider"])
    assert {i.name for i in session.get_inputs()} == {"points", "ends", "dynamic"}  # served as any graph model


def test_train_graph_with_layer_norms_exports_them_and_will_not_start_from_a_network_without(data, tmp_path,
                                                                                            capsys):
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--rounds", "2", "--width", "8", "--loss", "mse", "--cache",
              str(tmp_path / "cache"), "--quiet"]
    assert main(common + ["--out", str(tmp_path / "normed.onnx"), "--layer-norm"]) == 0
    card = json.loads((tmp_path / "normed.json").read_text())
    assert card["architecture"]["config"]["layer_norm"] is True and card["parity_max_abs_error"] < 1e-4
    assert card["training"]["settings"]["layer_norm"] is True
    assert main(common + ["--out", str(tmp_path / "plain.onnx")]) == 0
    # A plain network's function changes under a normalization: refused, not silently grown.
    assert main(common + ["--out", str(tmp_path / "grown.onnx"), "--layer-norm", "--init",
                          str(tmp_path / "cache" / "plain.weights.npz")]) != 0
    assert "--layer-norm" in capsys.readouterr().err
    assert not (tmp_path / "grown.onnx").exists()


def test_a_diverging_run_says_so_and_writes_nothing(data, tmp_path, capsys):
    out = tmp_path / "m.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "1", "--loss", "mse",
                 "--lr", "1e30", "--cache", str(tmp_path / "cache"), "--quiet"]) == 1
    assert "training loss became" in capsys.readouterr().err
    assert not out.exists() and not out.with_suffix(".json").exists()


@pytest.fixture(scope="module")
def graph_models(data, tmp_path_factory):
    """A model folder with one small trained graph model, `graph` (residual)."""
    folder = tmp_path_factory.mktemp("graph-models")
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
                 "--out", str(folder / "graph.onnx"), "--epochs", "1", "--batch-size", "4", "--width", "8",
                 "--rounds", "2", "--loss", "mse", "--cache", str(folder.parent / "graph-cache"), "--quiet"]) == 0
    return folder


@pytest.mark.parametrize("batch_max", [0, 4])
def test_a_served_graph_model_is_the_model_on_the_engines_own_records(graph_models, thesis_steps, batch_max):
    # Over a real gRPC server the request's decoded records (walls folded into one
    # static body) give the same point channels, and so the same warm start, as the
    # engine's records fed to the model by hand. Micro-batching stacks grids, so a
    # server that batches serves graph models directly.
    import grpc

    from deepcontact import wire
    from deepcontact.channels import Step, channel_values
    from deepcontact.kinematics import Physics
    from deepcontact.modelcard import ModelCard
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server

    folder = graph_models
    card = ModelCard.load(folder / "graph.json")
    spec = card.gridspec
    mean_in, std_in = spec.normalization_arrays(spec.inputs)
    mean_out, std_out = spec.normalization_arrays(spec.targets)
    session = ort.InferenceSession(str(folder / "graph.onnx"), providers=["CPUExecutionProvider"])
    world, steps = thesis_steps
    server = Server(models=folder, batch_max=batch_max).start()
    try:
        assert not server.batchers  # nothing to batch
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            requests = [wire.encode_step(k, "graph", bodies, points, world=world if k == 0 else None,
                                         builtin=points["builtin"]) for k, (bodies, points) in enumerate(steps)]
            replies = list(stub.Stream(iter(requests)))
    finally:
        server.stop()
    for (bodies, points), reply in zip(steps, replies):
        x = (channel_values(spec.inputs, Step(bodies, points, None, Physics.thesis())) - mean_in) / std_in
        ends = np.stack([points["body_a"], points["body_b"]], axis=1).astype(np.int32)
        dynamic = (bodies["type"] == 2).astype(np.float32)[:, None]
        y = session.run(["impulses"], {"points": x.astype(np.float32), "ends": ends, "dynamic": dynamic})[0]
        expected = points["builtin"] + (y * std_out + mean_out)
        np.testing.assert_allclose(np.stack(wire.decode_impulses(reply), axis=1), expected, atol=2e-4, rtol=1e-4)


def test_a_moving_card_serves_builtin_on_a_pile_at_rest_and_the_model_elsewhere(graph_models, thesis_steps,
                                                                                tmp_path):
    import shutil

    import grpc

    from deepcontact import wire
    from deepcontact.kinematics import points_at_rest
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server
    from training.card_variant import card_variant

    folder = tmp_path / "models"
    shutil.copytree(graph_models, folder)
    card_variant(folder / "graph.json", combine="moving")
    world, steps = thesis_steps
    server = Server(models=folder).start()
    try:
        with grpc.insecure_channel(server.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            served = {name: [np.stack(wire.decode_impulses(stub.Predict(
                wire.encode_step(k, name, bodies, points, world=world, builtin=points["builtin"]))), axis=1)
                for k, (bodies, points) in enumerate(steps)] for name in ("graph", "graph-moving")}
    finally:
        server.stop()
    rest = [points_at_rest(bodies, points) for bodies, points in steps]
    assert 0 < sum(r.sum() for r in rest) < sum(len(r) for r in rest)  # a settled pile, some of it still moving
    for (bodies, points), at_rest, plain, moving in zip(steps, rest, served["graph"], served["graph-moving"]):
        np.testing.assert_array_equal(moving[at_rest], points["builtin"][at_rest])
        np.testing.assert_array_equal(moving[~at_rest], plain[~at_rest])


def test_a_graph_model_refuses_requests_without_the_points_bodies(graph_models, thesis_steps):
    import grpc

    from deepcontact import wire
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server

    world, steps = thesis_steps
    bodies, points = steps[0]
    request = wire.encode_step(0, "graph", bodies, points, world=world, builtin=points["builtin"])
    request.ClearField("point_bodies")
    server = Server(models=graph_models).start()
    try:
        with grpc.insecure_channel(server.address) as channel:
            with pytest.raises(grpc.RpcError) as err:
                pb_grpc.WarmStartStub(channel).Predict(request)
    finally:
        server.stop()
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "each point's two bodies" in err.value.details()


def test_a_run_stopped_mid_epoch_and_resumed_reaches_the_weights_of_one_never_stopped(data, tmp_path, monkeypatch,
                                                                                      capsys):
    from training import train_graph

    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "3",
              "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse", "--mirror-augment",
              "--cache", str(tmp_path / "cache"), "--quiet"]
    assert main(common + ["--out", str(tmp_path / "whole.onnx")]) == 0

    class Killed(Exception):
        pass

    # Killed in the second epoch, after one of its updates: that update is lost, epoch 1 is not.
    saved, batches = [], []
    save_state, batch = train_graph._save_state, train_graph.Scaling.batch
    monkeypatch.setattr(train_graph, "_save_state", lambda *a: (save_state(*a), saved.append(a[6])))
    def batch_until_killed(self, *a, **k):
        if saved:
            batches.append(1)
            if len(batches) == 2:
                raise Killed
        return batch(self, *a, **k)
    monkeypatch.setattr(train_graph.Scaling, "batch", batch_until_killed)
    state = tmp_path / "resume" / "run.state.npz"
    run = common + ["--out", str(tmp_path / "resumed.onnx"), "--resume", str(state)]
    with pytest.raises(Killed):
        main(run)
    assert saved == [1] and state.exists() and not (tmp_path / "resumed.onnx").exists()
    monkeypatch.undo()

    # Started again with other arguments, it says which and leaves the state alone.
    assert main([a if a != "mse" else "relative" for a in run]) == 2
    assert "--loss 'mse' there" in capsys.readouterr().err and state.exists()

    assert main(run) == 0
    whole, resumed = (np.load(tmp_path / "cache" / f"{n}.weights.npz") for n in ("whole", "resumed"))
    assert whole.files == resumed.files
    for k in whole.files:
        np.testing.assert_array_equal(resumed[k], whole[k], err_msg=k)
    cards = [json.loads((tmp_path / f"{n}.json").read_text())["training"] for n in ("whole", "resumed")]
    assert cards[1]["history"] == cards[0]["history"] and cards[1]["resumed_after_epochs"] == [1]
    assert not state.exists()  # done: the same command now starts a new run


def test_every_epoch_is_kept_as_a_model_that_lab_iterations_prices_on_builtins_states(data, tmp_path):
    checkpoints = tmp_path / "epochs"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
                 "--out", str(tmp_path / "g.onnx"), "--epochs", "2", "--batch-size", "4", "--width", "8",
                 "--rounds", "1", "--loss", "mse", "--cache", str(tmp_path / "cache"),
                 "--checkpoints", str(checkpoints), "--quiet"]) == 0
    final = json.loads((tmp_path / "g.json").read_text())
    cards = [json.loads((checkpoints / f"g-e{k}.json").read_text()) for k in (1, 2)]
    assert [c["training"]["epoch"] for c in cards] == [1, 2] and cards[1]["training"]["checkpoint_of"] == "g"
    assert [c["validation"]["loss"] for c in cards] == [h[2] for h in final["training"]["history"]]
    best = cards[final["validation"]["epoch"] - 1]
    assert best["validation"]["loss"] == pytest.approx(final["validation"]["loss"])
    # The folder is a models folder: both epochs priced, in one run, on the same (Builtin's) states;
    # server:* names every model the server serves.
    out = tmp_path / "priced"
    assert main(["lab", "iterations", "--models", str(checkpoints), "--seeds", "901", "--steps", "20",
                 "--warm-starts", "builtin,price:server:*", "--deadline-ms", "1000",
                 "--out", str(out), "--quiet"]) == 0
    priced = json.loads((out / "summary.json").read_text())["picks"]["price:server:g-e1+server:g-e2"]
    assert priced["candidates"] == ["builtin", "server:g-e1", "server:g-e2"]
    assert priced["trajectory"]["value"] == 1.0 and all(r["value"] > 0 for r in priced["over_builtin"])


def test_the_max_loss_takes_other_norms_harm_weights_and_symmetry_and_the_card_says_which(data, tmp_path, capsys):
    out = tmp_path / "g.onnx"
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
              "--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "1", "--sweeps", "0,4",
              "--loss", "solver-projected-max", "--cache", str(tmp_path / "cache"), "--quiet"]
    assert main(common + ["--norm", "2", "--harm-weight", "3", "--symmetric"]) == 0
    card = json.loads(out.with_suffix(".json").read_text())
    settings = card["training"]["settings"]
    assert settings["norm"] == 2 and settings["harm_weight"] == 3.0 and np.isfinite(card["validation"]["loss"])
    assert settings["symmetric"] is True  # to be served mirrored, as it was trained
    assert main(common + ["--harm-weight", "0"]) == 2
    assert "--harm-weight" in capsys.readouterr().err


def test_a_network_given_more_inputs_starts_as_the_one_it_grew_from(graphs, tmp_path):
    from training.graph_model import ContactGraphNet, GraphConfig, init_weights
    from training.train_graph import initial_weights

    small_config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2)
    wide_config = GraphConfig(in_channels=len(GRAPH_INPUTS) + 2, width=8, rounds=2)
    small = init_weights(small_config, seed=1)
    small["decode1/kernel"] = np.random.default_rng(2).normal(size=small["decode1/kernel"].shape).astype(np.float32)
    np.savez(tmp_path / "small.weights.npz", **small)
    grown = initial_weights(tmp_path / "small.weights.npz", wide_config)
    assert not grown["encode0/kernel"][-2:].any()  # the new inputs' rows start at 0
    x, _, e, d = graphs.batch([3, 5])
    extra = np.random.default_rng(3).normal(size=(len(x), 2)).astype(np.float32)
    np.testing.assert_allclose(ContactGraphNet(wide_config, grown)(np.hstack([x, extra]), e, d).numpy(),
                               ContactGraphNet(small_config, small)(x, e, d).numpy(), rtol=1e-6, atol=1e-6)


def test_a_model_reading_last_steps_correction_is_served_what_training_saw(data, tmp_path, thesis_steps, capsys):
    import grpc

    from deepcontact import wire
    from deepcontact.channels import Step, channel_values
    from deepcontact.gridspec import GridSpec
    from deepcontact.kinematics import BODY_DYNAMIC, Physics
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server

    extra = "last_correction_normal,last_correction_tangent"
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--rounds", "1", "--width", "8", "--loss", "mse", "--cache",
              str(tmp_path / "cache"), "--quiet"]
    models = tmp_path / "models"
    assert main(common + ["--out", str(models / "last.onnx"), "--extra-inputs", extra]) == 0
    card = json.loads((models / "last.json").read_text())
    assert card["gridspec"]["inputs"][-2:] == extra.split(",")
    assert card["training"]["settings"]["extra_inputs"] == extra
    # A channel of the bodies, or one read already, is refused with the list of what it reads.
    for bad in ("mass", "vn", "nope"):
        assert main(common + ["--out", str(tmp_path / "bad.onnx"), "--extra-inputs", bad]) == 2
        assert "--extra-inputs" in capsys.readouterr().err

    world, steps = thesis_steps
    srv = Server(models=models).start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            requests = [wire.encode_step(k, "last", b, p, world=world if k == 0 else None, builtin=p["builtin"])
                        for k, (b, p) in enumerate(steps[:2])]
            replies = list(stub.Stream(iter(requests)))
            # The second step is served with the first one's points, matched by key.
            decoded = [wire.decode_step(r, max_bodies=10**4, max_points=10**5) for r in requests]
            (bodies, points), (_, first) = decoded[1], decoded[0]
            spec = GridSpec.from_dict(card["gridspec"])
            mean, std = spec.normalization_arrays(spec.inputs)
            x = (channel_values(spec.inputs, Step(bodies, points, first, Physics.thesis())) - mean) / std
            assert np.abs(x[:, -2:]).max() > 0  # the points carried their keys
            ends = np.stack([points["body_a"], points["body_b"]], axis=1).astype(np.int32)
            dynamic = (bodies["type"] == BODY_DYNAMIC).astype(np.float32)[:, None]
            session = ort.InferenceSession(str(models / "last.onnx"), providers=["CPUExecutionProvider"])
            y = session.run(None, {"points": x.astype(np.float32), "ends": ends, "dynamic": dynamic})[0]
            mo, so = spec.normalization_arrays(spec.targets)
            np.testing.assert_allclose(np.stack(wire.decode_impulses(replies[1]), 1), y * so + mo + points["builtin"],
                                       rtol=1e-4, atol=1e-5)
            # A client that does not send the keys is told so.
            old = wire.encode_step(0, "last", *steps[0], world=world, builtin=steps[0][1]["builtin"])
            old.ClearField("point_keys")
            with pytest.raises(grpc.RpcError) as err:
                stub.Predict(old)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "keys" in err.value.details()
    finally:
        srv.stop()


def test_a_model_reading_the_friction_is_served_the_requests_friction_and_refuses_requests_without(
        data, tmp_path, thesis_steps):
    # The records carry no friction: training reads it off the seed's scene (training.grids),
    # the server off the request's point_friction (what the simulation client always sends).
    import grpc

    from deepcontact import wire
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.predictors import World, load_model
    from server.serve import Server

    models = tmp_path / "models"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out",
                 str(models / "rubs.onnx"), "--cache", str(tmp_path / "cache"), "--extra-inputs", "friction",
                 "--targets", "face", *SMALL]) == 0
    card = json.loads((models / "rubs.json").read_text())
    assert card["gridspec"]["inputs"][-1] == "friction"
    assert card["gridspec"]["normalization"]["friction"]["mean"] == pytest.approx(0.5)  # the thesis world's
    world_msg, steps = thesis_steps
    bodies, points = steps[0]
    lower, upper, _ = wire.decode_world(world_msg)
    world = World((lower, upper), wire.decode_physics(world_msg))
    mu = np.full(len(points), 0.5, np.float32)
    local = load_model(models / "rubs.json")
    assert "point_friction" in local.requires
    srv = Server(models=models).start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            for friction in (mu, 2 * mu):
                reply = stub.Predict(wire.encode_step(0, "rubs", bodies, points, world=world_msg,
                                                      builtin=points["builtin"], friction=friction))
                sent = wire.decode_step(wire.encode_step(0, "rubs", bodies, points, builtin=points["builtin"]),
                                        max_bodies=10**4, max_points=10**5)
                want = local.predict(*sent, world, 0, friction=friction.astype(np.float64)).impulses
                np.testing.assert_allclose(np.stack(wire.decode_impulses(reply), 1), want, atol=1e-6)
            assert not np.allclose(want, local.predict(*sent, world, 0, friction=mu.astype(np.float64)).impulses)
            with pytest.raises(grpc.RpcError) as err:
                stub.Predict(wire.encode_step(0, "rubs", bodies, points, world=world_msg, builtin=points["builtin"]))
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "point_friction" in err.value.details()
    finally:
        srv.stop()


def test_mse_sticking_weighs_only_the_points_whose_friction_stays_inside_its_cone():
    import argparse

    from training.train_graph import BatchLoss, Scaling

    inputs = ("new_point", "builtin_normal", "builtin_tangent", "vn", "vt")
    scaling = Scaling(np.zeros(5, np.float32), np.ones(5, np.float32), np.zeros(2, np.float32), np.ones(2, np.float32))
    args = argparse.Namespace(loss="mse-sticking", tangent_weight=1.0, combine="residual")
    # One step; the solver's end slides at point 0 (|t| = 0.5 n, the step's largest ratio, so mu = 0.5),
    # Box2D's warm start slides at point 1, points 2 and 3 stick at both ends.
    builtin = np.array([[1.0, 0.0], [1.0, 0.5], [1.0, 0.1], [2.0, -0.2]], np.float32)
    correction = np.array([[0.0, 0.5], [0.2, -0.3], [0.1, 0.0], [0.0, 0.1]], np.float32)
    points = np.concatenate([np.zeros((4, 1), np.float32), builtin, np.zeros((4, 2), np.float32)], axis=1)
    pred = correction + np.array([[1.0, 1.0], [1.0, 1.0], [0.5, 0.0], [0.0, 0.5]], np.float32)
    loss = BatchLoss(lambda *a: pred, args, scaling, [], inputs)
    per_point, weights = loss(points, None, None, correction, None, None, None, np.zeros(4, np.int32), None, None)
    np.testing.assert_allclose(weights.numpy(), [0.0, 0.0, 1.0, 1.0])
    np.testing.assert_allclose(per_point.numpy(), [0.0, 0.0, 0.25, 0.25], atol=1e-6)


def test_mse_moving_weighs_the_net_push_of_the_error_on_each_moving_body_only():
    import argparse

    from training.train_graph import BatchLoss, Scaling

    scaling = Scaling(np.zeros(3, np.float32), np.ones(3, np.float32), np.zeros(2, np.float32),
                      np.full(2, 2.0, np.float32))  # normalized targets: 1 unit = 2 N s
    args = argparse.Namespace(loss="mse-moving", tangent_weight=1.0, combine="residual")
    # Bodies: 0 static ground, 1 moving at 0.5 m/s, 2 at rest on it. Points: 1 on the ground
    # (normal up from A = 0 to B = 1), 2 on 1, both at the bodies' centres' vertical line.
    ends = np.array([[0, 1], [1, 2]], np.int32)
    n, t = np.array([0.0, 1.0]), np.array([1.0, 0.0])  # tangent (n_y, -n_x)
    geometry = np.array([np.concatenate([n, t, [0.0, 0.0], [0.0, -0.5]]),
                         np.concatenate([n, t, [0.0, 0.5], [0.0, -0.5]])], np.float32)
    inverse = np.array([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0]], np.float32)
    speed = np.array([0.0, 0.5, 0.001], np.float32)
    y = np.zeros((2, 2), np.float32)
    pred = np.array([[0.5, 0.0], [0.0, 0.25]], np.float32)  # errors of 1 N s normal at 0, 0.5 N s tangent at 1
    loss = BatchLoss(lambda *a: pred, args, scaling, [], ("new_point", "builtin_normal", "builtin_tangent", "vn", "vt"))
    per_body, weights = loss(np.zeros((2, 5), np.float32), ends, None, y, geometry, None, inverse,
                             np.zeros(2, np.int32), None, speed)
    np.testing.assert_allclose(weights.numpy(), [0.0, 1.0, 0.0])  # the ground never, body 2 is at rest
    # Body 1 takes +1 N s up from point 0 and -0.5 N s along x from point 1 at r = (0, 0.5):
    # force (-0.5, 1), torque r x f = 0 * 0 - 0.5 * (-0.5) = 0.25; over the normal's std of 2 N s.
    np.testing.assert_allclose(per_body.numpy(), [0.0, (0.25 + 1.0 + 0.0625) / 4.0, 0.0], atol=1e-6)


def test_relative_moving_scores_each_step_against_its_own_moving_bodies_correction():
    import argparse

    from training.train_graph import MOVING_FLOOR, BatchLoss, Scaling

    scaling = Scaling(np.zeros(3, np.float32), np.ones(3, np.float32), np.zeros(2, np.float32), np.ones(2, np.float32))
    args = argparse.Namespace(loss="relative-moving", tangent_weight=1.0, combine="residual")
    # Two steps of one disc each on a static ground (bodies 0, 1 step 0; 2, 3 step 1), both moving;
    # a third step's disc (bodies 4, 5) at rest. Each point pushes its disc straight up.
    ends = np.array([[0, 1], [2, 3], [4, 5]], np.int32)
    row = np.array([0.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0], np.float32)  # n, t, r_A, r_B (on the line of centres)
    geometry = np.stack([row, row, row])
    inverse = np.array([[0, 0], [1, 1], [0, 0], [1, 1], [0, 0], [1, 1]], np.float32)
    speed = np.array([0.0, 0.5, 0.0, 0.5, 0.0, 0.0], np.float32)
    y = np.array([[1.0, 0.0], [0.0, 0.0], [2.0, 0.0]], np.float32)  # corrections 1 N s, 0, 2 N s
    pred = y + np.array([[0.5, 0.0], [0.02, 0.0], [1.0, 0.0]], np.float32)  # errors 0.5, 0.02, 1 N s
    loss = BatchLoss(lambda *a: pred, args, scaling, [], ("new_point", "builtin_normal", "builtin_tangent", "vn", "vt"))
    per_step, weights = loss(np.zeros((3, 5), np.float32), ends, None, y, geometry, None, inverse,
                             np.array([0, 1, 2], np.int32), None, speed)
    np.testing.assert_allclose(weights.numpy(), [1.0, 1.0, 0.0])  # the resting disc's step weighs nothing
    # The same error counts for more where the step's own correction is small (floored).
    np.testing.assert_allclose(per_step.numpy(), [0.25 / (1.0 + MOVING_FLOOR ** 2), 0.02 ** 2 / MOVING_FLOOR ** 2, 0.0],
                               rtol=1e-5)


def _shared_body_step(in_channels: int, rng: np.random.Generator):
    """One step of 30 points among 9 bodies: bodies 0 and 1 static, body 8 touched by no point,
    so most bodies gather several points and some points push on a static body.
    points (30, F) float32, ends (30, 2) int32, dynamic (9, 1) float32."""
    points = rng.standard_normal((30, in_channels)).astype(np.float32)
    ends = np.stack([rng.integers(0, 8, 30), rng.integers(0, 4, 30)], axis=1).astype(np.int32)
    dynamic = np.array([0, 0, 1, 1, 1, 1, 1, 1, 1], np.float32)[:, None]
    return points, ends, dynamic


def _random_net(config, rng: np.random.Generator, incidence: str = "segments"):
    """A network with every weight random: init_weights zeroes the last layer, whose outputs
    would then agree however the sums were taken."""
    from training.graph_model import ContactGraphNet, init_weights

    weights = {k: (0.5 * rng.standard_normal(v.shape)).astype(np.float32) for k, v in init_weights(config).items()}
    return ContactGraphNet(config, weights, incidence=incidence)


@pytest.mark.parametrize("layer_norm,pooled,body", [(False, False, ""), (True, False, ""), (True, True, ""),
                                                     (False, False, "state"), (False, False, "sums")])
def test_a_scatter_export_computes_what_tensorflow_computes_on_bodies_shared_by_points(layer_norm, pooled, body):
    from training.graph_model import ContactGraphNet, GraphConfig, to_onnx

    rng = np.random.default_rng(3)
    config = GraphConfig(in_channels=5, width=8, rounds=3, layer_norm=layer_norm, pooled=pooled,
                         body_state=bool(body), body_plus_sums=body == "sums")
    net = _random_net(config, rng)
    points, ends, dynamic = _shared_body_step(config.in_channels, rng)
    expected = np.asarray(net(points, ends, dynamic))
    # Without norms random weights make outputs of up to about 70, where float32 sums taken
    # in another order differ by a few 1e-5 of the value (how many depends on the kernels
    # TensorFlow picks for the CPU), so the tolerance is relative as well.
    for incidence in ("matmul", "scatter"):  # every way of summing per body is the same network
        other = ContactGraphNet(config, net.weights(), incidence=incidence)
        np.testing.assert_allclose(np.asarray(other(points, ends, dynamic)), expected, rtol=2e-4, atol=1e-5)
    session = ort.InferenceSession(to_onnx(net, incidence="scatter"), providers=["CPUExecutionProvider"])
    got = session.run(["impulses"], {"points": points, "ends": ends, "dynamic": dynamic})[0]
    np.testing.assert_allclose(got, expected, rtol=2e-4, atol=1e-4)


def test_a_scatter_export_sums_by_scatter_adds_with_no_one_hot_matrices_or_sorts():
    import onnx

    from training.graph_model import GraphConfig, to_onnx

    config = GraphConfig(in_channels=5, width=8, rounds=3, layer_norm=True)
    graph = onnx.load_from_string(to_onnx(_random_net(config, np.random.default_rng(0)), incidence="scatter")).graph
    ops = [n.op_type for n in graph.node]
    scatters = [n for n in graph.node if n.op_type == "ScatterND"]
    assert len(scatters) == 2 * config.rounds  # one for body A's messages, one for body B's, per round
    assert all(onnx.helper.get_node_attr_value(n, "reduction") == b"add" for n in scatters)
    # OneHot builds the (P, B) matrices of "matmul"; TopK, Unique and NonZero are tf2onnx's segment sums.
    assert not {"OneHot", "TopK", "Unique", "NonZero"} & set(ops)
    default = onnx.load_from_string(to_onnx(_random_net(config, np.random.default_rng(0)))).graph
    assert sorted(n.op_type for n in default.node) == sorted(ops)  # the scatter export is the default
    matmul = onnx.load_from_string(to_onnx(_random_net(config, np.random.default_rng(0)), incidence="matmul")).graph
    assert "OneHot" in {n.op_type for n in matmul.node}  # what the models before it were exported with


def test_an_unknown_way_of_summing_per_body_is_refused():
    from training.graph_model import ContactGraphNet, GraphConfig, to_onnx

    config = GraphConfig(in_channels=5, width=8, rounds=1)
    with pytest.raises(ValueError, match="incidence"):
        ContactGraphNet(config, incidence="sparse")
    with pytest.raises(ValueError, match="opset 16"):
        to_onnx(ContactGraphNet(config), opset=15, incidence="scatter")


def test_a_network_given_probes_starts_as_the_plain_one_and_is_served_what_training_saw(data, tmp_path,
                                                                                         thesis_steps, graphs):
    # Grown from a plain network, a network with probes answers as it did (its probes' reads
    # start at 0); exported, it takes the contact problem's three arrays, which the server
    # computes from the request's records (deepcontact.kinematics.contact_physics), alone or
    # as a mirror ensemble (the geometry reflected with the step).
    import grpc

    from deepcontact import wire
    from deepcontact.channels import Step, channel_values
    from deepcontact.gridspec import GridSpec
    from deepcontact.kinematics import BODY_DYNAMIC, Physics, contact_physics
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.serve import Server
    from training.ensemble import build_ensemble
    from training.graph_model import ContactGraphNet, GraphConfig
    from training.train_graph import initial_weights

    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "1",
              "--batch-size", "4", "--rounds", "2", "--width", "8", "--loss", "mse", "--cache",
              str(tmp_path / "cache"), "--quiet"]
    models = tmp_path / "models"
    assert main(common + ["--out", str(tmp_path / "plain.onnx")]) == 0
    plain = tmp_path / "cache" / "plain.weights.npz"
    config = GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2, probes=2)
    grown = initial_weights(plain, config)
    x, _, e, d = graphs.batch([3, 5])
    with np.load(plain) as f:
        before = ContactGraphNet(GraphConfig(in_channels=len(GRAPH_INPUTS), width=8, rounds=2), dict(f))(x, e, d)
    np.testing.assert_allclose(ContactGraphNet(config, grown)(x, e, d, physics=graphs.solver_batch([3, 5])).numpy(),
                               before.numpy(), rtol=1e-6, atol=1e-6)

    assert main(common + ["--out", str(models / "probed.onnx"), "--probes", "2", "--init", str(plain)]) == 0
    card = json.loads((models / "probed.json").read_text())
    assert card["architecture"]["config"]["probes"] == 2 and card["parity_max_abs_error"] < 1e-4
    session = ort.InferenceSession(str(models / "probed.onnx"), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["points", "ends", "dynamic", "geometry", "masses", "inverse"]
    mirrored = build_ensemble([models / "probed.json"], "probed-mirror", mirror=True)
    assert json.loads(mirrored.read_text())["parity_max_abs_error"] < 1e-4

    world, steps = thesis_steps
    srv = Server(models=models).start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            request = wire.encode_step(0, "probed", *steps[0], world=world, builtin=steps[0][1]["builtin"])
            reply = stub.Predict(request)
            assert stub.Predict(wire.encode_step(0, "probed-mirror", *steps[0], world=world,
                                                 builtin=steps[0][1]["builtin"])).ListFields()
    finally:
        srv.stop()
    bodies, points = wire.decode_step(request, max_bodies=10**4, max_points=10**5)
    spec = GridSpec.from_dict(card["gridspec"])
    mean, std = spec.normalization_arrays(spec.inputs)
    x = (channel_values(spec.inputs, Step(bodies, points, None, Physics.thesis())) - mean) / std
    ends = np.stack([points["body_a"], points["body_b"]], axis=1).astype(np.int32)
    dynamic = (bodies["type"] == BODY_DYNAMIC).astype(np.float32)[:, None]
    feed = dict(zip(("geometry", "masses", "inverse"), contact_physics(bodies, points)))
    y = session.run(None, {"points": x.astype(np.float32), "ends": ends, "dynamic": dynamic, **feed})[0]
    mo, so = spec.normalization_arrays(spec.targets)
    np.testing.assert_allclose(np.stack(wire.decode_impulses(reply), 1), y * so + mo + points["builtin"],
                               rtol=1e-4, atol=1e-5)
    unmoved = session.run(None, {"points": x.astype(np.float32), "ends": ends, "dynamic": dynamic, **feed,
                                 "masses": np.zeros_like(feed["masses"])})[0]
    assert np.abs(unmoved - y).max() > 1e-4  # the answer reads the operator: the check above sees it


def test_drawing_by_iterations_trains_on_the_hard_steps_more_often(data, tmp_path, monkeypatch):
    # --draw iterations draws each step in proportion to the iterations Box2D's own warm start
    # took there (the recorded file's count, read in the cache's step order), so the steps that
    # make up most of the bench's mean are seen most.
    from training import train_graph
    from training.contact_graph import step_iterations
    from training.grids import open_dataset

    with open_dataset(data / "train.h5") as ds:
        counts = ds.steps["point_count"]
    iterations = step_iterations(data / "train.h5")
    gs = build_graph_set(data / "train.h5")
    assert len(iterations) == len(gs) == np.count_nonzero(counts) and iterations.min() >= 1

    drawn = {}
    batch = train_graph.Scaling.batch

    def recording(self, gs, steps, **k):
        drawn.setdefault(len(gs), []).extend(np.asarray(steps).tolist())
        return batch(self, gs, steps, **k)

    monkeypatch.setattr(train_graph.Scaling, "batch", recording)
    common = ["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--epochs", "20",
              "--batch-size", "2", "--width", "8", "--rounds", "1", "--loss", "mse",
              "--cache", str(tmp_path / "cache"), "--quiet"]
    means = {}
    for draw in ("uniform", "iterations"):
        drawn.clear()
        assert main(common + ["--draw", draw, "--out", str(tmp_path / f"{draw}.onnx")]) == 0
        seen = drawn[len(gs)]
        means[draw] = iterations[seen].mean()
    assert means["iterations"] > means["uniform"]
    assert json.loads((tmp_path / "iterations.json").read_text())["training"]["settings"]["draw"] == "iterations"
    assert "draw" not in json.loads((tmp_path / "uniform.json").read_text())["training"]["settings"]


def test_drawing_converged_steps_leaves_out_those_the_solver_ended_at_its_cap(data, tmp_path, monkeypatch):
    # --draw converged trains only on steps whose recorded impulses are converged: where
    # Box2D's solve ended at its cap (the recorded scene's), the targets are an unconverged
    # iterate. A cap of 20 iterations gives a 60-step file both kinds.
    import dataclasses

    from simclient.scene import SceneSpec, spec_to_dict
    from training import train_graph
    from training.contact_graph import step_converged, step_iterations
    from training.dataset import Writer
    from training.generate import record_simulation

    thesis = SceneSpec.thesis()
    spec = dataclasses.replace(thesis, steps=60, solver=dataclasses.replace(thesis.solver, velocity_iterations=20))
    arrays = record_simulation(spec, 1)
    with Writer(tmp_path / "capped.h5", scene=spec_to_dict(spec), seeds=[1], command="test") as w:
        w.append(arrays["steps"], arrays["bodies"], arrays["points"], arrays["trace"])
    converged = step_converged(tmp_path / "capped.h5")  # (S,) bool, in the cache's step order
    assert (converged == (step_iterations(tmp_path / "capped.h5") < 20)).all()
    assert converged.any() and not converged.all()

    drawn = []
    batch = train_graph.Scaling.batch

    def recording(self, gs, steps, **k):
        if len(gs) == len(converged):
            drawn.extend(np.asarray(steps).tolist())
        return batch(self, gs, steps, **k)

    monkeypatch.setattr(train_graph.Scaling, "batch", recording)
    assert main(["train-graph", "--train", str(tmp_path / "capped.h5"), "--val", str(data / "val.h5"),
                 "--epochs", "10", "--batch-size", "4", "--width", "8", "--rounds", "1", "--loss", "mse",
                 "--draw", "converged", "--cache", str(tmp_path / "cache"),
                 "--out", str(tmp_path / "m.onnx"), "--quiet"]) == 0
    assert drawn and converged[drawn].all()
    assert json.loads((tmp_path / "m.json").read_text())["training"]["settings"]["draw"] == "converged"


def test_drawing_by_iterations_is_refused_beside_a_second_pass(data, tmp_path, capsys):
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
                 "--second-pass", str(data / "train.h5"), "--draw", "iterations",
                 "--out", str(tmp_path / "m.onnx"), "--quiet"]) == 2
    assert "--second-pass" in capsys.readouterr().err
