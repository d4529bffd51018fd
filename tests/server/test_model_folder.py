"""A models folder is checked as a whole at start: every bad card and ONNX file is
named in one message, or, with --skip-bad-models, logged while the good ones serve."""

from __future__ import annotations

import json
import logging
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import grpc
import pytest

from deepcontact.modelcard import ModelCardError
from deepcontact.v1 import warmstart_pb2 as pb
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server.predictors import load_model, load_models
from server.serve import Server
from tests.server.conftest import write_conv_model

SHIPPED = Path(__file__).parents[2] / "lab" / "models"  # the research store
GARBAGE = b"this is not an ONNX model\n" * 8


def bad_folder(folder: Path) -> Path:
    """A good model `tiny`, an ONNX file of garbage bytes with its card, and a card that is not JSON."""
    write_conv_model(folder, "tiny")
    write_conv_model(folder, "garbage")
    (folder / "garbage.onnx").write_bytes(GARBAGE)
    (folder / "broken.json").write_text('{"name": "broken", ')
    return folder


def test_every_bad_file_is_named_in_one_error(tmp_path):
    with pytest.raises(ModelCardError) as err:
        load_models(bad_folder(tmp_path))
    message = str(err.value)
    assert "\n" not in message
    assert "garbage.onnx: not an ONNX model" in message
    assert "broken.json: not JSON" in message
    assert "garbage.json: names garbage.onnx, which is bad" in message
    assert "tiny" not in message and "3 bad model files" in message


def test_serve_names_them_all_on_one_line_and_exits_2(tmp_path, capsys):
    from commands import main

    assert main(["serve", "--models", str(bad_folder(tmp_path)), "--bind", "127.0.0.1:0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("deepcontact serve: ") and err.count("\n") == 1
    assert "garbage.onnx: not an ONNX model" in err and "broken.json: not JSON" in err
    assert "unexpected error" not in err and "--skip-bad-models" in err


def test_with_skip_bad_models_the_good_models_serve_and_each_bad_file_is_logged(tmp_path):
    folder = bad_folder(tmp_path)
    port_file = tmp_path / "port"
    proc = subprocess.Popen([sys.executable, "-m", "commands", "serve", "--models", str(folder),
                             "--bind", "127.0.0.1:0", "--port-file", str(port_file), "--skip-bad-models",
                             "--grace", "1"],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not port_file.exists():
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with grpc.insecure_channel(f"127.0.0.1:{port_file.read_text().strip()}") as channel:
            names = {m.name for m in pb_grpc.WarmStartStub(channel).ListModels(pb.ListModelsRequest(),
                                                                               timeout=10).models}
        assert "tiny" in names and "zero" in names
        assert not names & {"garbage", "broken"}
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)  # reading stderr meanwhile: a full pipe cannot hold it
        assert proc.returncode == 0
        lines = [json.loads(line) for line in err.splitlines() if line.startswith("{")]
        skipped = {Path(line["file"]).name: line["problem"] for line in lines
                   if line["level"] == "WARNING" and line["msg"].startswith("skipping bad model file")}
        assert set(skipped) == {"garbage.onnx", "garbage.json", "broken.json"}
        assert skipped["broken.json"].startswith("not JSON")
        assert any(line["msg"] == "serving" and "tiny" in line["models"] for line in lines)
    finally:
        if proc.poll() is None:
            proc.kill()


def test_an_alias_of_a_bad_card_a_card_outside_its_folder_and_an_unnamed_onnx_file_are_bad(tmp_path, caplog):
    write_conv_model(tmp_path, "tiny")
    (tmp_path / "target.json").write_text(json.dumps({"name": "target"}))  # lacks most keys
    (tmp_path / "alias.json").write_text(json.dumps({"name": "alias", "alias_of": "target"}))
    card = json.loads((tmp_path / "tiny.json").read_text())
    (tmp_path / "escape.json").write_text(json.dumps({**card, "name": "escape", "onnx_file": "../tiny.onnx"}))
    shutil.copy(tmp_path / "tiny.onnx", tmp_path / "orphan.onnx")
    with pytest.raises(ModelCardError) as err:
        load_models(tmp_path)
    message = str(err.value)
    assert "target.json: model card lacks" in message
    assert "alias.json: an alias of target.json, which is bad" in message
    assert "escape.json: names '../tiny.onnx', not a file name in" in message
    assert "no model card names orphan.onnx" in message
    with caplog.at_level(logging.WARNING, logger="deepcontact.server"):
        served = load_models(tmp_path, skip_bad=True)
    assert [m.name for m in served] == ["tiny"]
    assert {r.file.rsplit("/", 1)[-1] for r in caplog.records} == {"target.json", "alias.json", "escape.json",
                                                                   "orphan.onnx"}


def test_a_face_card_whose_fallback_is_bad_is_bad_too(tmp_path):
    classifier = json.loads((SHIPPED / "face.json").read_text())["alias_of"]
    for name in (f"{classifier}.json", f"{classifier}.onnx"):
        shutil.copy(SHIPPED / name, tmp_path)
    write_conv_model(tmp_path, "fallback")
    (tmp_path / "fallback.onnx").write_bytes(GARBAGE)
    (tmp_path / "face.json").write_text(json.dumps({"name": "face", "alias_of": classifier,
                                                    "face": {"fallback": "fallback"}}))
    with pytest.raises(ModelCardError) as err:
        load_models(tmp_path)
    message = str(err.value)
    assert "fallback.onnx: not an ONNX model" in message and "fallback.json: names fallback.onnx" in message
    assert "face.json: its face falls back to 'fallback', which is bad" in message
    assert classifier not in message.split("(", 1)[1]  # the classifier itself is fine
    server = Server(models=tmp_path, skip_bad_models=True)  # not started: its predictors are what it would serve
    assert {m.name for m in server.models} == {classifier}


def test_a_card_whose_onnx_file_onnx_runtime_cannot_load_is_a_card_error_naming_it(tmp_path):
    write_conv_model(tmp_path, "tiny")
    (tmp_path / "tiny.onnx").write_bytes(GARBAGE)
    with pytest.raises(ModelCardError, match=r"tiny\.json: ONNX Runtime cannot serve tiny\.onnx \(InvalidProtobuf"):
        load_model(tmp_path / "tiny.json")
