"""`deepcontact bench server`: the server's stage timings on recorded thesis steps."""

from __future__ import annotations

import json

from commands import main


def test_bench_server_reports_every_stage_and_the_round_trip(tmp_path, model_dir):
    out = tmp_path / "server.json"
    assert main(["bench", "server", "--models", str(model_dir), "--model", "tiny", "--steps", "80",
                 "--rounds", "2", "--intra-op-threads", "2", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["intra_op_threads"] == 2 and result["steps"] > 0
    med = result["server_us_median"]
    assert med["total"] >= med["inference"] > 0 and 0 < med["outside_inference"] < med["total"]
    assert result["round_trip_ms_p99"] >= result["round_trip_ms_median"] > 0


def test_bench_server_refuses_a_model_it_does_not_have(model_dir, capsys):
    assert main(["bench", "server", "--models", str(model_dir), "--model", "nope", "--steps", "80"]) == 2
    assert "no model 'nope'" in capsys.readouterr().err


def test_bench_server_times_a_server_on_a_unix_socket(tmp_path, model_dir):
    out, bind = tmp_path / "server.json", f"unix:{tmp_path / 'warmstart.sock'}"
    assert main(["bench", "server", "--models", str(model_dir), "--model", "tiny", "--steps", "80",
                 "--rounds", "2", "--bind", bind, "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["bind"] == bind and result["steps"] > 0 and result["round_trip_ms_median"] > 0
