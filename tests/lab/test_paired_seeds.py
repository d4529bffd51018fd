"""lab.paired_seeds: one-seed bench runs of two folders, paired by seed."""

import json

import pytest

from lab.paired_seeds import main, paired_ratio, seed_means


def _runs(folder, means, warm_start="server:default"):
    for seed, mean in means.items():
        run = folder / str(seed)
        run.mkdir(parents=True)
        (run / "summary.json").write_text(json.dumps({"seeds": [seed],
                                                      "per_seed_mean_iterations": {warm_start: [mean]}}))


def test_runs_are_paired_by_the_seeds_both_folders_hold(tmp_path, capsys):
    _runs(tmp_path / "after", {901: 80.0, 902: 120.0, 903: 100.0})
    _runs(tmp_path / "before", {901: 100.0, 902: 150.0, 904: 10.0})  # 903 and 904 have no pair
    a, b = seed_means(tmp_path / "after", "server:default"), seed_means(tmp_path / "before", "server:default")
    value, low, high, seeds = paired_ratio(a, b)
    assert seeds == 2 and value == pytest.approx(200.0 / 250.0) and low == high == pytest.approx(0.8)
    assert main([str(tmp_path / "after"), str(tmp_path / "before")]) == 0
    assert "over 2 seeds: 0.800 [0.800, 0.800]" in capsys.readouterr().out


def test_two_warm_starts_of_other_names_and_too_few_seeds(tmp_path, capsys):
    _runs(tmp_path / "c50", {850: 30.0, 851: 60.0}, "server:default-c50")
    _runs(tmp_path / "shipped", {850: 40.0, 851: 60.0})
    assert main([str(tmp_path / "c50"), str(tmp_path / "shipped"), "--warm-start", "server:default-c50",
                 "--against", "server:default"]) == 0
    assert "0.900" in capsys.readouterr().out
    assert main([str(tmp_path / "c50"), str(tmp_path / "shipped")]) == 2  # no server:default runs in c50
    assert "a paired interval needs two or more" in capsys.readouterr().err
