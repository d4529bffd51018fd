"""`deepcontact lab corrections`: a served model's corrections against the solver's, by size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lab.corrections import band_table, fit_of, lost_contact
from deepcontact.channels import Step
from commands import main
from deepcontact.kinematics import BODY_DYNAMIC
from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE


def test_band_table_groups_persisting_points_by_the_solvers_correction():
    solver = np.array([0.005, -0.05, 0.2, -2.0, 1.5])
    served = np.array([-0.01, -0.04, 0.0, -1.0, 1.0])
    new = np.array([False, False, False, False, True])
    rows = {r["group"]: r for r in band_table(served, solver, new)}
    small = rows["persisting, |c| <= 0.01"]
    assert small["points"] == 1 and small["sign_agreement"] == 0.0  # served the wrong way
    assert rows["persisting, |c| in (0.01, 0.1]"]["sign_agreement"] == 1.0
    mid = rows["persisting, |c| in (0.1, 0.3]"]
    assert mid["served_share"] == 0.0 and mid["sign_agreement"] is None  # nothing served there
    assert mid["rms_error"] == pytest.approx(0.2)  # Builtin's error where nothing is served
    assert rows["persisting, |c| in (1, inf]"]["rms_error"] == pytest.approx(1.0)
    assert rows["persisting, all"]["points"] == 4 and rows["new points"]["points"] == 1
    # -1.0 served for -2.0: right sign, off by half; within half of it counts.
    assert rows["persisting, |c| in (1, inf]"]["within_half"] == 1.0
    assert small["within_half"] == 0.0 and mid["within_half"] is None


def _points(*rows):
    """Contact records from (key, body_a, body_b)."""
    points = np.zeros(len(rows), CONTACT_DTYPE)
    for i, (key, a, b) in enumerate(rows):
        points[i]["key"], points[i]["body_a"], points[i]["body_b"] = key, a, b
    return points


def test_lost_contact_marks_the_points_of_bodies_that_lost_one_since_the_last_step():
    bodies = np.zeros(5, BODY_DTYPE)
    bodies["type"] = [0, BODY_DYNAMIC, BODY_DYNAMIC, BODY_DYNAMIC, BODY_DYNAMIC]  # body 0: the ground
    previous = _points((10, 0, 1), (11, 1, 2), (12, 0, 3), (13, 3, 4))
    # Point 11 (bodies 1-2) and point 12 (ground-3) are gone; 10 and 13 persist, 14 is new.
    step = Step(bodies, _points((10, 0, 1), (13, 3, 4), (14, 0, 4)), previous)
    assert lost_contact(step).tolist() == [True, True, False]  # body 1; body 3; the ground absorbs, 4 lost none
    assert not lost_contact(Step(bodies, step.contacts, None)).any()  # no previous step: nothing lost
    assert not lost_contact(Step(bodies, previous, previous)).any()  # the same points: nothing lost


def test_bench_corrections_replays_recorded_steps_through_a_served_model(tmp_path, model_dir, capsys):
    data = tmp_path / "rec.h5"
    assert main(["generate", "--steps", "60", "--seeds", "1", "--out", str(data), "--quiet"]) == 0
    out = tmp_path / "bands.json"
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny", "--data", str(data),
                 "--max-steps", "20", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert sum(r["points"] for r in rows if r["group"] in ("persisting, all", "new points")) > 0
    assert "| persisting, all |" in capsys.readouterr().out
    # Two models: the mean of their warm starts is served.
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny,zero-ish", "--data", str(data),
                 "--max-steps", "20"]) == 2  # no such model
    mean = tmp_path / "mean.json"
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny,tiny", "--data", str(data),
                 "--max-steps", "20", "--json", str(mean)]) == 0
    assert json.loads(mean.read_text())["rows"] == rows  # the mean of a model and itself is the model
    assert "the mean of tiny, tiny" in capsys.readouterr().out
    # A model agrees with itself wherever it corrects anything.
    agreed = tmp_path / "agreed.json"
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny,tiny", "--agree", "0.2",
                 "--data", str(data), "--max-steps", "20", "--json", str(agreed)]) == 0
    assert json.loads(agreed.read_text())["rows"] == rows
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny", "--agree", "0.2",
                 "--data", str(data)]) == 2
    assert "at least two models" in capsys.readouterr().err
    # --where splits the persisting and new points between bodies that lost a contact and the rest.
    split = {}
    for where in ("lost-contact", "kept-contacts", "settled", "moving"):
        out = tmp_path / f"{where}.json"
        assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny", "--data", str(data),
                     "--max-steps", "20", "--where", where, "--json", str(out)]) == 0
        table = json.loads(out.read_text())
        assert table["where"] == where
        split[where] = {r["group"]: r["points"] for r in table["rows"]}
    every = {r["group"]: r["points"] for r in rows}
    for part, rest in (("lost-contact", "kept-contacts"), ("settled", "moving")):
        assert all(split[part][g] + split[rest][g] == every[g] for g in every)
    assert "since the previous step" in capsys.readouterr().out
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "nope", "--data", str(data)]) == 2
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny",
                 "--data", str(tmp_path / "none.h5")]) == 2
    assert "none.h5" in capsys.readouterr().err


def test_bench_corrections_can_score_against_the_converged_solve(tmp_path, model_dir, capsys):
    plain, oracle = tmp_path / "rec.h5", tmp_path / "rec-oracle.h5"
    assert main(["generate", "--steps", "40", "--seeds", "1", "--out", str(plain), "--quiet"]) == 0
    assert main(["generate", "--steps", "40", "--seeds", "1", "--oracle", "--out", str(oracle), "--quiet"]) == 0
    rows = {}
    for reference in ("final", "oracle"):
        out = tmp_path / f"{reference}.json"
        assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny", "--data", str(oracle),
                     "--reference", reference, "--json", str(out)]) == 0
        table = json.loads(out.read_text())
        assert table["reference"] == reference
        rows[reference] = {r["group"]: r for r in table["rows"]}
    # The same points and the same served warm starts, measured against two solutions of the step.
    assert rows["final"]["persisting, all"]["points"] == rows["oracle"]["persisting, all"]["points"]
    assert rows["final"]["persisting, all"]["rms_error"] != rows["oracle"]["persisting, all"]["rms_error"]
    assert "converged solve" in capsys.readouterr().out
    # `recorded` serves the recorded solve's end: no error against it, some against the converged solve.
    for reference, exact in (("final", True), ("oracle", False)):
        out = tmp_path / f"recorded-{reference}.json"
        assert main(["lab", "corrections", "--model", "recorded", "--data", str(oracle), "--reference", reference,
                     "--json", str(out)]) == 0
        errors = [r["rms_error"] for r in json.loads(out.read_text())["rows"] if r["points"]]
        assert (max(errors) == 0.0) is exact
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "tiny", "--data", str(plain),
                 "--reference", "oracle"]) == 2
    assert "--oracle" in capsys.readouterr().err


def test_bench_corrections_splits_each_correction_into_the_part_that_moves_the_bodies_and_the_self_stress(
        tmp_path, model_dir, capsys):
    data = tmp_path / "rec.h5"
    assert main(["generate", "--steps", "200", "--seeds", "1", "--out", str(data), "--quiet"]) == 0
    tables = {}
    for part in ("whole", "body-space", "self-stress"):
        out = tmp_path / f"{part}.json"
        assert main(["lab", "corrections", "--models", str(model_dir), "--model", "recorded", "--data", str(data),
                     "--max-steps", "20", "--part", part, "--json", str(out)]) == 0
        tables[part] = json.loads(out.read_text())
        assert tables[part]["part"] == part
        assert tables[part]["explained"] == 1.0  # the recorded solve's end, exact in every part
        assert tables[part]["scale"] == pytest.approx(1.0) and tables[part]["correlation"] == pytest.approx(1.0)
    rms = {part: {r["group"]: r["rms_correction"] for r in t["rows"]}["persisting, all"] for part, t in tables.items()}
    assert 0.0 < rms["self-stress"] < rms["whole"]  # a pile has a self-stress, a share of the correction
    assert "self-stress part of each correction" in capsys.readouterr().out
    assert main(["lab", "corrections", "--models", str(model_dir), "--model", "recorded,recorded", "--agree", "0.2",
                 "--part", "self-stress", "--data", str(data)]) == 2
    assert "leave out --part" in capsys.readouterr().err


def test_fit_of_reads_a_shrunk_answer_as_its_scale():
    rng = np.random.default_rng(0)
    solver = rng.normal(0.0, 0.3, 10_000)  # N s
    fit = fit_of(0.7 * solver, solver)  # right in direction, 70 % of the size
    assert fit["scale"] == pytest.approx(0.7) and fit["correlation"] == pytest.approx(1.0)
    assert fit["explained"] == pytest.approx(1 - 0.3 ** 2)
    noisy = fit_of(solver + rng.normal(0.0, 0.3, solver.shape), solver)  # unbiased noise as large as the answer
    assert noisy["scale"] == pytest.approx(1.0, abs=0.05) and noisy["explained"] == pytest.approx(0.0, abs=0.05)
    assert np.isnan(fit_of(np.zeros(3), np.ones(3))["correlation"])
