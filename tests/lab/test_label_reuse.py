"""`deepcontact lab label-reuse`: the route on labels held across a stream's steps, priced on
Box2D's own states of a thesis world."""

from __future__ import annotations

from pathlib import Path

from commands import main
from lab.label_reuse import price
from server.predictors import load_model

ROOT = Path(__file__).resolve().parents[2]


def test_held_labels_are_the_steps_own_until_every_point_persists():
    runs, counted, reused = price(850, 40, load_model(ROOT / "models" / "default.json"))
    assert counted == len(runs["builtin"]) == len(runs["fresh"]) == len(runs["reused"]) > 0
    assert 0 < reused < counted  # the pile forms: steps whose every point persists
    # A step with a new point is labelled afresh, so the two answers part only where labels were held.
    assert (runs["fresh"] != runs["reused"]).sum() <= reused


def test_the_command_prints_both_ratios_and_refuses_a_card_without_a_route(capsys):
    assert main(["lab", "label-reuse", "--seeds", "850-851", "--steps", "30"]) == 0
    out = capsys.readouterr().out
    assert "| the step's own |" in out and "| held across steps |" in out and "held / own:" in out
    assert main(["lab", "label-reuse", "--seeds", "850", "--model", "contact-graph"]) == 2
    assert "not a face card" in capsys.readouterr().err
