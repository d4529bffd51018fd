"""lab/shadow_ablation.sh: the ablation's same-state column prices shipped models only."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_every_model_the_script_prices_is_shipped_and_priced_once():
    script = (ROOT / "lab" / "shadow_ablation.sh").read_text()
    batches = re.findall(r'"([^"]*)"', script[script.index("batches=("):script.index("\n)\n")], re.S)
    names = [n for b in batches for n in b.split()]
    assert len(batches) == 3 and len(names) == len(set(names)) > 60
    assert all(any((ROOT / d / f"{n}.json").is_file() for d in ("models", "lab/models")) for n in names)
    assert "graph-projected-max-1-799-long-e2" not in names  # the default it was measured with is served, not priced
    assert "candidates=server:graph-projected-max-1-799-long-e2\n" in script
