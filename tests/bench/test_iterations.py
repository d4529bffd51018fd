"""`deepcontact bench iterations` end to end: starts its own server, writes table and figures."""

from __future__ import annotations

import json

from deepcontact.cli import main
from tests.server.conftest import write_conv_model


def test_bench_iterations_writes_summary_table_and_figures(tmp_path):
    models = tmp_path / "models"
    models.mkdir()
    write_conv_model(models, "tiny")
    out = tmp_path / "out"
    assert main(["bench", "iterations", "--seeds", "901", "--steps", "30", "--warm-starts",
                 "none,builtin,extrapolate,server:tiny,server:grid-identity", "--models", str(models),
                 "--deadline-ms", "1000", "--out", str(out), "--quiet"]) == 0
    summary = json.loads((out / "summary.json").read_text())["warm_starts"]
    assert set(summary) == {"none", "builtin", "extrapolate", "server:tiny", "server:grid-identity"}
    assert summary["server:tiny"]["p50_latency_ms"] > 0 and summary["server:tiny"]["fallback_steps"] == 0
    assert "| builtin |" in (out / "results.md").read_text()
    for fig in ("fig20_contacts_iterations.png", "fig21_convergence.png", "fig26_mse.png"):
        assert (out / fig).stat().st_size > 10_000
