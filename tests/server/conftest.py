"""A real server on loopback with a small real ONNX model (built with onnx.helper,
so the tests need no TensorFlow; the model folder and the thesis steps to send
it are in tests/conftest.py)."""

from __future__ import annotations

import grpc
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from deepcontact.gridspec import GridSpec
from deepcontact.modelcard import ModelCard
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.serve import Server


def write_conv_model(folder, name="tiny", fixed_grid=False, combine="replace", seed=0, inputs=None, weights=None):
    """A 1x1 convolution from the input channels (default the thesis's 6) to 2 outputs, with its card;
    weights: every weight this value (e.g. NaN, a model gone wrong) instead of random ones."""
    spec = GridSpec.thesis() if inputs is None else GridSpec.thesis(inputs=tuple(inputs))
    cin, cout = len(spec.inputs), len(spec.targets)
    rng = np.random.default_rng(seed)
    w = rng.normal(0, 0.1, (cout, cin, 1, 1)).astype(np.float32)
    if weights is not None:
        w[:] = weights
    nodes = [
        helper.make_node("Transpose", ["grids"], ["nchw"], perm=[0, 3, 1, 2]),
        helper.make_node("Conv", ["nchw", "w"], ["y"]),
        helper.make_node("Transpose", ["y"], ["impulses"], perm=[0, 2, 3, 1]),
    ]
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info("grids", TensorProto.FLOAT, ["batch", "ny", "nx", cin])],
        [helper.make_tensor_value_info("impulses", TensorProto.FLOAT, ["batch", "ny", "nx", cout])],
        [helper.make_tensor("w", TensorProto.FLOAT, w.shape, w.ravel())],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, folder / f"{name}.onnx")
    card = ModelCard(name=name, kind="test-conv", onnx_file=f"{name}.onnx", gridspec=spec,
                     fixed_grid=fixed_grid, combine=combine)
    card.save(folder / f"{name}.json")
    return card


@pytest.fixture(scope="session")
def server(model_dir):
    srv = Server(models=model_dir, bind="127.0.0.1:0").start()
    yield srv
    srv.stop()


@pytest.fixture()
def stub(server):
    with grpc.insecure_channel(server.address) as channel:
        yield pb_grpc.WarmStartStub(channel)
