"""`deepcontact demo`: the main job, end to end on a real server, engine and ONNX Runtime."""

from __future__ import annotations

import json

from deepcontact.cli import main
from tests.server.conftest import write_conv_model


def test_the_demo_runs_the_shipped_selection_and_names_what_an_alias_is(tmp_path, capsys):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    (models / "default.json").write_text(json.dumps({"name": "default", "alias_of": "tiny"}))
    out = tmp_path / "out"
    assert main(["demo", "--model", "default", "--models", str(models), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "default is tiny" in captured.err
    assert "| server:default |" in captured.out and "| builtin |" in captured.out
    assert "`shadow:server:default`: every candidate solved from the same state" in captured.out
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["warm_starts"]) == {"none", "builtin", "server:default", "shadow:server:default"}
    assert summary["picks"]["shadow:server:default"]["candidates"] == ["builtin", "server:default"]


def test_the_demo_says_which_card_is_missing(tmp_path, capsys):
    assert main(["demo", "--model", "nope", "--models", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "no model card nope" in capsys.readouterr().err
