"""`deepcontact demo`: the main job, end to end on a real server, engine and ONNX Runtime."""

from __future__ import annotations

import json

from commands import main
from tests.server.conftest import write_conv_model


def test_the_demo_prints_one_table_and_writes_the_details(tmp_path, capsys):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "pressure")
    write_conv_model(models, "tiny", seed=1)
    (models / "default.json").write_text(json.dumps({"name": "default", "alias_of": "tiny"}))
    out = tmp_path / "out"
    assert main(["demo", "--models", str(models), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = [line for line in printed.splitlines() if line.startswith("| ")]
    assert rows[0] == "| warm start | mean iterations | / builtin | p50 latency ms | learned route |"
    assert [r.split(" | ")[0] for r in rows[1:] if not r.startswith("|---")] == [
        "| none", "| builtin", "| server:pressure, guard off", "| server:default, guard off", "| server:default"]
    assert "| builtin | " in printed and " | 1.000 | – | – |" in printed
    assert "below 1: fewer than Box2D's own" in printed
    details = (out / "details.md").read_text()
    assert "Ratios to builtin" in details and "Guard (the learned start" in details
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["warm_starts"]) == {"none", "builtin", "server:pressure, guard off",
                                           "server:default, guard off", "server:default"}
    assert (out / "fig21_convergence.png").exists()


def test_the_demo_says_which_card_is_missing(tmp_path, capsys):
    assert main(["demo", "--models", str(tmp_path), "--out", str(tmp_path / "out")]) == 2
    assert "no model card pressure, default" in capsys.readouterr().err
