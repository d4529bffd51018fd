"""The server's predictors and step decoding, without gRPC: the same transfer
and normalization as training, bit for bit, with the contact points' kernel
weights computed once per step."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from deepcontact import wire
from deepcontact.features import world_to_grids
from deepcontact.gridspec import GridSpec
from deepcontact.kinematics import Physics
from deepcontact.modelcard import ModelCard, ModelCardError
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE
from deepcontact.transfer import g2p, p2g
from server.predictors import GridIdentityPredictor, ModelPredictor, World, _Normalization
from tests.server.conftest import write_conv_model

DOMAIN = ((0.0, 0.0), (15.0, 15.0))
WORLD = World(DOMAIN, Physics.thesis())
NORMALIZATION = {
    "mass": (0.3, 2.5), "vx": (-0.1, 0.7), "omega": (0.05, 1.3), "normal_y": (-0.2, 0.9),
    "impulse_normal": (0.4, 1.7), "impulse_tangent": (-0.01, 0.2),
}


@pytest.fixture(scope="module")
def normalized_model(tmp_path_factory):
    """A residual 1x1-convolution model whose card normalizes most channels."""
    folder = tmp_path_factory.mktemp("normalized")
    card = write_conv_model(folder, "norm", combine="residual", seed=3)
    card = dataclasses.replace(card, gridspec=card.gridspec.with_normalization(NORMALIZATION))
    card.save(folder / "norm.json")
    return ModelPredictor(ModelCard.load(folder / "norm.json"), folder / "norm.onnx")


def sent(bodies, points):
    """The records the server works on: the step through the wire."""
    msg = wire.encode_step(0, "norm", bodies, points, builtin=points["builtin"], impulses=points["impulse"])
    return wire.decode_step(msg, max_bodies=10**4, max_points=10**5)


def with_a_point_outside(points):
    """The points plus a copy of the first one 2 m past the right wall (dropped)."""
    extra = points[:1].copy()
    extra["point"] = [[17.0, 3.0]]
    return np.concatenate([points, extra])


def test_normalization_is_gridspecs_bit_for_bit():
    spec = GridSpec.thesis(normalization=NORMALIZATION)
    norm = _Normalization(spec)
    rng = np.random.default_rng(0)
    grid = (3 * rng.normal(size=(61, 61, 6))).astype(np.float32)
    np.testing.assert_array_equal(norm.inputs(grid.copy()), spec.normalize(grid, "inputs")[None])
    y = rng.normal(size=(1, 61, 61, 2)).astype(np.float32)
    np.testing.assert_array_equal(norm.targets(y), spec.denormalize(y[0], "targets"))


def test_a_model_step_is_the_transfer_done_by_hand(normalized_model, thesis_steps):
    model = normalized_model
    _, steps = thesis_steps
    for bodies, points in steps:
        bodies, points = sent(bodies, with_a_point_outside(points))
        answer = model.predict(bodies, points, WORLD, 0)
        impulses = answer.impulses
        assert set(answer.stages) == {"p2g", "inference", "g2p"} and answer.served_by is None
        # Training's way: P2G, normalize, the model, denormalize, G2P (+ builtin: residual).
        spec = model._specs.get(DOMAIN)
        x = spec.normalize(world_to_grids(bodies, points, spec, outside="drop"), "inputs")[None]
        y = model.session.run(None, {"grids": x})[0]
        expected, _ = g2p(spec.denormalize(y[0], "targets"), points["point"], spec, outside="drop")
        expected = expected + points["builtin"]
        assert impulses.dtype == np.float32 and impulses.shape == (len(points), 2)
        np.testing.assert_array_equal(impulses, expected)
        np.testing.assert_array_equal(impulses[-1], points["builtin"][-1])  # dropped: builtin only


def test_grid_identity_is_p2g_then_g2p(thesis_steps):
    _, steps = thesis_steps
    bodies, points = sent(*steps[0])
    points = with_a_point_outside(points)
    predictor = GridIdentityPredictor(GridSpec.thesis())
    got = predictor.predict(bodies, points, WORLD, 0).impulses
    spec = GridSpec.thesis()
    grid, _ = p2g(points["point"], points["impulse"], spec, outside="drop")
    expected, _ = g2p(grid, points["point"], spec, outside="drop")
    np.testing.assert_array_equal(got, expected)


def reference_decode(msg):
    """decode_step written field by field."""
    b = np.frombuffer(msg.bodies, np.float32).reshape(msg.body_count, len(wire.BODY_COLUMNS))
    p = np.frombuffer(msg.points, np.float32).reshape(msg.point_count, len(wire.POINT_COLUMNS))
    bodies = np.zeros(len(b) + 1, BODY_DTYPE)  # row 0: the walls' static stand-in
    bodies["index"] = np.arange(len(b) + 1)
    bodies["type"][1:] = 2
    bodies["position"][1:] = b[:, 0:2]
    bodies["angle"][1:] = b[:, 2]
    bodies["velocity"][1:] = b[:, 3:5]
    bodies["angular_velocity"][1:] = b[:, 5]
    bodies["mass"][1:] = b[:, 6]
    bodies["radius"][1:] = b[:, 7]
    if msg.body_inertia:
        bodies["inertia"][1:] = np.frombuffer(msg.body_inertia, np.float32)
    points = np.zeros(len(p), CONTACT_DTYPE)
    points["point"] = p[:, 0:2]
    points["normal"] = p[:, 2:4]
    if msg.builtin:
        points["builtin"] = np.frombuffer(msg.builtin, np.float32).reshape(-1, 2)
    if msg.impulses:
        points["impulse"] = np.frombuffer(msg.impulses, np.float32).reshape(-1, 2)
    if msg.point_separation:
        points["separation"] = np.frombuffer(msg.point_separation, np.float32)
    if msg.point_bodies:
        rows = np.frombuffer(msg.point_bodies, np.int32).reshape(-1, 2) + 1
        points["body_a"], points["body_b"] = rows[:, 0], rows[:, 1]
    if msg.point_keys:
        points["key"] = np.frombuffer(msg.point_keys, np.uint64)
    return bodies, points


@pytest.mark.parametrize("extra", [{}, {"builtin": True}, {"builtin": True, "impulses": True}])
def test_steps_decode_into_the_records_field_by_field(thesis_steps, extra):
    _, steps = thesis_steps
    for bodies, points in steps + [(steps[0][0][:0], steps[0][1][:0])]:
        kw = {k: points["builtin" if k == "builtin" else "impulse"] for k in extra}
        msg = wire.encode_step(0, "tiny", bodies, points, **kw)
        got = wire.decode_step(msg, max_bodies=10**4, max_points=10**5)
        for g, e in zip(got, reference_decode(msg)):
            assert g.dtype == e.dtype and g.shape == e.shape
            assert g.tobytes() == e.tobytes()


def test_decoded_steps_keep_the_engines_body_indices_and_contact_velocities(thesis_steps):
    from deepcontact.kinematics import contact_velocities

    _, steps = thesis_steps
    for bodies, points in steps:
        got_bodies, got_points = wire.decode_step(wire.encode_step(0, "tiny", bodies, points),
                                                  max_bodies=10**4, max_points=10**5)
        np.testing.assert_array_equal(got_bodies[got_points["body_b"]]["position"], bodies[points["body_b"]]["position"])
        np.testing.assert_array_equal(contact_velocities(got_bodies, got_points, points["builtin"], Physics.thesis()),
                                      contact_velocities(bodies, points, points["builtin"], Physics.thesis()))


@pytest.mark.parametrize("field", ["bodies", "points", "builtin", "impulses", "point_separation", "body_inertia"])
def test_a_non_finite_array_is_named(thesis_steps, field):
    _, steps = thesis_steps
    bodies, points = steps[0]
    msg = wire.encode_step(0, "tiny", bodies, points, builtin=points["builtin"], impulses=points["builtin"])
    bad = np.frombuffer(getattr(msg, field), np.float32).copy()
    bad[-1] = np.inf
    setattr(msg, field, bad.tobytes())
    with pytest.raises(wire.WireError, match=f"^{field}: holds NaN or infinite values"):
        wire.decode_step(msg, max_bodies=10**4, max_points=10**5)


def test_combine_serves_model_builtin_or_both():
    from server.predictors import combine

    predicted = np.array([[1.0, 0.1], [2.0, 0.2], [3.0, 0.3]], np.float32)
    builtin = np.array([[0.5, 0.0], [0.0, 0.0], [0.0, -0.1]], np.float32)  # point 1 is new
    np.testing.assert_array_equal(combine("replace", predicted, builtin), predicted)
    np.testing.assert_array_equal(combine("residual", predicted, builtin), predicted + builtin)
    np.testing.assert_array_equal(combine("new-points", predicted, builtin), np.array([[0.5, 0.0], [2.0, 0.2], [0.0, -0.1]], np.float32))
    # "persisting": the correction where Box2D already warm-starts the point, nothing at new ones.
    np.testing.assert_allclose(combine("persisting", predicted, builtin), np.array([[1.5, 0.1], [0.0, 0.0], [3.0, 0.2]], np.float32))
    # "moving": the correction on moving bodies only, builtin on a pile at rest.
    rest = np.array([False, True, False])
    np.testing.assert_allclose(combine("moving", predicted, builtin, rest=rest),
                               np.array([[1.5, 0.1], [0.0, 0.0], [3.0, 0.2]], np.float32))
    with pytest.raises(ValueError, match="at rest"):
        combine("moving", predicted, builtin)
    # A card's correction_scale shrinks a residual model's correction.
    np.testing.assert_allclose(combine("residual", predicted, builtin, 0.5), builtin + 0.5 * predicted)
    # Its correction_threshold drops the corrections whose normal part is at most that.
    np.testing.assert_allclose(combine("residual", predicted, builtin, 1.0, 1.5),
                                  np.array([[0.5, 0.0], [2.0, 0.2], [3.0, 0.2]], np.float32))


def test_cards_may_share_an_onnx_file_and_orphans_are_refused(tmp_path):
    from deepcontact.modelcard import ModelCardError
    from server.predictors import load_models

    card = write_conv_model(tmp_path, "base")
    dataclasses.replace(card, name="base-new-points", combine="new-points").save(tmp_path / "base-new-points.json")
    models = {m.name: m.card.combine for m in load_models(tmp_path)}
    assert models == {"base": "replace", "base-new-points": "new-points"}
    (tmp_path / "base.json").unlink()
    (tmp_path / "base-new-points.json").unlink()
    with pytest.raises(ModelCardError, match="no model card names base.onnx"):
        load_models(tmp_path)


def test_the_shipped_models_include_default_an_alias_served_like_its_target():
    from pathlib import Path

    from server.predictors import load_models

    models = {m.name: m for m in load_models(Path(__file__).parents[2] / "models")}
    target = ModelCard.alias_target(Path(__file__).parents[2] / "models" / "default.json")
    assert "default" in models and target in models
    assert models["default"].card.onnx_file == models[target].card.onnx_file
    assert models["default"].card.combine == models[target].card.combine


@pytest.mark.parametrize("intercept", [-50.0, 50.0])
def test_a_gated_model_serves_box2ds_warm_start_where_its_gate_says_and_its_own_answer_elsewhere(
        tmp_path, thesis_steps, intercept):
    import json
    import shutil
    from pathlib import Path

    from deepcontact.step_gate import FEATURES, StepGate
    from server.predictors import load_model

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    # the shipped default's graph network: the end of its chain of face routes
    target = "default"
    while (face := ModelCard.load(shipped / f"{target}.json").face) is not None:
        target = face["fallback"]
    for name in (f"{target}.json", f"{target}.onnx"):
        shutil.copy(shipped / name, tmp_path)
    f = len(FEATURES)  # a gate that answers the same at every step: its intercept alone decides
    gate = StepGate((0.0,) * f, (1.0,) * f, (intercept,) + (0.0,) * f).to_dict()
    (tmp_path / "gated.json").write_text(json.dumps({"name": "gated", "alias_of": target, "step_gate": gate}))
    plain, gated = load_model(tmp_path / f"{target}.json"), load_model(tmp_path / "gated.json")
    assert "point_separation" in gated.requires and "builtin" in gated.requires
    world_msg, steps = thesis_steps
    lower, upper, _ = wire.decode_world(world_msg)
    world = World((lower, upper), wire.decode_physics(world_msg))
    bodies, points = steps[0]
    points = points.copy()
    points["builtin"] = points["impulse"] * 0.9  # a warm start the model corrects
    own = plain.predict(bodies, points, world, 0).impulses
    answer = gated.predict(bodies, points, world, 0)
    served = answer.impulses
    if intercept > 0:
        np.testing.assert_array_equal(served, own)
    else:
        np.testing.assert_array_equal(served, points["builtin"])
        assert not np.array_equal(own, points["builtin"])
    assert set(answer.stages) == {"features", "inference", "g2p"} and answer.stages["g2p"] > 0


def test_a_face_card_falls_back_to_the_card_it_names_where_its_labels_look_wrong_or_the_step_is_large(tmp_path, thesis_steps):
    # With max_residual and fallback, a step whose admitted solve misses its labels' equations by
    # more than that share gets the named card's answer (here the classifier's own, which has no
    # face): at a share of 0 every step with a residual does; at a large one none does. The same
    # for a step with more points than max_points, before any label is asked for.
    import json
    import shutil
    from pathlib import Path

    from server.predictors import load_model

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    classifier = json.loads((shipped / "face.json").read_text())["alias_of"]
    for name in (f"{classifier}.json", f"{classifier}.onnx"):
        shutil.copy(shipped / name, tmp_path)
    world_msg, steps = thesis_steps
    lower, upper, _ = wire.decode_world(world_msg)
    world = World((lower, upper), wire.decode_physics(world_msg))
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5)

    def served(name, **face):
        (tmp_path / f"{name}.json").write_text(json.dumps({"name": name, "alias_of": classifier,
                                                           "face": {"pressing": 0.75, "rounds": 200, **face}}))
        return load_model(tmp_path / f"{name}.json").predict(bodies, points, world, 0, friction=mu).impulses

    own = load_model(tmp_path / f"{classifier}.json").predict(bodies, points, world, 0).impulses
    np.testing.assert_array_equal(served("always", max_residual=1e-12, fallback=classifier), own)
    np.testing.assert_array_equal(served("never", max_residual=1e9, fallback=classifier), served("plain"))
    assert not np.array_equal(served("plain"), own)
    # A step with more points than max_points is not solved: the fallback's answer, else Box2D's.
    np.testing.assert_array_equal(served("large", max_points=len(points) - 1, fallback=classifier), own)
    np.testing.assert_array_equal(served("large-builtin", max_points=len(points) - 1), points["builtin"])
    np.testing.assert_array_equal(served("small", max_points=len(points), fallback=classifier), served("plain"))
    # A fallback is served only inside what it was trained on: on a world of another time step
    # than its card's trained_on holds, Box2D's own start answers in its place.
    from deepcontact.envelope import Envelope

    card = json.loads((tmp_path / f"{classifier}.json").read_text())
    card.update(name="thesis-only", trained_on=Envelope().to_dict())  # the thesis world's dt, 0.01 s
    (tmp_path / "thesis-only.json").write_text(json.dumps(card))
    np.testing.assert_array_equal(served("large-familiar", max_points=len(points) - 1, fallback="thesis-only"), own)
    (tmp_path / "large-elsewhere.json").write_text(json.dumps({"name": "large-elsewhere", "alias_of": classifier,
        "face": {"pressing": 0.75, "rounds": 200, "max_points": len(points) - 1, "fallback": "thesis-only"}}))
    other = World(world.domain, dataclasses.replace(world.physics, dt=0.04))
    elsewhere = load_model(tmp_path / "large-elsewhere.json").predict(bodies, points, other, 0, friction=mu)
    np.testing.assert_array_equal(elsewhere.impulses, points["builtin"])
    assert elsewhere.served_by == "builtin"
    # The route itself answers only for the worlds its classifier was trained on; elsewhere its
    # fallback does (here a route on a classifier that labels every world).
    (tmp_path / "thesis-route.json").write_text(json.dumps({"name": "thesis-route", "alias_of": "thesis-only",
        "face": {"pressing": 0.75, "rounds": 200, "fallback": "plain"}}))
    route = load_model(tmp_path / "thesis-route.json")
    inside = route.predict(bodies, points, world, 0, friction=mu)
    np.testing.assert_array_equal(inside.impulses, served("plain"))
    assert inside.served_by is None
    outside = route.predict(bodies, points, other, 0, friction=mu)
    assert outside.served_by == "plain"
    # Its answer carries that verdict, for the reply to say without judging the step again.
    assert inside.unfamiliar is None and outside.unfamiliar.startswith("dt 0.04")
    # retry_pressing: where the first reading misses max_residual, the labels are read again at
    # each threshold in turn; the first reading that meets it is served, the fallback where none does.
    from deepcontact.faces import solved_on_labels

    labels = own.astype(np.float64)
    residual = {p: solved_on_labels(bodies, points, labels, mu, world.physics, p, 1.0, 200)[1] for p in (0.75, 0.9, 1.1)}
    gate = 0.5 * (residual[0.75] + residual[1.1])  # one reading on each side of it
    first, later = (0.75, 1.1) if residual[0.75] <= gate else (1.1, 0.75)
    served_first = served("first-only", pressing=first)
    np.testing.assert_array_equal(served("retried", pressing=later, retry_pressing=[later, first],
                                         max_residual=gate, fallback=classifier), served_first)
    np.testing.assert_array_equal(served("none-meets", pressing=later, retry_pressing=[later],
                                         max_residual=gate, fallback=classifier), own)
    with pytest.raises(ModelCardError, match="retry_pressing"):
        served("retries-without-a-gate", retry_pressing=[0.9])
    with pytest.raises(ModelCardError, match="retry_pressing"):
        served("retries-not-a-list", retry_pressing=0.9, max_residual=0.3)
    # A fallback with a face of its own is a second route, tried in turn; a chain of routes
    # that comes back to one of its own is refused.
    np.testing.assert_array_equal(served("chain", max_points=len(points) - 1, fallback="plain"), served("plain"))
    # Where its own route ran and missed its labels, not a second route on the same step: that
    # route's own fallback answers (here none: Box2D's start).
    np.testing.assert_array_equal(served("missed", max_residual=1e-12, fallback="plain"), points["builtin"])
    (tmp_path / "loop-a.json").write_text(json.dumps({"name": "loop-a", "alias_of": classifier,
                                                      "face": {"pressing": 0.75, "fallback": "loop-b"}}))
    (tmp_path / "loop-b.json").write_text(json.dumps({"name": "loop-b", "alias_of": classifier,
                                                      "face": {"pressing": 0.75, "fallback": "loop-a"}}))
    with pytest.raises(ModelCardError, match="in a circle"):
        load_model(tmp_path / "loop-a.json")
    with pytest.raises(ModelCardError, match="no model card"):
        served("missing", max_residual=0.3, fallback="nowhere")


def test_a_face_card_serves_the_step_solved_on_its_classifiers_labels_and_needs_the_friction(tmp_path, thesis_steps):
    # The shipped face route: the classifier graph-face-r8-e12 answers each point with its
    # labels written as impulses; the alias card `face` has the server read them, solve the
    # step on them and admit the result. Over real gRPC, with each point's friction sent.
    import grpc
    import json
    import shutil
    from pathlib import Path

    from deepcontact.faces import solved_on_labels
    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.predictors import load_model
    from server.serve import Server

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    face = json.loads((shipped / "face.json").read_text())
    for name in ("face.json", f"{face['alias_of']}.json", f"{face['alias_of']}.onnx"):
        shutil.copy(shipped / name, tmp_path)
    classifier = load_model(tmp_path / f"{face['alias_of']}.json")
    assert "point_friction" not in classifier.requires
    assert {"point_friction", "physics", "body_inertia"} <= set(load_model(tmp_path / "face.json").requires)
    world_msg, steps = thesis_steps
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5, np.float32)  # the thesis world's friction at every pair
    sent_bodies, sent_points = wire.decode_step(wire.encode_step(0, "face", bodies, points, builtin=points["builtin"]),
                                                max_bodies=10**4, max_points=10**5)
    lower, upper, _ = wire.decode_world(world_msg)
    world = World((lower, upper), wire.decode_physics(world_msg))
    labels = classifier.predict(sent_bodies, sent_points, world, 0).impulses
    settings = face["face"]
    expected, _ = solved_on_labels(sent_bodies, sent_points, labels.astype(np.float64), mu.astype(np.float64),
                                   world.physics, settings["pressing"], settings.get("share", 1.0), settings["rounds"],
                                   settings.get("label_friction"))
    srv = Server(models=tmp_path, bind="127.0.0.1:0").start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            reply = stub.Predict(wire.encode_step(0, "face", bodies, points, world=world_msg,
                                                  builtin=points["builtin"], friction=mu))
            served = np.stack(wire.decode_impulses(reply), axis=1)
            np.testing.assert_allclose(served, expected, atol=1e-6)
            assert (served[:, 0] >= 0).all() and (np.abs(served[:, 1]) <= 0.5 * served[:, 0] + 1e-5).all()
            t = reply.timings  # the face route's stages, each under its own name
            assert t.features_us > 0 and t.inference_us > 0 and t.solve_us > 0 and t.admit_us > 0
            assert t.p2g_us == t.g2p_us == 0 and t.total_us >= t.features_us + t.inference_us + t.solve_us + t.admit_us
            with pytest.raises(grpc.RpcError) as refused:  # an older client, without the friction
                stub.Predict(wire.encode_step(0, "face", bodies, points, world=world_msg, builtin=points["builtin"]))
            assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "point_friction" in refused.value.details()
            with pytest.raises(grpc.RpcError) as refused:
                stub.Predict(wire.encode_step(0, "face", bodies, points, world=world_msg, builtin=points["builtin"],
                                              friction=-mu))
            assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "point_friction: holds negative values" in refused.value.details()
    finally:
        srv.stop()


def test_a_face_card_serves_its_fallback_where_its_route_would_miss_the_clients_budget(tmp_path, thesis_steps):
    # A request carries how long its client waits (budget_us). A face card whose route has been
    # seen to cost more than is left answers its fallback card's answer in time, and says so
    # (served_by); with room, or without a budget, it serves its route. Over real gRPC.
    import grpc
    import json
    import shutil
    from pathlib import Path

    from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
    from server.predictors import load_model
    from server.serve import Server

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    classifier = json.loads((shipped / "face.json").read_text())["alias_of"]
    for name in (f"{classifier}.json", f"{classifier}.onnx"):
        shutil.copy(shipped / name, tmp_path)
    (tmp_path / "timed.json").write_text(json.dumps({"name": "timed", "alias_of": classifier, "face": {
        "pressing": 0.75, "rounds": 200, "fallback": classifier}}))
    world_msg, steps = thesis_steps
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5, np.float32)
    lower, upper, _ = wire.decode_world(world_msg)
    world = World((lower, upper), wire.decode_physics(world_msg))
    sent_bodies, sent_points = wire.decode_step(wire.encode_step(0, "timed", bodies, points, builtin=points["builtin"]),
                                                max_bodies=10**4, max_points=10**5)
    own = load_model(tmp_path / f"{classifier}.json").predict(sent_bodies, sent_points, world, 0).impulses
    srv = Server(models=tmp_path, bind="127.0.0.1:0", deadline_margin_s=0.0).start()
    try:
        timed = next(m for m in srv.models if m.name == "timed")
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)

            def ask(budget_us):
                request = wire.encode_step(0, "timed", bodies, points, world=world_msg, builtin=points["builtin"],
                                           friction=mu)
                request.budget_us = budget_us
                reply = stub.Predict(request)
                return np.stack(wire.decode_impulses(reply), axis=1), reply.served_by

            route, by = ask(0)  # no budget: the route, whatever it costs
            assert by == "" and not np.array_equal(route, own)
            for _ in range(4):  # the route as seen on a host far slower than the budget
                timed.cost.observe(len(points), 10.0)
            late, by = ask(1_000_000)
            assert by == classifier
            np.testing.assert_array_equal(late, own)
            np.testing.assert_array_equal(ask(0)[0], route)
            assert ask(30_000_000)[1] == ""  # a budget with room for it
    finally:
        srv.stop()


def shipped_classifier(folder):
    """The shipped face route's classifier (the alias target of models/face.json), its card and
    ONNX file copied into folder: its name."""
    import json
    import shutil
    from pathlib import Path

    shipped = Path(__file__).parents[2] / "lab" / "models"  # the research store
    classifier = json.loads((shipped / "face.json").read_text())["alias_of"]
    for name in (f"{classifier}.json", f"{classifier}.onnx"):
        shutil.copy(shipped / name, folder)
    return classifier


def face_card(folder, name, classifier, **face):
    """A face card over the classifier in folder, with these face settings: its path."""
    import json

    path = folder / f"{name}.json"
    path.write_text(json.dumps({"name": name, "alias_of": classifier,
                                "face": {"pressing": 0.75, "rounds": 200, **face}}))
    return path


def thesis_world(world_msg):
    lower, upper, _ = wire.decode_world(world_msg)
    return World((lower, upper), wire.decode_physics(world_msg))


def test_a_face_card_loads_as_a_face_route_built_whole_with_its_classifier_and_its_fallback(tmp_path):
    from server.face_route import ROUTE_NEEDS, FaceRoutePredictor
    from server.predictors import GraphPredictor, load_model

    classifier = shipped_classifier(tmp_path)
    route = load_model(face_card(tmp_path, "route", classifier, fallback=classifier, max_points=300))
    assert isinstance(route, FaceRoutePredictor) and route.takes_deadline
    assert route.name == "route" and route.card.face["max_points"] == 300 and route.settings is route.card.face
    # The classifier is the card's network without the route; the fallback the card it names, loaded with it.
    assert isinstance(route.classifier, GraphPredictor) and route.classifier.card.face is None
    assert isinstance(route.fallback, GraphPredictor) and route.fallback.name == classifier
    assert set(route.requires) == set(route.classifier.requires) | set(ROUTE_NEEDS) | set(route.fallback.requires)
    alone = load_model(face_card(tmp_path, "alone", classifier))
    assert isinstance(alone, FaceRoutePredictor) and alone.fallback is None
    plain = load_model(tmp_path / f"{classifier}.json")
    assert type(plain) is GraphPredictor and not plain.takes_deadline and "point_friction" not in plain.requires
    with pytest.raises(ModelCardError, match="FaceRoutePredictor"):  # a graph model does not serve a face by halves
        GraphPredictor(route.card, tmp_path / route.card.onnx_file)


def test_served_by_is_a_field_of_the_answer_and_the_fallbacks_stages_are_its_own(tmp_path, thesis_steps):
    from server.predictors import Prediction, load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = thesis_world(world_msg)
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5)
    own = load_model(tmp_path / f"{classifier}.json").predict(bodies, points, world, 0)
    assert isinstance(own, Prediction) and own.served_by is None
    route = load_model(face_card(tmp_path, "route", classifier, fallback=classifier)).predict(bodies, points, world, 0,
                                                                                              friction=mu)
    assert route.served_by is None and not np.array_equal(route.impulses, own.impulses)
    # Past max_points: the fallback card answers, with its own stages, and says so.
    large = load_model(face_card(tmp_path, "large", classifier, max_points=len(points) - 1, fallback=classifier))
    answer = large.predict(bodies, points, world, 0, friction=mu)
    assert answer.served_by == classifier and set(answer.stages) == {"features", "inference", "g2p"}
    assert all(isinstance(s, float) for s in answer.stages.values())
    np.testing.assert_array_equal(answer.impulses, own.impulses)
    builtin = load_model(face_card(tmp_path, "builtin", classifier, max_points=len(points) - 1))
    answer = builtin.predict(bodies, points, world, 0, friction=mu)
    assert answer.served_by == "builtin" and answer.stages == {} and answer.impulses.dtype == np.float32
    np.testing.assert_array_equal(answer.impulses, points["builtin"])


def test_a_face_routes_step_reports_its_features_inference_solve_and_admission(tmp_path, thesis_steps):
    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = thesis_world(world_msg)
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5)
    answer = load_model(face_card(tmp_path, "route", classifier)).predict(bodies, points, world, 0, friction=mu)
    assert set(answer.stages) == {"features", "inference", "solve", "admit"}
    assert all(s > 0 for s in answer.stages.values()) and answer.served_by is None
    # Labels taken for wrong (every residual above 0): the route's stages, and the fallback's added in.
    rejected = load_model(face_card(tmp_path, "rejected", classifier, max_residual=1e-12, fallback=classifier))
    answer = rejected.predict(bodies, points, world, 0, friction=mu)
    assert answer.served_by == classifier
    assert set(answer.stages) == {"features", "inference", "solve", "admit", "g2p"}


@pytest.mark.parametrize("check", [{}, {"check_sweeps": 12}, {"check_sweeps": 200, "check_stop": True}],
                         ids=["one-jacobi-step", "twelve-sweeps", "sweeps-to-the-stopping-rule"])
def test_a_route_against_builtin_serves_its_answer_only_where_it_beats_box2ds_start(tmp_path, thesis_steps, check):
    """against_builtin compares the route's answer with Box2D's start by one projected Jacobi
    step from each, or with check_sweeps by the solver's own sweeps played on the server's copy
    of the step (deepcontact.faces.sweep_changes), and with check_stop by the sweeps each takes
    to the stopping rule the client declared (the World's tolerance, deepcontact.faces.sweeps_to_stop)."""
    import dataclasses

    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = dataclasses.replace(thesis_world(world_msg), tolerance=1e-4)
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5, np.float32)
    checked = load_model(face_card(tmp_path, "checked", classifier, against_builtin=True, **check))
    plain = load_model(face_card(tmp_path, "plain", classifier))
    assert checked.settings["against_builtin"] and not plain.settings["against_builtin"]
    # Box2D's start where the solver ended (the recorded final impulses): nothing beats it.
    solved = points.copy()
    solved["builtin"] = points["impulse"]
    answer = checked.predict(bodies, solved, world, 0, friction=mu)
    assert answer.served_by == "builtin" and "admit" in answer.stages
    np.testing.assert_array_equal(answer.impulses, solved["builtin"])
    # No warm start at all: the route's answer beats it, and is the unchecked route's.
    cold = points.copy()
    cold["builtin"] = 0.0
    answer = checked.predict(bodies, cold, world, 0, friction=mu)
    assert answer.served_by is None
    np.testing.assert_array_equal(answer.impulses, plain.predict(bodies, cold, world, 0, friction=mu).impulses)


@pytest.mark.parametrize("route_change, served_by", [(1e-6, None), (1e-4, "builtin")],
                         ids=["route-nearer-its-end", "box2d-nearer-its-end"])
def test_a_route_checked_by_the_stopping_rule_breaks_a_tie_by_the_last_change(tmp_path, thesis_steps, monkeypatch,
                                                                                 route_change, served_by):
    """Where the route's answer and Box2D's start stop at the same sweep, the one whose last
    sweep changed the impulses less is served: the solver's count is the same from either, and
    the nearer start leaves the next step's warm start nearer its end too."""
    import dataclasses

    import server.face_route
    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = dataclasses.replace(thesis_world(world_msg), tolerance=1e-4)
    bodies, points = steps[0]
    mu = np.full(len(points), 0.5, np.float32)

    def both_stop_at_sweep_five(bodies, points, start, friction, physics, sweeps, prepared=None, stop=0.0,
                                by_island=False, restitution=None):
        assert stop == 1e-4  # the client's stopping rule reached the check
        return (5, 1e-5) if np.array_equal(start, points["builtin"]) else (5, route_change)

    monkeypatch.setattr(server.face_route, "_sweep_change", both_stop_at_sweep_five)
    checked = load_model(face_card(tmp_path, "checked", classifier, against_builtin=True, check_sweeps=200,
                                   check_stop=True))
    assert checked.predict(bodies, points, world, 0, friction=mu).served_by == served_by


def test_by_the_stopping_rule_the_routes_side_is_counted_no_further_than_box2ds(tmp_path, thesis_steps, monkeypatch):
    """Checked by the client's stopping rule, the route's side of the check stops counting at the
    sweep where Box2D's start stopped: past it the route has lost whatever its count. The verdict
    is the one a count to the card's 200 sweeps gives, for fewer sweeps where the route loses."""
    import server.face_route
    from deepcontact.faces import sweeps_to_stop
    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = dataclasses.replace(thesis_world(world_msg), tolerance=1e-3)
    checked = load_model(face_card(tmp_path, "checked", classifier, against_builtin=True, check_sweeps=200,
                                   check_stop=True))
    counted = []
    real = server.face_route._sweep_change

    def recorded(bodies, points, start, friction, physics, sweeps, prepared=None, stop=0.0, by_island=False,
                 restitution=None):
        answer = real(bodies, points, start, friction, physics, sweeps, prepared, stop, by_island, restitution)
        counted.append((sweeps, answer))
        return answer

    monkeypatch.setattr(server.face_route, "_sweep_change", recorded)
    rng = np.random.default_rng(3)
    verdicts, spared = set(), []
    for bodies, points in steps:
        mu = points["friction"].astype(np.float64)
        builtin = points["builtin"].astype(np.float64)
        solution = points["impulse"].astype(np.float64)  # the solver's own end: it stops at once
        for start in (solution, builtin * rng.uniform(0.9, 1.1, builtin.shape), np.zeros_like(builtin)):
            counted.clear()
            verdict = checked._beats_builtin(bodies, points, start, mu, world)
            (_, (box2d_sweeps, box2d)), (route_most, _) = counted
            assert route_most <= box2d_sweeps
            spared.append(200 - route_most)
            counts, changes = sweeps_to_stop(bodies, points, np.stack([start, builtin]), mu, world.physics, 1e-3, 200)
            full = counts[0] < counts[1] or (counts[0] == counts[1] and changes[0] < changes[1])
            assert (int(counts[1]), float(changes[1])) == (box2d_sweeps, box2d)
            assert verdict == full
            verdicts.add(verdict)
    assert verdicts == {True, False}  # both ways were met
    assert max(spared) > 0  # where Box2D's start stopped before sweep 200, the rest were spared


def test_a_route_checked_island_by_island_serves_each_island_the_start_that_stops_it_sooner(tmp_path):
    """With by_island, the check counts each island of the step (bodies joined by contacts, not
    through the static terrain) as Box2D's solver stops it, and serves the route's answer on the
    islands where it stops sooner and Box2D's start on the rest: on the zoo's terrain, with Box2D's
    start the solver's own end on the largest island and nothing elsewhere, the islands part."""
    import shutil
    from pathlib import Path

    from bench.inprocess import declared_world
    from deepcontact.faces import island_sweeps_to_stop
    from server.predictors import load_model
    from simclient import worlds

    for name in ("contact-modes-zoo.json", "contact-modes-zoo.onnx"):
        shutil.copy(Path(__file__).parents[2] / "models" / name, tmp_path)
    settings = dict(against_builtin=True, check_sweeps=200, check_stop=True)
    by_island = load_model(face_card(tmp_path, "by-island", "contact-modes-zoo", by_island=True, **settings))
    plain = load_model(face_card(tmp_path, "plain", "contact-modes-zoo"))
    assert by_island.settings["by_island"] and not plain.settings["by_island"]
    spec = worlds.WorldSpec("simclient.zoo:terrain")
    engine = worlds.build(spec, 850)
    world = declared_world(spec, engine)
    for _ in range(40):
        engine.collide()
        engine.solve()
    parted = 0
    for _ in range(3):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        b = points["builtin"]
        exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
        mu = points["friction"].astype(np.float32)
        islands = island_sweeps_to_stop(bodies, points, exact[None], mu.astype(np.float64), world.physics,
                                        world.tolerance, 1)[2]
        assert islands.counts.shape[1] > 2  # stones resting apart on the terrain
        largest = np.bincount(islands.point).argmax() == islands.point
        mixed = points.copy()
        mixed["builtin"] = np.where(largest[:, None], exact, 0.0)
        route = plain.predict(bodies, mixed, world, 0, friction=mu).impulses
        answer = by_island.predict(bodies, mixed, world, 0, friction=mu)
        from_route = np.all(answer.impulses == route, axis=1)
        from_box2d = np.all(answer.impulses == mixed["builtin"], axis=1)
        assert (from_route | from_box2d).all()
        for i in np.unique(islands.point):  # an island is served whole from one start
            on = islands.point == i
            assert from_route[on].all() or from_box2d[on].all()
        differ = np.any(route != mixed["builtin"], axis=1)
        if from_box2d[largest].all() and differ[largest].any() and (from_route & differ)[~largest].any():
            parted += 1
            assert answer.served_by is None  # the route's, on the islands it won
        engine.solve()
    assert parted > 0


def test_a_route_with_repairs_serves_each_island_the_soonest_of_its_answer_its_repairs_and_box2ds(tmp_path):
    """With repairs, the route's answer is repaired (relabelled off its own motion and solved
    again) and each island served whichever start stops it soonest: never later than the route
    without them, and on the zoo's stacks of boxes settling, where the classifier labels a landing
    box's points wrong, much sooner."""
    import shutil
    from pathlib import Path

    from bench.inprocess import declared_world
    from deepcontact.faces import island_sweeps_to_stop
    from server.predictors import load_model
    from simclient import worlds

    for name in ("contact-modes-zoo.json", "contact-modes-zoo.onnx"):
        shutil.copy(Path(__file__).parents[2] / "models" / name, tmp_path)
    settings = dict(against_builtin=True, check_sweeps=200, check_stop=True, by_island=True, rounds=100)
    repaired = load_model(face_card(tmp_path, "repaired", "contact-modes-zoo", repairs=3, **settings))
    plain = load_model(face_card(tmp_path, "plain", "contact-modes-zoo", **settings))
    spec = worlds.WorldSpec("simclient.zoo:stack")
    engine = worlds.build(spec, 850)
    world = declared_world(spec, engine)
    sweeps = {"repaired": 0, "plain": 0}
    for _ in range(60):
        engine.collide()
        bodies, points = engine.bodies(), engine.contacts()
        if len(points):
            mu = points["friction"].astype(np.float32)
            restitution = engine.point_restitution(points)
            answers = {name: model.predict(bodies, points, world, 0, friction=mu, restitution=restitution).impulses
                       for name, model in (("repaired", repaired), ("plain", plain))}
            # On the server's copy of the step, each island stopped by the repaired route's choice
            # no later than by the plain one's, so the step too.
            counts = island_sweeps_to_stop(bodies, points, np.stack([answers["repaired"], answers["plain"]]),
                                           mu.astype(np.float64), world.physics, world.tolerance, 200,
                                           restitution=restitution)[0]
            assert counts[0] <= counts[1]
            for name, x in answers.items():  # Box2D's own count from each
                sweeps[name] += engine.trial(np.ascontiguousarray(x[:, 0], np.float32),
                                             np.ascontiguousarray(x[:, 1], np.float32))
            b = engine.builtin_start()
            engine.set_warm_start(*b)
        engine.solve()
    assert sweeps["repaired"] < 0.7 * sweeps["plain"], sweeps


def test_a_route_with_min_rounds_fits_at_its_fewest_rounds_and_ends_its_rounds_before_the_check(
        tmp_path, thesis_steps):
    """With min_rounds, a step with a deadline takes the route where the route is expected to end
    in that many admission rounds (the route's cost is learned so), and its admission runs rounds
    past them only while the check after it would still end by the deadline: a large step gets
    fewer rounds rather than Box2D's start. Without a deadline, or with room, every round runs."""
    import time

    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = thesis_world(world_msg)
    bodies, points = steps[0]
    cold = points.copy()
    cold["builtin"] = 0.0  # no warm start: the route's answer, admitted or not, beats it
    mu = np.full(len(points), 0.5, np.float32)
    settings = dict(rounds=200, rho=1000.0, solver="dual", against_builtin=True, check_sweeps=12)
    fewest = load_model(face_card(tmp_path, "fewest", classifier, min_rounds=5, **settings))
    whole = load_model(face_card(tmp_path, "whole", classifier, **settings))
    assert fewest.settings["min_rounds"] == 5 and whole.settings["min_rounds"] is None
    unhurried = fewest.predict(bodies, cold, world, 0, friction=mu).impulses
    np.testing.assert_array_equal(unhurried, whole.predict(bodies, cold, world, 0, friction=mu).impulses)
    with_room = fewest.predict(bodies, cold, world, 0, friction=mu, deadline=time.perf_counter() + 60.0)
    assert with_room.served_by is None
    np.testing.assert_array_equal(with_room.impulses, unhurried)
    # A check seen to take longer than the budget leaves no time for rounds: the solve's own answer.
    for _ in range(4):
        fewest.sweep_cost.observe(len(points), 100.0)  # s a sweep
        whole.sweep_cost.observe(len(points), 100.0)
    hurried = fewest.predict(bodies, cold, world, 0, friction=mu, deadline=time.perf_counter() + 60.0)
    assert hurried.served_by is None and not np.allclose(hurried.impulses, unhurried)
    # Without min_rounds the rounds run to the deadline itself, as before.
    np.testing.assert_array_equal(
        whole.predict(bodies, cold, world, 0, friction=mu, deadline=time.perf_counter() + 60.0).impulses, unhurried)
    # The route seen to take longer than the budget at its fewest rounds is not taken.
    for _ in range(4):
        fewest.cost.observe(len(points), 100.0)
    assert fewest.predict(bodies, cold, world, 0, friction=mu, deadline=time.perf_counter() + 60.0).served_by \
        == "builtin"


def test_a_route_with_carry_keeps_its_admission_in_the_streams_memory(tmp_path, thesis_steps):
    """With carry, the route's admission goes on along a stream (the memory the server keeps for
    it and its model): each step's state is kept under the route's name, the next step begins
    there, and a step alone (no memory) is the route without carry."""
    from deepcontact.admission import AdmissionCarry
    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = thesis_world(world_msg)
    carried = load_model(face_card(tmp_path, "carried", classifier, rounds=3, rho=1000.0, solver="dual", carry=True))
    plain = load_model(face_card(tmp_path, "plain", classifier, rounds=3, rho=1000.0, solver="dual"))
    assert carried.takes_memory
    memory, differ = {}, 0
    for k, (bodies, points) in enumerate(steps):
        mu = np.full(len(points), 0.5, np.float32)
        along = carried.predict(bodies, points, world, k, friction=mu, memory=memory)
        alone = carried.predict(bodies, points, world, k, friction=mu)
        np.testing.assert_array_equal(alone.impulses, plain.predict(bodies, points, world, k, friction=mu).impulses)
        if k == 0:  # nothing kept yet: the cold route
            np.testing.assert_array_equal(along.impulses, alone.impulses)
        differ += not np.array_equal(along.impulses, alone.impulses)
        assert isinstance(memory["carried"], AdmissionCarry)
    assert differ > 0


def test_a_step_declined_whole_for_its_joints_is_served_box2ds_start_by_builtin(thesis_steps):
    from server.joints import ALL_JOINTED, predict_around_joints
    from server.predictors import ConstantPredictor, Prediction

    world_msg, steps = thesis_steps
    bodies, points = steps[0]
    chain = np.stack([np.arange(1, len(bodies) - 1), np.arange(2, len(bodies))], 1)  # every body on a joint
    answer = predict_around_joints(ConstantPredictor("bad", 50.0, 50.0), bodies, points, chain,
                                   thesis_world(world_msg), 0)
    assert isinstance(answer, Prediction) and answer.served_by == ALL_JOINTED == "builtin" and answer.stages == {}
    np.testing.assert_array_equal(answer.impulses, points["builtin"])
    free = predict_around_joints(ConstantPredictor("bad", 50.0, 50.0), bodies, points, chain[:1],
                                 thesis_world(world_msg), 0)
    assert free.served_by is None and (free.impulses == 50.0).any()


def thesis_only_and_denser(tmp_path, thesis_steps):
    """The shipped classifier as "thesis-only" in tmp_path (trained_on: the thesis world's
    envelope alone) and a thesis step with it at ten times the density: (world, bodies, points,
    friction (P,), dense bodies, dense points), every mass, inertia and Box2D start times ten."""
    import json

    from deepcontact.envelope import Envelope

    classifier = shipped_classifier(tmp_path)
    card = json.loads((tmp_path / f"{classifier}.json").read_text())
    card.update(name="thesis-only", trained_on=Envelope().to_dict())
    (tmp_path / "thesis-only.json").write_text(json.dumps(card))
    world_msg, steps = thesis_steps
    bodies, points = steps[0]
    dense_bodies, dense_points = bodies.copy(), points.copy()
    dense_bodies["mass"] *= 10
    dense_bodies["inertia"] *= 10
    dense_points["builtin"] *= 10
    return (thesis_world(world_msg), bodies, points, np.full(len(points), 0.5, np.float32), dense_bodies,
            dense_points)


def test_a_route_that_rescales_labels_a_denser_step_as_the_step_it_scales_and_solves_it_in_its_own_units(
        tmp_path, thesis_steps):
    """Ten times the density is the same contact problem with every mass and impulse ten times
    larger: a card with rescale labels it as the thesis step it scales, and its answer is that
    step's ten times over; the reply still calls the step unfamiliar."""
    from server.predictors import load_model

    world, bodies, points, mu, dense_bodies, dense_points = thesis_only_and_denser(tmp_path, thesis_steps)
    rescaled = load_model(face_card(tmp_path, "rescaled", "thesis-only", rescale=True))
    checked = load_model(face_card(tmp_path, "checked", "thesis-only", against_builtin=True))
    at_scale = checked.predict(bodies, points, world, 0, friction=mu)
    dense = rescaled.predict(dense_bodies, dense_points, world, 0, friction=mu)
    assert dense.unfamiliar is not None and "density" in dense.unfamiliar
    assert dense.served_by == at_scale.served_by
    np.testing.assert_allclose(dense.impulses, 10 * at_scale.impulses, rtol=1e-3, atol=1e-4)
    # Half the size at the same density: every length halved, a quarter of the mass, the same
    # velocities. The same problem in other units, so a quarter of the answer.
    small_bodies, small_points = bodies.copy(), points.copy()
    small_bodies["position"] /= 2
    small_bodies["radius"] /= 2
    small_bodies["mass"] /= 4
    small_bodies["inertia"] /= 16
    small_bodies["angular_velocity"] *= 2
    small_points["point"] /= 2
    small_points["separation"] /= 2
    small_points["builtin"] /= 4
    small = rescaled.predict(small_bodies, small_points, world, 0, friction=mu)
    assert small.unfamiliar is not None and "radius" in small.unfamiliar and small.served_by == at_scale.served_by
    np.testing.assert_allclose(small.impulses, at_scale.impulses / 4, rtol=1e-3, atol=1e-5)
    # Without rescale the route declines the denser step: Box2D's start (no fallback here).
    plain = load_model(face_card(tmp_path, "plain", "thesis-only")).predict(dense_bodies, dense_points, world, 0,
                                                                            friction=mu)
    assert plain.served_by == "builtin"


def test_a_fallback_network_that_knows_a_step_only_rescaled_answers_it_rescaled_in_the_steps_own_units(
        tmp_path, thesis_steps):
    """Where a card that rescales does not serve a step itself (here: never in time), a fallback
    network trained at one scale that knows the step only rescaled into that scale is asked so,
    and its answer comes back in the step's units: ten times the density, ten times its answer on
    the thesis step. The same card without rescale gives Box2D's start there."""
    import time

    from server.predictors import load_model

    world, bodies, points, mu, dense_bodies, dense_points = thesis_only_and_denser(tmp_path, thesis_steps)
    answers = {}
    for rescale in (True, False):
        route = load_model(face_card(tmp_path, f"late-{rescale}", "thesis-only", rescale=rescale, fallback="thesis-only"))
        route.cost = NeverInTime()
        answers[rescale] = route.predict(dense_bodies, dense_points, world, 0, friction=mu,
                                         deadline=time.perf_counter() + 1.0)
    at_scale = route.fallback.predict(bodies, points, world, 0, None, friction=mu)
    assert answers[True].served_by == "thesis-only"
    np.testing.assert_allclose(answers[True].impulses, 10 * at_scale.impulses, rtol=1e-3, atol=1e-4)
    assert answers[False].served_by == "builtin"
    np.testing.assert_array_equal(answers[False].impulses, dense_points["builtin"])


def test_a_route_with_check_work_checks_a_larger_step_with_fewer_sweeps(tmp_path, thesis_steps, monkeypatch):
    """With check_work W, each start's side of the check plays no more than W / points sweeps
    (the card's check_sweeps where that is fewer): a large step's check costs about what a
    smaller one's does, where 200 sweeps from each start were most of a 700-point step's time."""
    import server.face_route
    from server.predictors import load_model

    classifier = shipped_classifier(tmp_path)
    world_msg, steps = thesis_steps
    world = dataclasses.replace(thesis_world(world_msg), tolerance=1e-6)  # neither start stops early
    checked = load_model(face_card(tmp_path, "checked", classifier, against_builtin=True, check_sweeps=200,
                                   check_stop=True, check_work=8_000))
    played = []
    real = server.face_route._sweep_change

    def recorded(bodies, points, start, friction, physics, sweeps, *args, **kwargs):
        played.append((len(points), sweeps))
        return real(bodies, points, start, friction, physics, sweeps, *args, **kwargs)

    monkeypatch.setattr(server.face_route, "_sweep_change", recorded)
    for bodies, points in steps[:: max(1, len(steps) // 8)]:
        checked._beats_builtin(bodies, points, points["impulse"].astype(np.float64),
                               points["friction"].astype(np.float64), world)
    assert len({n_points for n_points, _ in played}) > 1  # steps of several sizes
    for n_points, sweeps in played:
        assert 1 <= sweeps <= min(200, 8_000 // n_points)
    assert max(s for _, s in played) > min(s for _, s in played)  # the smaller steps played more


class NeverInTime:
    """A route's cost estimate (server.deadline.CostBySize) by which no step fits its deadline."""

    def fits(self, *args, **kwargs):
        return False

    def observe(self, *args):
        pass


def late_route(tmp_path, thesis_steps, name, **face):
    """A dual-solver face route over the shipped classifier with these face settings, whose
    classifier is expected never to fit a deadline, and a thesis step to serve it:
    (route, world, bodies, points, friction (P,)). Skips where the host has one core (labels are
    held only where the server has a core to spare)."""
    import os

    from server.predictors import load_model

    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("labels are held only where the server has a core to spare")
    world_msg, steps = thesis_steps
    bodies, points = steps[-1]
    route = load_model(face_card(tmp_path, name, shipped_classifier(tmp_path), solver="dual", **face))
    route.cost = NeverInTime()
    return route, thesis_world(world_msg), bodies, points, np.full(len(points), 0.5, np.float32)


def test_a_step_too_large_to_label_in_time_is_solved_on_the_labels_held_for_its_points(tmp_path, thesis_steps):
    """With held_labels, a step that the route would not end by its deadline with its classifier
    is answered by the fallback (here Box2D's start) and labelled after the reply on the spare
    core; the stream's next step with the same points is solved on those labels, without the
    classifier, and the reply says so."""
    import time

    from server.held_labels import HeldLabels
    from server.predictors import load_model

    route, world, bodies, points, mu = late_route(tmp_path, thesis_steps, "held", held_labels=True)
    memory: dict = {}
    first = route.predict(bodies, points, world, 7, friction=mu, deadline=time.perf_counter() + 1.0, memory=memory)
    assert first.served_by == "builtin"
    held = memory["held:held"]
    assert isinstance(held, HeldLabels)
    waited = time.perf_counter()
    while held.lookup(points, 8) is None and time.perf_counter() - waited < 10.0:  # labelled in the background
        time.sleep(0.01)
    second = route.predict(bodies, points, world, 8, friction=mu, deadline=time.perf_counter() + 1.0, memory=memory)
    assert second.served_by == "held (held labels)"
    assert second.stages["inference"] == 0.0  # no classifier on the step itself
    alone = load_model(face_card(tmp_path, "alone", shipped_classifier(tmp_path), solver="dual"))
    np.testing.assert_allclose(second.impulses, alone.predict(bodies, points, world, 8, friction=mu).impulses,
                               atol=1e-6)  # the same labels, the same answer


def test_with_held_from_builtin_a_step_with_no_labels_held_is_solved_on_box2ds_start_read_as_labels(tmp_path,
                                                                                                    thesis_steps):
    """held_from_builtin: where the route would not end in time with its classifier and no labels
    are held yet (a stream's first step, or points new on a step), Box2D's start read as labels
    (its face, deepcontact.faces.face_labels) stands in for the classifier's."""
    import time

    from deepcontact.faces import contact_face, face_labels

    route, world, bodies, points, mu = late_route(tmp_path, thesis_steps, "fill", held_labels=True,
                                                  held_from_builtin=True)
    first = route.predict(bodies, points, world, 7, friction=mu, deadline=time.perf_counter() + 1.0, memory={})
    assert first.served_by == "fill (held labels)"
    assert first.stages["inference"] == 0.0  # no classifier on the step itself
    labels = face_labels(contact_face(points["builtin"], mu))
    on_builtin = route._route(bodies, points, world, 7, None, mu, None, time.thread_time(), labels=labels)
    np.testing.assert_allclose(first.impulses, on_builtin.impulses, atol=1e-6)
