"""`deepcontact bench iterations` end to end: starts its own server, writes table and figures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from commands import main
from tests.server.conftest import write_conv_model


def test_bench_iterations_writes_summary_table_and_figures(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    out = tmp_path / "out"
    assert main(["bench", "iterations", "--seeds", "901", "--steps", "30", "--warm-starts",
                 "none,builtin,extrapolate,server:tiny,server:grid-identity", "--models", str(models),
                 "--deadline-ms", "1000", "--out", str(out), "--quiet"]) == 0
    written = json.loads((out / "summary.json").read_text())
    summary = written["warm_starts"]
    assert set(summary) == {"none", "builtin", "extrapolate", "server:tiny", "server:grid-identity"}
    assert summary["server:tiny"]["p50_latency_ms"] > 0 and summary["server:tiny"]["fallback_steps"] == 0
    assert written["picks"] == {}  # no composite: no trial solves (deepcontact lab iterations prices those)
    table = (out / "results.md").read_text()
    assert "| builtin |" in table and "| server:tiny |" in table
    for fig in ("fig20_contacts_iterations.png", "fig21_convergence.png", "fig26_mse.png"):
        assert (out / fig).stat().st_size > 10_000


def test_server_star_names_every_model_the_server_serves_and_no_provider(tmp_path, capsys):
    from bench.iterations import expand_served
    from server.process import ServerProcess

    models = tmp_path / "models"
    models.mkdir()
    with ServerProcess(models) as server:  # providers only (zero, random, bad, grid-identity)
        with pytest.raises(ValueError, match="serves no model"):
            expand_served(["server:*"], server.address)
    for name in ("tiny-e10", "tiny-e2"):
        write_conv_model(models, name)
    with ServerProcess(models) as server:
        assert expand_served(["builtin", "server:*"], server.address) == ["builtin", "server:tiny-e2", "server:tiny-e10"]


def test_ratios_to_builtin_come_with_their_interval_over_seeds(tmp_path):
    out = tmp_path / "out"
    assert main(["bench", "iterations", "--seeds", "901-903", "--steps", "120", "--warm-starts",
                 "none,builtin,copy2", "--out", str(out), "--quiet", "--workers", "2"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    copy2 = summary["ratios_to_builtin"]["copy2"]
    assert copy2["mean"]["seeds"] == 3 and copy2["mean"]["low"] <= copy2["mean"]["value"] <= copy2["mean"]["high"]
    assert copy2["mean"]["high"] < 1.0 and copy2["median"]["value"] < 1.0  # the rounded oracle beats builtin
    assert len(summary["per_seed_mean_iterations"]["none"]) == 3
    row = next(line for line in (out / "results.md").read_text().splitlines() if line.startswith("| copy2 |"))
    assert "[" in row and "✓" in row


def test_a_run_that_falls_asleep_sooner_is_judged_on_every_step_too():
    """Sleeping parts the two measures: a run whose bodies sleep after its costly settling step
    has one step with contacts, and its mean there is high, though it solved less in all."""
    from bench.iterations import ratios_to_builtin

    def run(iterations, points):
        return {"per_step": {"velocity_iterations": iterations, "contact_points": points}}

    builtin = [run([100, 2, 2, 2], [30, 30, 30, 30]), run([80, 2, 2, 2], [30, 30, 30, 30])]
    asleep = [run([100, 0, 0, 0], [30, 0, 0, 0]), run([80, 0, 0, 0], [30, 0, 0, 0])]
    ratios = ratios_to_builtin({"builtin": builtin, "server:model": asleep})["server:model"]
    assert ratios["mean"].value == pytest.approx(180 / (192 / 4))  # 3.75x over the steps with contacts
    assert ratios["every_step"].value == pytest.approx(180 / 192)  # 0.94x of the solver's work


def test_every_series_of_a_figure_has_its_own_look_and_baselines_stay_grey():
    from bench.iterations import series_styles

    names = ["none", "builtin", "copy", "copy2", "copy0", "extrapolate", "server:random", "server:bad",
             "server:grid-identity", "server:pressure", "server:residual", "server:unet", "server:default"]
    styles = series_styles(names)
    looks = {(str(st["color"]), str(st["ls"])) for st in styles.values()}
    assert len(looks) == len(names)
    assert styles["builtin"]["color"] == "black"
    learned = [styles[n] for n in names if n in ("server:pressure", "server:residual", "server:unet", "server:default")]
    assert all(st["ls"] == "-" and not isinstance(st["color"], str) for st in learned)
    assert all(isinstance(styles[n]["color"], str) and styles[n]["ls"] != "-" for n in ("none", "copy", "server:bad"))


def test_a_long_name_is_cut_short_in_the_legend():
    from bench.iterations import legend_label

    assert legend_label("server:default") == "server:default"
    long = "server:" + "x" * 80
    assert len(legend_label(long)) == 60 and legend_label(long).endswith("\u2026")


def test_iteration_figures_are_the_same_in_process_on_workers_and_on_ray(tmp_path, ray_cluster):
    from bench.iterations import TIMING_FIELDS
    from server.process import ServerProcess

    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    figures = {}
    with ServerProcess(models) as server:  # one server for the three runs; every task opens its own stream
        for backend, flags in (("process", []), ("workers", ["--workers", "2"]), ("ray", ["--ray", ray_cluster])):
            out = tmp_path / backend
            assert main(["bench", "iterations", "--seeds", "901-902", "--steps", "30", "--warm-starts",
                         "none,builtin,extrapolate,server:tiny,server:grid-identity", "--server", server.address,
                         "--deadline-ms", "1000", "--out", str(out), "--quiet", *flags]) == 0
            summary = json.loads((out / "summary.json").read_text())["warm_starts"]
            figures[backend] = {name: {k: v for k, v in s.items() if k not in TIMING_FIELDS}
                                for name, s in summary.items()}
    assert figures["process"]["server:tiny"]["fallback_steps"] == 0
    assert figures["workers"] == figures["process"]
    assert figures["ray"] == figures["process"]


def test_server_warm_starts_on_a_ray_cluster_need_a_reachable_server(tmp_path, capsys):
    assert main(["bench", "iterations", "--seeds", "901", "--warm-starts", "builtin,server:pressure",
                 "--ray", "ray://head:10001", "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "--server" in capsys.readouterr().err


def test_runs_on_seeds_models_saw_are_flagged_and_choosing_seeds_are_not(tmp_path, capsys):
    for seeds, flagged in (("848-851", True), ("850-851", False)):
        assert main(["bench", "iterations", "--seeds", seeds, "--steps", "40", "--warm-starts", "builtin",
                     "--out", str(tmp_path / seeds), "--quiet"]) == 0
        warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning")]
        # Only the validation seeds are named: 850-899 are held out for choosing variants.
        assert warnings == (["warning: seeds 848-849 are training or validation seeds (1-849): models were fitted "
                             "or stopped on them, so results there are not held out (choose on 850-899, report on "
                             "900-999)"] if flagged else [])


def test_steps_at_the_cap_are_priced_apart_from_those_that_converge():
    from bench.iterations import cap_summary, cap_table

    # (steps, candidates) per seed, builtin first: one capped step a seed; the model
    # brings the first seed's under the cap and halves the rest
    per_seed = [np.array([[1000, 600], [200, 100], [100, 50]]), np.array([[1000, 1000], [300, 150]])]
    c = cap_summary(per_seed, cap=1000)
    assert c["cap"] == 1000 and c["builtin_steps"] == 2 / 5
    assert c["builtin_iterations"] == 2000 / 2600
    assert c["steps"] == [2 / 5, 1 / 5] and c["freed"] == [0.0, 0.5]
    assert c["over_builtin_under"][1]["value"] == 0.5  # where Builtin converges, half its iterations
    assert c["over_builtin_at"][1]["value"] == 1600 / 2000
    assert c["over_builtin_at"][1]["seeds"] == 2
    lines = cap_table(["builtin", "server:m"], c)
    assert "Builtin ends 40.0% of these steps there, 76.9% of its iterations" in lines[1]
    assert lines[-1].startswith("| server:m | 20.0% | 50.0% | 0.500 [")


def test_at_the_cap_a_start_is_also_priced_by_its_sweeps_to_builtins_accuracy():
    from bench.iterations import cap_summary, cap_table

    per_seed = [np.array([[1000, 1000], [200, 100]]), np.array([[1000, 1000], [300, 150]])]
    # the same steps' sweeps to Builtin's accuracy: the model gets there in 400 and 600
    reach = [np.array([[1000, 400], [200, 100]]), np.array([[800, 600], [300, 150]])]
    c = cap_summary(per_seed, cap=1000, reach=reach)
    assert c["over_builtin_at"][1]["value"] == 1.0  # the iteration count cannot see it
    assert c["reach_at"][1]["value"] == 1000 / 1800
    assert c["reach_all"][1]["value"] == 1250 / 2300
    row = cap_table(["builtin", "server:m"], c)[-1]
    assert row.startswith("| server:m | 50.0% | 0.0% | 0.500 [") and "| 0.556 [" in row and "| 0.543 [" in row


def test_a_model_the_server_refuses_for_this_world_stops_the_run_before_it_starts(tmp_path, capsys):
    from server.process import ServerProcess

    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    out = tmp_path / "out"
    with ServerProcess(models, "--max-grid-nodes", str(61 * 61)) as server:  # the thesis box and no more
        assert main(["bench", "iterations", "--seeds", "901", "--steps", "10", "--box-size", "16", "16",
                     "--warm-starts", "builtin,server:tiny", "--server", server.address, "--out", str(out),
                     "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "refuses server:tiny for this world" in err and "65x65" in err
    assert not (out / "summary.json").exists() and not (out / "results.md").exists()
