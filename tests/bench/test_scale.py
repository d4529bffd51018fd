"""`deepcontact bench scale`: times the real commands and compares their answers."""

from __future__ import annotations

import json

from bench.scale import config_flags
from commands import main


def test_bench_scale_times_each_configuration_and_compares_the_answers(tmp_path, capsys):
    out = tmp_path / "scale.json"
    assert main(["bench", "scale", "--commands", "generate", "--configs", "workers=1,workers=2", "--seeds", "1-2",
                 "--steps", "10", "--repeats", "2", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["results"]["generate"]
    assert len(rows["workers=1"]["seconds"]) == 2 and rows["workers=1"]["against"] is None
    assert rows["workers=2"]["against"] == "workers=1" and rows["workers=2"]["speedup"] > 0
    assert all(row["same_answers"] for row in rows.values())
    assert capsys.readouterr().out.strip().endswith("every run gave the same answers as the first")


def test_any_worker_count_is_a_configuration():
    assert config_flags("workers=16") == ["--workers", "16"]
    assert config_flags("ray=4") == ["--ray", "--workers", "4"]


def test_unknown_configurations_are_refused(capsys):
    assert main(["bench", "scale", "--configs", "workers=0"]) == 2
    assert "workers=0" in capsys.readouterr().err
    assert main(["bench", "scale", "--configs", "threads=2"]) == 2
    assert "threads=2" in capsys.readouterr().err


def test_iterations_spread_over_server_replicas(tmp_path):
    out = tmp_path / "scale.json"
    assert main(["bench", "scale", "--commands", "iterations", "--configs", "workers=2", "--iteration-seeds", "901-902",
                 "--warm-starts", "builtin,server:default", "--replicas", "2", "--steps", "10", "--repeats", "1",
                 "--json", str(out)]) == 0
    assert json.loads(out.read_text())["results"]["iterations"]["workers=2"]["same_answers"]
