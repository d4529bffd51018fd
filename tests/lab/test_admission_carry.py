"""`deepcontact lab admission-carry`: the default's route with its admission begun cold and where
its points' stopped the step before, priced on Box2D's own states of a thesis world."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from commands import main
from lab.admission_carry import STARTS, price
from server.predictors import load_model

ROOT = Path(__file__).resolve().parents[2]


def test_every_start_is_priced_on_the_same_steps_and_ten_times_the_rounds_end_nearest():
    sweeps, apart = price(850, 120, load_model(ROOT / "models" / "default.json"))  # the pile formed
    steps = len(sweeps["builtin"])
    assert steps > 0 and all(len(sweeps[name]) == len(apart[name]) == steps for name, _, _ in STARTS)
    # The first step with contacts has nothing to carry: every start of the same rounds agrees there.
    assert sweeps["cold"][0] == sweeps["carried z"][0] == sweeps["carried z and s"][0]
    assert np.nanmean(apart["cold, 10x the rounds"]) < np.nanmean(apart["cold"])


def test_the_command_prints_each_start_and_refuses_a_card_without_a_route(capsys):
    assert main(["lab", "admission-carry", "--seeds", "850", "--steps", "30"]) == 0
    out = capsys.readouterr().out
    assert all(f"| {name} |" in out for name, _, _ in STARTS)
    assert main(["lab", "admission-carry", "--seeds", "850", "--model", "contact-graph"]) == 2
    assert "not a face card" in capsys.readouterr().err
    assert main(["lab", "admission-carry", "--seeds", "850", "--steps", "0"]) == 2
    assert "--steps must be >= 1" in capsys.readouterr().err
