"""`deepcontact lab admission`: the admission's cost per step beside Box2D's solve."""

from __future__ import annotations

import json

import pytest

from commands import main


def test_bench_admission_times_every_part_on_steps_with_contacts(tmp_path, capsys):
    out = tmp_path / "admission.json"
    assert main(["lab", "admission", "--seeds", "901", "--settle", "120", "--steps", "2", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    parts = {"body_space", "moving_split", "admit", "admit_moving", "box2d_solve"}
    assert set(result["summary"]) == parts
    assert len(result["per_step"]) == 2 and all(r["contact_points"] > 0 for r in result["per_step"])
    assert all(s["median_ms"] > 0 and s["p90_ms"] >= s["median_ms"] for s in result["summary"].values())
    assert result["summary"]["box2d_solve"]["median_ratio_to_box2d_solve"] == 1.0
    assert "| admit moving |" in capsys.readouterr().out


def test_bench_admission_refuses_bad_arguments():
    with pytest.raises(SystemExit, match="--steps >= 1"):
        main(["lab", "admission", "--steps", "0"])
    with pytest.raises(SystemExit, match="lab admission"):
        main(["lab", "admission", "--seeds", "x"])
