"""Distillation: `train-graph --teacher CARD` trains on another graph model's answers."""

from __future__ import annotations

import dataclasses
import hashlib
import json

import numpy as np

from commands import main
from deepcontact.modelcard import ModelCard
from tests.training.conftest import SMALL
from training import teacher as teacher_module
from training.contact_graph import build_graph_set
from training.teacher import Teacher, answers


def test_a_student_started_from_its_teacher_fits_the_teachers_answers_exactly(data, small_graph, tmp_path):
    folder, cache = small_graph
    out = tmp_path / "student.onnx"
    assert main(["train-graph", "--train", str(data / "train.h5"), "--val", str(data / "val.h5"), "--out", str(out),
                 "--cache", str(cache), "--teacher", str(folder / "small.json"),
                 "--init", str(cache / "small.weights.npz"), "--lr", "1e-12", *SMALL]) == 0
    student = json.loads(out.with_suffix(".json").read_text())
    own = json.loads((folder / "small.json").read_text())
    # The teacher's own network, scored against its own answers: no error left. Against the
    # recorded corrections it had plenty; the normalization is the recorded targets' either way.
    assert student["validation"]["loss"] < 1e-8 < 1e-3 < own["validation"]["loss"]
    assert student["gridspec"]["normalization"] == own["gridspec"]["normalization"]
    digest = hashlib.sha1((folder / "small.onnx").read_bytes()).hexdigest()[:12]
    assert student["training"]["teacher"] == {"card": str(folder / "small.json"), "name": "small",
                                              "onnx_sha1": digest}
    # The answers were kept for the next run with this teacher: one file per data file.
    assert len(list(cache.glob(f"*-teacher-{digest}.npz"))) == 2


def test_a_steps_answer_does_not_depend_on_the_steps_answered_beside_it(data, small_graph, monkeypatch):
    folder, _ = small_graph
    graphs = build_graph_set(data / "val.h5", max_steps=10)
    teacher = Teacher.load(folder / "small.json")
    together = answers(graphs, teacher)
    monkeypatch.setattr(teacher_module, "STEPS_AT_ONCE", 1)
    alone = answers(graphs, teacher)
    assert together.shape == graphs.targets.shape
    np.testing.assert_allclose(together, alone, atol=1e-5)


def test_a_teacher_that_cannot_answer_the_students_steps_is_refused(data, small_graph, tmp_path, capsys):
    folder, cache = small_graph
    base = ["train-graph", "--val", str(data / "val-oracle.h5"), "--out", str(tmp_path / "s.onnx"),
            "--cache", str(cache), *SMALL]
    # The teacher answers corrections to Box2D's solve, not to the converged one.
    assert main(base + ["--train", str(data / "train-oracle.h5"), "--targets", "oracle",
                        "--teacher", str(folder / "small.json")]) == 2
    assert "the student is trained on oracle_correction_normal" in capsys.readouterr().err
    # A grid model does not answer at contact points.
    card = ModelCard.load(folder / "small.json")
    dataclasses.replace(card, kind="grid", name="grid").save(tmp_path / "grid.json")
    (tmp_path / "small.onnx").write_bytes((folder / "small.onnx").read_bytes())
    assert main(base + ["--train", str(data / "train.h5"), "--teacher", str(tmp_path / "grid.json")]) == 2
    assert "a teacher is a graph model" in capsys.readouterr().err
    assert main(base + ["--train", str(data / "train.h5"), "--teacher", str(tmp_path / "none.json")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert not (tmp_path / "s.onnx").exists()
