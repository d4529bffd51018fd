"""Every command on degenerate input (no contacts yet, one body, zero steps)
ends with its summary or a one-line error, never a traceback."""

from __future__ import annotations

import json

import pytest

from commands import main


@pytest.fixture(scope="module")
def no_contacts(tmp_path_factory):
    """A data file of 3 steps: the bodies are still falling."""
    path = tmp_path_factory.mktemp("data") / "falling.h5"
    assert main(["generate", "--seeds", "5", "--steps", "3", "--workers", "1", "--out", str(path), "--quiet"]) == 0
    return path


def run(capsys, argv: list[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    return code, out, err


def one_line_error(err: str, words: str) -> bool:
    lines = [line for line in err.splitlines() if line.strip()]
    return len(lines) == 1 and lines[0].startswith(f"deepcontact {words}: ")


@pytest.mark.parametrize("scene", [["--steps", "3"], ["--bodies", "1", "--steps", "20"]],
                         ids=["still-falling", "one-body"])
def test_simulate_without_contacts_says_so_and_keeps_nulls(capsys, tmp_path, scene):
    out_file = tmp_path / "r.json"
    code, out, _ = run(capsys, ["simulate", "--seed", "905", *scene, "--warm-start", "builtin",
                                "--out", str(out_file), "--quiet"])
    assert code == 0 and "no steps with contacts" in out and str(out_file) in out
    summary = json.loads(out_file.read_text())["summary"]
    assert summary["steps_with_contacts"] == 0
    assert summary["mean_velocity_iterations"] is None and summary["p50_latency_ms"] is None


@pytest.mark.parametrize("words, argv", [
    ("simulate", ["--seed", "905", "--steps", "0", "--warm-start", "builtin", "--out", "{tmp}/r.json"]),
    ("generate", ["--seeds", "5", "--steps", "0", "--out", "{tmp}/d.h5"]),
    ("bench server", ["--steps", "3", "--models", "{models}", "--model", "tiny"]),
    ("bench server", ["--steps", "0", "--models", "{models}", "--model", "tiny"]),
    ("bench load", ["--server", "127.0.0.1:9", "--model", "tiny", "--replay", "{data}", "--out", "{tmp}/load"]),
    ("bench load", ["--server", "127.0.0.1:9", "--model", "tiny", "--duration", "0", "--out", "{tmp}/load"]),
    ("bench soak", ["--duration", "0", "--out", "{tmp}/soak"]),
    ("train", ["--train", "{data}", "--val", "{data}", "--out", "{tmp}/run"]),
    ("evaluate", ["--model", "{models}/tiny.onnx", "--data", "{data}"]),
], ids=lambda x: x if isinstance(x, str) else None)
def test_commands_refuse_what_they_cannot_use_in_one_line(capsys, tmp_path, no_contacts, model_dir, words, argv):
    fill = {"tmp": tmp_path, "models": model_dir, "data": no_contacts}
    code, _, err = run(capsys, words.split() + [a.format(**fill) for a in argv])
    assert code == 2 and one_line_error(err, words), err


def test_bench_iterations_without_contacts_writes_its_table_and_figures(capsys, tmp_path):
    code, out, _ = run(capsys, ["bench", "iterations", "--seeds", "905", "--steps", "3",
                                "--warm-starts", "none,builtin,extrapolate", "--out", str(tmp_path), "--quiet"])
    assert code == 0 and "No steps with contacts" in out
    summary = json.loads((tmp_path / "summary.json").read_text())["warm_starts"]
    assert all(s["mean_velocity_iterations"] is None for s in summary.values())
    assert (tmp_path / "fig21_convergence.png").exists()


def test_the_transfer_table_after_zero_steps(capsys):
    code, out, _ = run(capsys, ["transfer-table", "--steps", "0"])
    assert code == 0 and out.strip()


def test_an_unexpected_error_is_one_line_unless_debugging(capsys, monkeypatch, tmp_path):
    import simclient.simulate

    def broken(*args, **kwargs):
        raise ZeroDivisionError("a bug")

    monkeypatch.setattr(simclient.simulate, "run_simulation", broken)
    argv = ["simulate", "--seed", "905", "--steps", "3", "--warm-start", "builtin", "--out", str(tmp_path / "r.json"),
            "--quiet"]
    monkeypatch.delenv("DEEPCONTACT_DEBUG")
    code, _, err = run(capsys, argv)
    assert code == 1 and one_line_error(err, "simulate") and "ZeroDivisionError: a bug" in err
    monkeypatch.setenv("DEEPCONTACT_DEBUG", "1")
    with pytest.raises(ZeroDivisionError):
        main(argv)
