"""Nothing a client sends can crash the server or corrupt another stream."""

from __future__ import annotations

import grpc
import numpy as np
import pytest
from google.protobuf.message import DecodeError
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from deepcontact import wire
from deepcontact.v1 import warmstart_pb2 as pb

MODELS = st.sampled_from(["tiny", "tiny-fixed", "zero", "random", "bad", "grid-identity", "", "nope"])
FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=32)


@st.composite
def malformed_requests(draw):
    r = pb.StepRequest(step=draw(st.integers(0, 2**64 - 1)), model=draw(MODELS))
    if draw(st.booleans()):
        r.world.CopyFrom(pb.World(x_min=draw(FLOATS), y_min=draw(FLOATS), x_max=draw(FLOATS), y_max=draw(FLOATS),
                                  edge_count=draw(st.integers(0, 5)), edges=draw(st.binary(max_size=96))))
    r.body_count = draw(st.integers(0, 40))
    r.point_count = draw(st.integers(0, 40))
    for field, cols in (("bodies", 8), ("points", 4), ("builtin", 2), ("impulses", 2)):
        count = r.body_count if field == "bodies" else r.point_count
        if draw(st.booleans()):  # well-sized, values anywhere (outside the domain, NaN, huge)
            values = draw(st.lists(st.floats(-1e6, 1e6, width=32) | FLOATS, min_size=count * cols,
                                   max_size=count * cols))
            setattr(r, field, np.asarray(values, np.float32).tobytes())
        else:
            setattr(r, field, draw(st.binary(max_size=64)))
    return r


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(garbage=malformed_requests(), raw=st.binary(max_size=200))
def test_random_and_malformed_messages_never_take_the_server_down(stub, server, thesis_steps, garbage, raw):
    for call in (lambda: stub.Predict(garbage), lambda: list(stub.Stream(iter([garbage, garbage])))):
        try:
            call()
        except grpc.RpcError as err:
            assert err.code() in (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND)
    # Raw bytes: what does not parse as a StepRequest is INVALID_ARGUMENT, on either RPC.
    try:
        pb.StepRequest.FromString(raw)
        expected = (grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND)
    except DecodeError:
        expected = (grpc.StatusCode.INVALID_ARGUMENT,)
    with grpc.insecure_channel(server.address) as channel:
        for call in (lambda: channel.unary_unary("/deepcontact.v1.WarmStart/Predict")(raw, timeout=5),
                     lambda: list(channel.stream_stream("/deepcontact.v1.WarmStart/Stream")(iter([raw]), timeout=5))):
            with pytest.raises(grpc.RpcError) as err:
                call()
            assert err.value.code() in expected
    # And a valid step is still answered correctly.
    world, steps = thesis_steps
    bodies, points = steps[0]
    reply = stub.Predict(wire.encode_step(1, "bad", bodies, points, world=world))
    assert (wire.decode_impulses(reply)[0] == 50).all()
