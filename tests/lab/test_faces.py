"""`deepcontact lab faces`: a served model's answer read as an active set."""

from __future__ import annotations

import json

from commands import main


def test_bench_faces_counts_the_wrong_labels_a_step_of_each_reading(tmp_path, model_dir, capsys):
    data = tmp_path / "steps.h5"
    assert main(["generate", "--steps", "80", "--seeds", "1", "--out", str(data), "--quiet"]) == 0
    out = tmp_path / "faces.json"
    assert main(["lab", "faces", "--models", str(model_dir), "--model", "tiny", "--data", str(data),
                 "--pressing", "1e-6,0.01", "--share", "0.99,0.9", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["who"] for r in rows] == ["builtin"] + ["tiny"] * 4  # Box2D's warm start, then each reading
    assert [(r["pressing"], r["share"]) for r in rows[1:]] == [(1e-6, 0.99), (1e-6, 0.9), (0.01, 0.99), (0.01, 0.9)]
    for r in rows:
        assert 0 <= r["right"] <= 1 and r["steps_at_most_3"] <= r["steps_at_most_10"] <= 1
        assert abs(sum(r["kinds"].values()) - r["wrong_mean"]) < 1e-9  # every wrong label is of one kind
    assert "| read | points right |" in capsys.readouterr().out

    # What serving the face route would cost: the step solved on the labels, and admitted.
    assert main(["lab", "faces", "--models", str(model_dir), "--model", "tiny", "--data", str(data),
                 "--solve-time", "5", "--rounds", "10", "--json", str(out)]) == 0
    timed = json.loads(out.read_text())["solve_ms"]
    assert timed["steps"] == 5 and set(timed) == {"steps", "points_median", "solve", "admit", "admit_cut"}
    assert all(0 <= timed[k]["median"] <= timed[k]["p90"] for k in ("solve", "admit", "admit_cut"))
    assert "nearest_admissible, 10 rounds" in capsys.readouterr().out

    # The recorded solve's own end, read as a face, is its face: nothing wrong.
    assert main(["lab", "faces", "--model", "recorded", "--data", str(data), "--json", str(out)]) == 0
    recorded = json.loads(out.read_text())["rows"][1]
    assert recorded["right"] == 1.0 and recorded["wrong_mean"] == 0.0 and recorded["steps_at_most_3"] == 1.0


def test_bench_faces_refuses_bad_readings_and_missing_models(tmp_path, model_dir, capsys):
    data = tmp_path / "steps.h5"
    assert main(["generate", "--steps", "20", "--seeds", "1", "--out", str(data), "--quiet"]) == 0
    for bad in (["--share", "0"], ["--share", "x"], ["--pressing", "-1"], ["--friction", "0"], ["--max-steps", "0"],
                ["--solve-time", "-1"], ["--rounds", "0"],
                ["--model", "nope"]):
        assert main(["lab", "faces", "--models", str(model_dir), "--data", str(data), "--model", "tiny", *bad]) == 2
    assert "deepcontact lab faces:" in capsys.readouterr().err
