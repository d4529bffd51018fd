"""`deepcontact bench transfer`: the P2G/G2P timings on a settled thesis world."""

from __future__ import annotations

import json

import pytest

from commands import main


def test_bench_transfer_times_the_four_transfers_and_loses_no_particle(tmp_path, capsys):
    out = tmp_path / "transfer.json"
    assert main(["bench", "transfer", "--repeats", "3", "--settle-steps", "20", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert set(result["timings_us"]) == {"p2g_inputs", "g2p_sph", "p2g_targets", "g2p_bilinear"}
    assert all(t["median"] > 0 and t["p90"] >= t["median"] for t in result["timings_us"].values())
    assert result["bodies"] == 100 and result["contact_points"] > 0
    assert result["lost"] == {"bodies": 0, "contacts": 0, "g2p": 0}
    assert result["input_shape"] == [61, 61, 6] and result["target_shape"] == [61, 61, 2]
    printed = capsys.readouterr().out
    assert "P2G inputs    -> 61x61x6" in printed and "G2P SPH       <- 61x61x2" in printed


def test_bench_transfer_refuses_zero_repeats():
    with pytest.raises(SystemExit, match="--repeats must be at least 1"):
        main(["bench", "transfer", "--repeats", "0"])
