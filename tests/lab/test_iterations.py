"""`deepcontact lab iterations` and `lab simulate`: the product's commands with the lab's warm starts."""

from __future__ import annotations

import json

import pytest

from commands import main
from tests.server.conftest import write_conv_model


def test_lab_iterations_prices_composites_on_the_same_states_in_process_and_on_workers(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    written = {}
    for backend, flags in (("process", []), ("workers", ["--workers", "2"])):  # workers are spawned afresh
        out = tmp_path / backend
        assert main(["lab", "iterations", "--seeds", "901", "--steps", "30", "--warm-starts",
                     "builtin,server:tiny,pick:server:tiny+server:zero,price:server:tiny", "--models", str(models),
                     "--deadline-ms", "1000", "--out", str(out), "--quiet", *flags]) == 0
        written[backend] = json.loads((out / "summary.json").read_text())
    summary = written["process"]["warm_starts"]
    pick = written["process"]["picks"]["pick:server:tiny+server:zero"]  # the trial solves: every candidate on the same states
    assert pick["candidates"] == ["builtin", "server:tiny", "server:zero"] and pick["over_builtin"][0]["value"] == 1.0
    assert abs(sum(pick["picked"]) - 1.0) < 1e-9 and pick["serves"] == "the picked"
    # two models: each is also priced against the first on the same states
    assert pick["over_first"][1]["value"] == 1.0 and pick["over_first"][2]["value"] > 0
    assert written["process"]["picks"]["price:server:tiny"]["over_first"] is None  # one model: nothing to pair
    assert pick["steps"] == summary["pick:server:tiny+server:zero"]["steps_with_contacts"]
    assert pick["trajectory"]["seeds"] == 1 and pick["trajectory"]["value"] > 0  # builtin here against on its own
    priced = written["process"]["picks"]["price:server:tiny"]  # served builtin: Builtin's own trajectory
    assert priced["trajectory"]["value"] == 1.0 and priced["serves"] == "Builtin's"
    assert summary["price:server:tiny"]["mean_velocity_iterations"] == summary["builtin"]["mean_velocity_iterations"]
    table = (tmp_path / "process" / "results.md").read_text()
    assert "`price:server:tiny`: every candidate solved from the same state at each of" in table
    assert "(Builtin's trajectory)" in table and "`pick:server:tiny+server:zero`: every candidate" in table
    for name in summary:  # the same trials on spawned workers, which import the lab's warm starts themselves
        assert written["workers"]["warm_starts"][name]["mean_velocity_iterations"] == \
            summary[name]["mean_velocity_iterations"]
    assert written["workers"]["picks"]["price:server:tiny"]["mean_iterations"] == priced["mean_iterations"]


def test_server_star_inside_a_composite_names_every_served_model(tmp_path):
    import lab  # noqa: F401  (registers the composites)
    from bench.iterations import expand_served
    from server.process import ServerProcess

    models = tmp_path / "models"
    models.mkdir()
    for name in ("tiny-e10", "tiny-e2"):
        write_conv_model(models, name)
    with ServerProcess(models) as server:
        assert expand_served(["builtin", "server:*", "price:server:*+jitter@0.1"], server.address) == [
            "builtin", "server:tiny-e2", "server:tiny-e10", "price:server:tiny-e2+server:tiny-e10+jitter@0.1"]


def test_a_composite_of_many_warm_starts_is_named_short_in_the_legend():
    import lab  # noqa: F401
    from bench.iterations import legend_label

    many = "shadow:server:default+" + "+".join(f"server:graph-variant-{i}" for i in range(5))
    assert legend_label(many) == "shadow:server:default (+5 more)"
    assert legend_label("price:server:a+server:b") == "price:server:a (+1 more)"
    assert legend_label("split:server:default") == "split:server:default"  # one warm start: as it is
    assert legend_label("solved@0.75:server:a") == "solved@0.75:server:a"


def test_lab_simulate_runs_a_lab_warm_start_and_says_which_command_refused(tmp_path, capsys):
    out = tmp_path / "shadow.json"
    assert main(["lab", "simulate", "--seed", "901", "--steps", "40", "--warm-start", "shadow:jitter@0.01",
                 "--out", str(out), "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert result["warm_start"] == "shadow:jitter@0.01" and len(result["trials"]) > 0
    assert main(["lab", "simulate", "--seed", "901", "--warm-start", "oracle:magic", "--out", str(out)]) == 2
    assert "deepcontact lab simulate: unknown oracle variant" in capsys.readouterr().err


@pytest.mark.parametrize("words", [["lab", "simulate"], ["lab", "iterations"]])
def test_the_lab_commands_list_the_labs_warm_starts_beside_the_products(words, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "1000")  # no line breaks inside a name
    with pytest.raises(SystemExit):
        main([*words, "--help"])
    text = capsys.readouterr().out
    for name in ("builtin", "server:NAME", "oracle:VARIANT", "price:W1+W2+...", "solve@K", "rest-admissible"):
        assert name in text
