"""`deepcontact lab spread`: Box2D's closed loop against itself perturbed far below the
stopping tolerance, and other warm starts against Builtin's run and its expectation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from commands import main
from lab.closed_loop_spread import draw_names, pooled, spread

SMALL = ["--bodies", "12", "--steps", "60", "--seeds", "901-903", "--quiet"]


def test_draws_are_jitter_warm_starts_and_bad_sizes_are_refused():
    assert draw_names("1e-8, 1e-6") == ["jitter@1e-8", "jitter@1e-6"]
    for bad in ("", "0", "-1e-7", "tiny", "nan"):
        with pytest.raises(ValueError):
            draw_names(bad)


def test_the_expectation_pools_each_seeds_steps_over_the_draws():
    builtin = [np.array([10, 20]), np.array([4, 4])]
    draw = [np.array([30, 40]), np.array([8, 8])]
    both = pooled([builtin, draw])
    assert [b.tolist() for b in both] == [[10, 20, 30, 40], [4, 4, 8, 8]]
    runs = {name: [{"per_step": {"velocity_iterations": its.tolist(), "contact_points": [5] * len(its)}}
                   for its in per_seed] for name, per_seed in (("builtin", builtin), ("jitter@1e-7", draw),
                                                               ("model", builtin))}
    result = spread(runs, ["jitter@1e-7"])
    assert result["draws"]["jitter@1e-7"]["every step"].value == pytest.approx(86 / 38)
    # The same runs as Builtin's: 1 to Builtin, and below 1 to an expectation the draw made dearer.
    model = result["others"]["model"]["contact steps"]
    assert model["builtin"].value == pytest.approx(1.0)
    assert model["expected"].value == pytest.approx((38 / 4) / (124 / 8))


def test_the_command_prints_the_draws_and_other_warm_starts_against_both_references(tmp_path, capsys):
    out = tmp_path / "spread"
    assert main(["lab", "spread", *SMALL, "--draws", "1e-7,1e-6", "--warm-starts", "builtin,copy",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| jitter@1e-7 |" in text and "| jitter@1e-6 |" in text and "the draws' spread" in text
    assert "| copy |" in text and "Builtin's expectation" in text
    saved = json.loads((out / "spread.json").read_text())
    assert saved["draws"] == ["jitter@1e-7", "jitter@1e-6"] and saved["seeds"] == [901, 902, 903]
    copy = saved["ratios"]["others"]["copy"]
    assert set(copy) == {"contact steps", "every step"} and set(copy["every step"]) == {"builtin", "expected"}
    assert (out / "spread.md").read_text().startswith("thesis")


def test_bad_draws_fail_in_one_line_with_nothing_written(tmp_path, capsys):
    out = tmp_path / "spread"
    assert main(["lab", "spread", *SMALL, "--draws", "big", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "--draws" in err
    assert not out.exists()
    assert main(["lab", "spread", *SMALL, "--draws", "1e-7", "--warm-starts", "jitter@1e-7", "--out", str(out)]) == 2
    assert "one of the draws" in capsys.readouterr().err and not out.exists()
