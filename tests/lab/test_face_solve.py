"""`deepcontact lab face-solve`: the face route's parts timed by step size, on the shipped default."""

from __future__ import annotations

import json
import platform

from commands import main


def test_bench_face_solve_times_each_part_and_the_route_with_both_heaps(tmp_path, capsys):
    out = tmp_path / "face-solve.json"
    assert main(["lab", "face-solve", "--steps", "90", "--json", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["model"] == "default" and result["steps"] == len(result["rows"]) > 0
    for row in result["rows"]:
        assert row["unknowns"] > 0 and min(row["system_ms"], row["gelsy_ms"], row["route_ms"]) > 0
        if platform.libc_ver()[0] == "glibc":  # the route again at glibc's starting thresholds
            assert row["route_glibc_heap_ms"] > 0
    assert sum(size["steps"] for size in result["by_size"]) == result["steps"]
    assert "| points | steps | unknowns |" in capsys.readouterr().out


def test_bench_face_solve_refuses_a_card_without_a_face(capsys):
    assert main(["lab", "face-solve", "--model", "pressure", "--steps", "5"]) == 2
    assert "has no face" in capsys.readouterr().err
