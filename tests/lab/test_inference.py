"""`deepcontact lab inference`: ONNX Runtime levers timed on the server's own input grids."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lab.inference import add_arguments
from commands import main
from deepcontact.modelcard import ModelCard


def test_bench_inference_times_every_lever_against_the_default_session(tmp_path, model_dir, capsys):
    out = tmp_path / "inference.json"
    assert main(["lab", "inference", "--models", str(model_dir), "--model", "tiny", "--steps", "80",
                 "--repeats", "1", "--rows", "32", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["median_ms"]) == {"default", "no-spinning", "extended", "basic", "no-arena", "int8", "rows=32"}
    assert all(v > 0 for v in result["median_ms"].values()) and result["steps"] >= 4
    assert 0 <= result["int8_rms_error"] < result["output_rms"]  # quantized, and close to the float model
    assert "| rows=32 |" in capsys.readouterr().out


def test_bench_inference_refuses_what_it_cannot_time(tmp_path, model_dir, capsys):
    assert main(["lab", "inference", "--models", str(model_dir), "--model", "nope"]) == 2
    assert "nope" in capsys.readouterr().err
    assert main(["lab", "inference", "--models", str(model_dir), "--model", "tiny", "--rows", "a"]) == 2


def test_bench_inference_times_a_shipped_grid_model_when_no_model_is_named():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args([])
    # The README runs it bare: its default must be a shipped model this bench can time.
    card = ModelCard.load(Path(__file__).parents[2] / args.models / f"{args.model}.json")
    assert card.kind != "graph"
