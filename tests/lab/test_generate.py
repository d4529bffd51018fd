"""`deepcontact lab generate`: the cost of recording, and of writing with each compression."""

from __future__ import annotations

import json

from commands import main


def test_bench_generate_times_the_write_with_each_compression(tmp_path, capsys):
    out = tmp_path / "generate.json"
    assert main(["lab", "generate", "--seeds", "900", "--compressions", "gzip,none", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["write"]) == {"gzip", "none"}
    # times are not asserted (benchmarks measure speed); what each costs on disk is
    assert result["write"]["none"]["mb_per_simulation"] > result["write"]["gzip"]["mb_per_simulation"]
    assert result["recorded_s_median"] > 0 and "at most" in capsys.readouterr().out


def test_an_unknown_compression_is_refused(capsys):
    assert main(["lab", "generate", "--compressions", "zstd"]) == 2
    assert "zstd" in capsys.readouterr().err
