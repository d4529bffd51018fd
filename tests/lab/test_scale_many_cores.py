"""lab/scale_many_cores.sh: one run answers generate's per-compression rate and the served sweep's cost."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_the_script_runs_small_and_every_compression_records_the_same_simulations(tmp_path):
    env = dict(os.environ, PY=sys.executable, WORKERS="2", GEN_SEEDS="1-2", IT_SEEDS="901-901", REPEATS="1")
    subprocess.run(["bash", str(ROOT / "lab" / "scale_many_cores.sh"), str(tmp_path)], cwd=ROOT, env=env,
                   check=True, capture_output=True, text=True)

    generate = json.loads((tmp_path / "generate.json").read_text())
    assert [r["compression"] for r in generate["runs"]] == ["gzip", "lzf", "none"]
    assert all(r["same_as_gzip"] and r["simulations"] == 2 and r["wall_s"] > 0 for r in generate["runs"])
    # Uncompressed is the largest file: the compressions really differ.
    sizes = {r["compression"]: r["mb_per_simulation"] for r in generate["runs"]}
    assert sizes["none"] > sizes["lzf"] and sizes["none"] > sizes["gzip"]

    for name, simulations in (("builtin", 1), ("replicas1", 2), ("replicas4", 2)):
        run = json.loads((tmp_path / f"iterations-{name}.json").read_text())["results"]["iterations"]["workers=2"]
        assert run["simulations"] == simulations and run["same_answers"]
