"""The warm-start service over real gRPC on loopback, with real ONNX Runtime."""

from __future__ import annotations

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from deepcontact import wire
from deepcontact.gridspec import GridSpec
from deepcontact.modelcard import ModelCard
from deepcontact.features import world_to_grids
from deepcontact.transfer import g2p, p2g
from deepcontact.v1 import warmstart_pb2 as pb
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from commands import main
from server.serve import Server
from server.service import Limits


def request(world, bodies, points, model, step=0, **kw):
    return wire.encode_step(step, model, bodies, points, world=world, **kw)


def test_list_models_names_models_and_providers(stub):
    models = {m.name: m for m in stub.ListModels(pb.ListModelsRequest()).models}
    assert {"tiny", "tiny-fixed", "zero", "random", "bad", "grid-identity"} <= set(models)
    assert models["tiny-fixed"].fixed_grid and not models["tiny"].fixed_grid
    assert GridSpec.from_json(models["tiny"].gridspec_json).shape == (61, 61)


def test_predict_runs_p2g_onnx_g2p_like_training(stub, thesis_steps, model_dir):
    world, steps = thesis_steps
    bodies, points = steps[0]
    reply = stub.Predict(request(world, bodies, points, "tiny", step=7))
    normal, tangent = wire.decode_impulses(reply)
    assert reply.step == 7 and reply.point_count == len(points)

    # The same computation done here, from the card, without the server.
    import onnxruntime as ort

    card = ModelCard.load(model_dir / "tiny.json")
    spec = card.gridspec
    sent_bodies, sent_points = wire.decode_step(request(world, bodies, points, "tiny"),
                                                max_bodies=10**6, max_points=10**6)
    x = spec.normalize(world_to_grids(sent_bodies, sent_points, spec), "inputs")[None]
    y = ort.InferenceSession(str(model_dir / "tiny.onnx")).run(None, {"grids": x})[0][0]
    expected, _ = g2p(spec.denormalize(y, "targets"), points["point"], spec)
    np.testing.assert_allclose(np.stack([normal, tangent], 1), expected, rtol=1e-5, atol=1e-6)
    t = reply.timings
    assert t.total_us >= t.p2g_us + t.inference_us + t.g2p_us > 0
    assert t.features_us == t.solve_us == t.admit_us == 0  # a grid model's stages only


def test_stream_answers_in_order_with_the_world_sent_once(stub, thesis_steps):
    world, steps = thesis_steps

    def requests():
        for k, (bodies, points) in enumerate(steps):
            yield request(world if k == 0 else None, bodies, points, "tiny", step=100 + k)

    replies = list(stub.Stream(requests()))
    assert [r.step for r in replies] == [100 + k for k in range(len(steps))]
    assert [r.point_count for r in replies] == [len(p) for _, p in steps]


def test_providers(stub, thesis_steps):
    world, steps = thesis_steps
    bodies, points = steps[0]
    zero = wire.decode_impulses(stub.Predict(request(world, bodies, points, "zero")))
    assert not np.any(zero[0]) and not np.any(zero[1])
    bad = wire.decode_impulses(stub.Predict(request(world, bodies, points, "bad")))
    assert (bad[0] == 50).all() and (bad[1] == 50).all()
    r1 = wire.decode_impulses(stub.Predict(request(world, bodies, points, "random", step=3)))
    r2 = wire.decode_impulses(stub.Predict(request(world, bodies, points, "random", step=3)))
    np.testing.assert_array_equal(r1[0], r2[0])  # seeded per step
    assert (0 <= r1[0]).all() and (r1[0] <= 5).all() and (np.abs(r1[1]) <= 2).all()
    # grid-identity: the request's impulses through P2G and back, as the transfer does it.
    final = points["impulse"]
    got = wire.decode_impulses(stub.Predict(request(world, bodies, points, "grid-identity", impulses=final)))
    spec = GridSpec.thesis()
    expected, _ = g2p(p2g(points["point"], final, spec)[0], points["point"], spec)
    np.testing.assert_allclose(np.stack(got, 1), expected, rtol=1e-5, atol=1e-6)


def test_a_fixed_size_model_names_both_sizes(stub, thesis_steps):
    _, steps = thesis_steps
    bodies, points = steps[0]
    big = wire.encode_world((0, 0), (20, 10))
    with pytest.raises(grpc.RpcError) as err:
        stub.Predict(request(big, bodies, points, "tiny-fixed"))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert "61x61" in err.value.details() and "41x81" in err.value.details()
    # The any-size model serves the same world.
    assert stub.Predict(request(big, bodies, points, "tiny")).point_count == len(points)

@pytest.mark.parametrize("model", ["tiny", "grid-identity"])
def test_a_domain_too_large_to_grid_is_refused_not_allocated(stub, thesis_steps, model):
    # 1 km square at 0.25 m: 16 M nodes, 400 MB a channel. Before the bound, the
    # server tried to allocate it (CI's fuzz test drew such a domain and was killed).
    _, steps = thesis_steps
    bodies, points = steps[0]
    huge = wire.encode_world((-500, -500), (500, 500))
    for call in (lambda r: stub.Predict(r), lambda r: list(stub.Stream(iter([r])))):
        with pytest.raises(grpc.RpcError) as err:
            call(request(huge, bodies, points, model))
        assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert "4001x4001" in err.value.details() and "262,144 nodes" in err.value.details()
    # The server still answers a world of the usual size.
    world = wire.encode_world((0, 0), (15, 15))
    assert stub.Predict(request(world, bodies, points, model)).point_count == len(points)


def test_the_grid_bound_is_the_operators_to_set(model_dir, thesis_steps):
    _, steps = thesis_steps
    bodies, points = steps[0]
    srv = Server(models=model_dir, limits=Limits(max_grid_nodes=61 * 61)).start()  # the thesis box and no more
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            thesis = wire.encode_world((0, 0), (15, 15))
            assert stub.Predict(request(thesis, bodies, points, "tiny")).point_count == len(points)
            with pytest.raises(grpc.RpcError) as err:
                stub.Predict(request(wire.encode_world((0, 0), (16, 16)), bodies, points, "tiny"))
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "65x65" in err.value.details() and "3,721 nodes" in err.value.details()
    finally:
        srv.stop()
    assert main(["serve", "--models", str(model_dir), "--max-grid-nodes", "0"]) == 2


@pytest.mark.parametrize("mutate, code, words", [
    (lambda r: setattr(r, "model", "nope"), grpc.StatusCode.NOT_FOUND, "nope"),
    (lambda r: setattr(r, "point_count", r.point_count + 1), grpc.StatusCode.INVALID_ARGUMENT, "points"),
    (lambda r: setattr(r, "bodies", r.bodies[:-4]), grpc.StatusCode.INVALID_ARGUMENT, "bodies"),
    (lambda r: setattr(r, "points", np.full(r.point_count * 4, np.nan, np.float32).tobytes()),
     grpc.StatusCode.INVALID_ARGUMENT, "NaN"),
    (lambda r: setattr(r, "body_count", 10**7), grpc.StatusCode.INVALID_ARGUMENT, "limit"),
    (lambda r: r.ClearField("world"), grpc.StatusCode.INVALID_ARGUMENT, "world"),
    (lambda r: setattr(r.world, "x_max", -1.0), grpc.StatusCode.INVALID_ARGUMENT, "domain"),
    (lambda r: (setattr(r, "joint_count", 2), setattr(r, "joint_bodies", np.zeros(3, np.int32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "joint_bodies"),
    (lambda r: (setattr(r, "joint_count", 1), setattr(r, "joint_bodies", np.array([0, 10**6], np.int32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "rows outside"),
    (lambda r: (setattr(r, "joint_count", 1), setattr(r, "joint_bodies", np.array([0, 1], np.int32).tobytes()),
                setattr(r, "joint_revolute", np.ones(6, np.float32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "joint_revolute"),
    (lambda r: (setattr(r, "joint_count", 1), setattr(r, "joint_bodies", np.array([0, 1], np.int32).tobytes()),
                setattr(r, "joint_revolute", np.full(7, 5.0, np.float32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "kind of joint"),
    (lambda r: (setattr(r, "joint_count", 1), setattr(r, "joint_bodies", np.array([0, 1], np.int32).tobytes()),
                setattr(r, "joint_revolute", np.ones(7, np.float32).tobytes()),
                setattr(r, "joint_limits", np.full(8, 4.0, np.float32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "joint_limits"),
    (lambda r: (setattr(r, "joint_count", 1), setattr(r, "joint_bodies", np.array([0, 1], np.int32).tobytes()),
                setattr(r, "joint_revolute", np.full(7, 3.0, np.float32).tobytes())),
     grpc.StatusCode.INVALID_ARGUMENT, "need their limits"),
])
def test_bad_requests_get_a_status_that_names_the_problem(stub, thesis_steps, mutate, code, words):
    world, steps = thesis_steps
    r = request(world, *steps[0], "tiny")
    mutate(r)
    with pytest.raises(grpc.RpcError) as err:
        stub.Predict(r)
    assert err.value.code() == code
    assert words in err.value.details()


def test_a_stream_without_a_world_is_refused(stub, thesis_steps):
    _, steps = thesis_steps
    with pytest.raises(grpc.RpcError) as err:
        list(stub.Stream(iter([request(None, *steps[0], "tiny")])))
    assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT


def test_health_reports_serving(server):
    with grpc.insecure_channel(server.address) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        for service in ("", "deepcontact.v1.WarmStart"):
            status = health.Check(health_pb2.HealthCheckRequest(service=service)).status
            assert status == health_pb2.HealthCheckResponse.SERVING


def test_decode_time_starts_when_grpc_parses_the_request(thesis_steps):
    # gRPC parses a request in the thread that then runs the handler; the
    # step's decode time includes that parse and whatever gRPC does between.
    import time

    from server.predictors import providers
    from server.service import WarmStartService, _parse_step

    world, steps = thesis_steps
    service = WarmStartService(providers())
    stream_world = service._world(world)
    raw = request(world, *steps[0], "zero").SerializeToString()
    parsed = _parse_step(raw)
    time.sleep(0.02)
    assert service._step(parsed, stream_world)[0].timings.decode_us >= 20_000
    # Consumed once: a step that was not parsed here is timed from its own start.
    assert service._step(parsed, stream_world)[0].timings.decode_us < 20_000


def test_a_model_reading_contact_velocities_and_the_last_step_is_served_what_training_saw(tmp_path, thesis_steps):
    from deepcontact.kinematics import Physics
    from server.serve import Server
    from tests.server.conftest import write_conv_model

    inputs = ("mass", "vn_builtin", "separation", "previous_builtin_normal")
    card = write_conv_model(tmp_path, "kinematic", inputs=inputs)
    world, steps = thesis_steps
    srv = Server(models=tmp_path).start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            replies = list(stub.Stream(iter([request(world if k == 0 else None, b, p, "kinematic", step=k,
                                                     builtin=p["builtin"]) for k, (b, p) in enumerate(steps[:2])])))
            # The second step was served with the first one's points as its previous step.
            import onnxruntime as ort

            spec = card.gridspec
            grid = world_to_grids(*steps[1], spec, previous=steps[0][1], physics=Physics.thesis())
            y = ort.InferenceSession(str(tmp_path / "kinematic.onnx")).run(None, {"grids": spec.normalize(grid)[None]})
            expected, _ = g2p(spec.denormalize(y[0][0], "targets"), steps[1][1]["point"], spec)
            np.testing.assert_allclose(np.stack(wire.decode_impulses(replies[1]), 1), expected, rtol=1e-4, atol=1e-6)
            # A client pricing several models on one state sends one request per model for the
            # same step: each still sees the step before, not the request before.
            interleaved = [request(world if k == 0 else None, b, p, model, step=k, builtin=p["builtin"])
                           for k, (b, p) in enumerate(steps[:2]) for model in ("zero", "kinematic")]
            again = list(stub.Stream(iter(interleaved)))
            np.testing.assert_array_equal(np.stack(wire.decode_impulses(again[3]), 1),
                                          np.stack(wire.decode_impulses(replies[1]), 1))
            # A client that sends neither the points' bodies nor the physics is told what is missing.
            old = request(world, *steps[0], "kinematic", builtin=steps[0][1]["builtin"])
            old.ClearField("point_bodies")
            old.world.dt = 0.0
            with pytest.raises(grpc.RpcError) as err:
                stub.Predict(old)
            assert err.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert "each point's two bodies" in err.value.details() and "time step and gravity" in err.value.details()
    finally:
        srv.stop()


def test_a_stream_that_declares_a_new_world_gets_its_model_ready_before_the_first_step(tmp_path, thesis_steps):
    from deepcontact.kinematics import Physics
    from server.serve import Server
    from simclient.client import WarmStartClient
    from tests.server.conftest import write_conv_model

    # A model that needs more than bodies and points: the declaring message carries none of it.
    card = write_conv_model(tmp_path, "needy", combine="residual", inputs=("mass", "vn", "builtin_normal"))
    world, steps = thesis_steps
    srv = Server(models=tmp_path, bind="127.0.0.1:0").start()
    try:
        needy = next(m for m in srv.models if m.name == "needy")
        assert (1, 61, 61, 3) in needy.warm_shapes  # the card's grid, at start
        wide = wire.encode_world((0.0, 0.0), (25.0, 15.0), physics=Physics.thesis())
        shape = (1, *GridSpec.for_domain((0.0, 0.0), (25.0, 15.0), card.gridspec.resolution,
                                         card.gridspec.h).shape, 3)
        assert shape not in needy.warm_shapes
        with WarmStartClient(srv.address, world=wide) as client:
            assert client.declare("needy", timeout=10.0)  # a message without points: an empty reply
            assert shape in needy.warm_shapes
            bodies, points = steps[-1]
            reply = client.step(wire.encode_step(1, "needy", bodies, points, builtin=points["builtin"]), timeout=10.0)
            assert reply.point_count == len(points) and client.reconnects == 0
    finally:
        srv.stop()


def test_points_on_jointed_bodies_get_box2ds_start_and_the_model_answers_the_rest(stub, thesis_steps):
    world, steps = thesis_steps
    bodies, points = steps[0]
    builtin = points["builtin"]
    plain = np.stack(wire.decode_impulses(stub.Predict(request(world, bodies, points, "tiny", builtin=builtin))), 1)
    touched = np.bincount(np.concatenate([points["body_a"], points["body_b"]]), minlength=len(bodies))
    touched[0] = 0  # the box is static: a joint to it binds only the other body
    a, b = np.argsort(touched)[-2:]  # the two bodies with the most contacts, on one joint
    reply = stub.Predict(request(world, bodies, points, "tiny", builtin=builtin, joints=np.array([[a, b]])))
    got = np.stack(wire.decode_impulses(reply), 1)
    on_joint = np.isin(points["body_a"], [a, b]) | np.isin(points["body_b"], [a, b])
    assert on_joint.any() and not on_joint.all()
    np.testing.assert_array_equal(got[on_joint], builtin[on_joint])
    assert np.isfinite(got).all() and not np.array_equal(got[~on_joint], builtin[~on_joint])
    assert not reply.served_by
    # The model sees the rest after the fixed impulses: near the joint its answer moves.
    assert not np.array_equal(got[~on_joint], plain[~on_joint])


def test_a_step_whose_every_point_is_on_a_joint_is_answered_with_box2ds_start(stub, thesis_steps):
    world, steps = thesis_steps
    bodies, points = steps[0]
    chain = np.stack([np.arange(1, len(bodies) - 1), np.arange(2, len(bodies))], 1)  # every body on a joint
    reply = stub.Predict(request(world, bodies, points, "tiny", builtin=points["builtin"], joints=chain))
    np.testing.assert_array_equal(np.stack(wire.decode_impulses(reply), 1), points["builtin"])
    assert reply.served_by == "builtin"
    zero = stub.Predict(request(world, bodies, points, "zero", builtin=points["builtin"], joints=chain))
    assert not np.stack(wire.decode_impulses(zero), 1).any()  # a provider answers as it is


def test_the_shipped_default_extrapolates_box2ds_start_along_a_stream_at_jointed_points(thesis_steps):
    """The default's card asks for Box2D's start extrapolated in time at the points no model speaks
    for (face extrapolate_jointed): on a stream's third step, each jointed point carried over all
    three starts at builtin + (builtin - builtin before) where that line would have beaten the copy
    on the step before; the first steps, the other points, and a lone Predict keep Box2D's start."""
    from pathlib import Path

    from simclient.client import WarmStartClient

    world, steps = thesis_steps
    models = Path(__file__).parents[2] / "models"
    srv = Server(models=models, bind="127.0.0.1:0").start()
    try:
        replies = []
        with WarmStartClient(srv.address, world=world) as client:  # the world goes once, on the stream's first step
            for k, (bodies, points) in enumerate(steps[:3]):
                chain = np.stack([np.arange(1, len(bodies) - 1), np.arange(2, len(bodies))], 1)  # every body jointed
                replies.append(client.step(wire.encode_step(k, "default", bodies, points, builtin=points["builtin"],
                                                            friction=np.full(len(points), 0.5, np.float32),
                                                            joints=chain), 10.0))
        for reply, (_, points) in zip(replies[:2], steps):
            np.testing.assert_array_equal(np.stack(wire.decode_impulses(reply), 1), points["builtin"])
        got = np.stack(wire.decode_impulses(replies[2]), 1)
        assert replies[2].served_by == "extrapolated"
        by_key = [dict(zip(p["key"].tolist(), p["builtin"].astype(np.float32))) for _, p in steps[:3]]
        expected, drawn = [], 0
        for key, now in by_key[2].items():
            before, older = by_key[1].get(key), by_key[0].get(key)
            if before is None or older is None or not (now.any() and before.any() and older.any()):
                expected.append(now)
                continue
            d1 = now - before
            d2 = d1 - (before - older)
            line = np.abs(d2).max() < np.abs(d1).max()
            drawn += line
            expected.append(now + d1 if line else now)
        assert drawn > 0
        np.testing.assert_allclose(got, np.array(expected), rtol=1e-6, atol=1e-7)
        bodies, points = steps[2]
        chain = np.stack([np.arange(1, len(bodies) - 1), np.arange(2, len(bodies))], 1)
        with grpc.insecure_channel(srv.address) as channel:  # a step alone has no steps before it
            alone = pb_grpc.WarmStartStub(channel).Predict(
                request(world, bodies, points, "default", step=2, builtin=points["builtin"],
                        friction=np.full(len(points), 0.5, np.float32), joints=chain))
        np.testing.assert_array_equal(np.stack(wire.decode_impulses(alone), 1), points["builtin"])
    finally:
        srv.stop()


def test_a_kinematic_body_travels_with_mass_zero_and_is_decoded_as_kinematic(thesis_steps):
    _, steps = thesis_steps
    bodies, points = steps[0]
    bodies = bodies.copy()
    bodies["type"][5], bodies["mass"][5], bodies["inertia"][5] = 1, 0.0, 0.0  # kinematic, as Box2D exports it
    decoded, _ = wire.decode_step(wire.encode_step(0, "m", bodies, points), max_bodies=10**4, max_points=10**5)
    # Row 0 is the walls' stand-in; the request's bodies follow in order (the box, static, does not travel).
    assert decoded["type"][5] == 1 and (np.delete(decoded["type"][1:], 4) == 2).all()


def test_a_stream_keeps_each_models_memory_of_its_own(tmp_path, thesis_steps):
    """A route with carry (its admission goes on along the stream) answers a stream's steps as
    the same route in process with one memory for the stream; asked about the same states beside
    another model (price:), it keeps its own; a single request (Predict) has none and is answered
    cold."""
    from deepcontact.kinematics import Physics
    from server.predictors import World, load_model
    from server.serve import Server
    from tests.server.test_predictors import face_card, shipped_classifier

    classifier = shipped_classifier(tmp_path)
    face_card(tmp_path, "carried", classifier, rounds=3, rho=1000.0, solver="dual", carry=True)
    world, steps = thesis_steps
    mu = [np.full(len(p), 0.5, np.float32) for _, p in steps]
    srv = Server(models=tmp_path, bind="127.0.0.1:0").start()
    try:
        with grpc.insecure_channel(srv.address) as channel:
            stub = pb_grpc.WarmStartStub(channel)
            asks = [request(world if k == 0 else None, b, p, model, step=k, builtin=p["builtin"], friction=mu[k])
                    for k, (b, p) in enumerate(steps) for model in ("zero", "carried")]
            served = [np.stack(wire.decode_impulses(r), 1) for r in stub.Stream(iter(asks))][1::2]
            single = np.stack(wire.decode_impulses(stub.Predict(request(
                world, *steps[-1], "carried", step=len(steps) - 1, builtin=steps[-1][1]["builtin"], friction=mu[-1]))), 1)
    finally:
        srv.stop()
    route = load_model(tmp_path / "carried.json")
    declared = World(tuple(map(tuple, wire.decode_world(world)[:2])), Physics.thesis())
    memory = {}
    along = [route.predict(b, p, declared, k, friction=mu[k], memory=memory).impulses for k, (b, p) in enumerate(steps)]
    for got, want in zip(served, along):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)
    cold = route.predict(*steps[-1], declared, len(steps) - 1, friction=mu[-1]).impulses
    np.testing.assert_allclose(single, cold, rtol=1e-5, atol=1e-6)
    assert not np.allclose(along[-1], cold, rtol=1e-5, atol=1e-6)
