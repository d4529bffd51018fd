"""Distillation: `train-graph --teacher CARD` trains on another graph model's answers."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from deepcontact.cli import main
from deepcontact.modelcard import ModelCard
from training import teacher as teacher_module
from training.contact_graph import build_graph_set
from training.teacher import Teacher, answers

SMALL = ["--epochs", "1", "--batch-size", "4", "--width", "8", "--rounds", "2", "--loss", "mse", "--quiet"]


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory):
    """(folder, cache): a small graph model `teacher` trained on the recorded corrections."""
    folder = tmp_path_factory.mktemp("teacher")
    cache = folder / "cache"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"),
                 "--out", str(folder / "teacher.onnx"), "--cache", str(cache), *SMALL]) == 0
    return folder, cache


def test_a_student_started_from_its_teacher_fits_the_teachers_answers_exactly(data, trained, tmp_path):
    folder, cache = trained
    out = tmp_path / "student.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--cache", str(cache), "--teacher", str(folder / "teacher.json"),
                 "--init", str(cache / "teacher.weights.npz"), "--lr", "1e-12", *SMALL]) == 0
    student = json.loads(out.with_suffix(".json").read_text())
    own = json.loads((folder / "teacher.json").read_text())
    # The teacher's own network, scored against its own answers: no error left. Against the
    # recorded corrections it had plenty; the normalization is the recorded targets' either way.
    assert student["validation"]["loss"] < 1e-8 < 1e-3 < own["validation"]["loss"]
    assert student["gridspec"]["normalization"] == own["gridspec"]["normalization"]
    digest = hashlib.sha1((folder / "teacher.onnx").read_bytes()).hexdigest()[:12]
    assert student["training"]["teacher"] == {"card": str(folder / "teacher.json"), "name": "teacher",
                                              "onnx_sha1": digest}
    # The answers were kept for the next run with this teacher: one file per data file.
    assert len(list(cache.glob(f"*-teacher-{digest}.npz"))) == 2


def test_a_steps_answer_does_not_depend_on_the_steps_answered_beside_it(data, trained, monkeypatch):
    folder, _ = trained
    graphs = build_graph_set(data / "val.h5", max_steps=10)
    teacher = Teacher.load(folder / "teacher.json")
    together = answers(graphs, teacher)
    monkeypatch.setattr(teacher_module, "STEPS_AT_ONCE", 1)
    alone = answers(graphs, teacher)
    assert together.shape == graphs.targets.shape
    np.testing.assert_allclose(together, alone, atol=1e-5)


def test_a_teacher_that_cannot_answer_the_students_steps_is_refused(data, trained, tmp_path, capsys):
    folder, cache = trained
    base = ["train-graph", "--val", str(data / "val-oracle.h5"), "--out", str(tmp_path / "s.onnx"),
            "--cache", str(cache), *SMALL]
    # The teacher answers corrections to Box2D's solve, not to the converged one.
    assert main(base + ["--train", str(data / "train-oracle.h5"), "--targets", "oracle",
                        "--teacher", str(folder / "teacher.json")]) == 2
    assert "the student is trained on oracle_correction_normal" in capsys.readouterr().err
    # A grid model does not answer at contact points.
    card = ModelCard.load(folder / "teacher.json")
    dataclasses.replace(card, kind="grid", name="grid").save(tmp_path / "grid.json")
    (tmp_path / "teacher.onnx").write_bytes((folder / "teacher.onnx").read_bytes())
    assert main(base + ["--train", str(data / "train.h5"), "--teacher", str(tmp_path / "grid.json")]) == 2
    assert "a teacher is a graph model" in capsys.readouterr().err
    assert main(base + ["--train", str(data / "train.h5"), "--teacher", str(tmp_path / "none.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert not (tmp_path / "s.onnx").exists()
