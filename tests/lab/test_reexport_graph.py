"""lab.reexport_graph: a shipped contact-graph model exported again with scatter sums
serves what it served, over a real server, and its cards say how it was exported."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnx

from deepcontact.modelcard import ModelCard
from training.recover_weights import exported_incidence, recover
from lab.reexport_graph import main

from tests.training.test_ensemble import served

SHIPPED = Path(__file__).parents[2] / "lab" / "models"  # the research store
SOURCE = "graph-projected-max-1-799"  # three rounds, exported with one-hot matmuls, with a -t1 card


def _ops(path: Path) -> set[str]:
    return {n.op_type for n in onnx.load(str(path)).graph.node}


def test_a_reexported_model_serves_what_it_served_and_its_cards_say_how_it_is_exported(tmp_path, thesis_steps):
    world, steps = thesis_steps
    before = tmp_path / "before"
    before.mkdir()
    for name in (f"{SOURCE}.json", f"{SOURCE}-t1.json", f"{SOURCE}.onnx"):
        shutil.copy(SHIPPED / name, before)
    (before / "default.json").write_text(json.dumps({"name": "default", "alias_of": SOURCE, "why": "a test"}))
    after = tmp_path / "after"
    shutil.copytree(before, after)
    assert "OneHot" in _ops(after / f"{SOURCE}.onnx")

    assert main([str(after / f"{SOURCE}.json")]) == 0
    assert "ScatterND" in _ops(after / f"{SOURCE}.onnx") and "OneHot" not in _ops(after / f"{SOURCE}.onnx")
    for name in (SOURCE, f"{SOURCE}-t1"):  # the threshold card serves the same file
        for old, new in zip(served(before, name, world, steps), served(after, name, world, steps)):
            np.testing.assert_allclose(new, old, atol=1e-5)
        card = ModelCard.load(after / f"{name}.json")
        assert card.architecture["onnx_incidence"] == "scatter"
        assert card.architecture["onnx_bytes"] == (after / f"{SOURCE}.onnx").stat().st_size
        assert card.commands[-1].startswith("python -m lab.reexport_graph")
    assert json.loads((after / "default.json").read_text())["alias_of"] == SOURCE  # an alias stays an alias
    # The weights are the shipped ones, recovered from either file.
    old_weights, _ = recover(before / f"{SOURCE}.json")
    new_weights, parity = recover(after / f"{SOURCE}.json")
    assert parity < 1e-4 and set(new_weights) == set(old_weights)
    for k, w in old_weights.items():
        np.testing.assert_array_equal(new_weights[k], w)


def test_a_second_reexport_changes_nothing_and_a_grid_model_is_refused(tmp_path, capsys):
    for name in (f"{SOURCE}.json", f"{SOURCE}.onnx"):
        shutil.copy(SHIPPED / name, tmp_path)
    assert main([str(tmp_path / f"{SOURCE}.json")]) == 0
    exported = (tmp_path / f"{SOURCE}.onnx").read_bytes()
    assert exported_incidence(exported) == "scatter"
    assert main([str(tmp_path / f"{SOURCE}.json")]) == 0
    assert "already exported with scatter sums" in capsys.readouterr().out
    assert (tmp_path / f"{SOURCE}.onnx").read_bytes() == exported
    for name in ("pressure.json", "pressure.onnx"):
        shutil.copy(SHIPPED / name, tmp_path)
    assert main([str(tmp_path / "pressure.json")]) == 2
    assert "graph models only" in capsys.readouterr().err
