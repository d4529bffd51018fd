"""training.machine: the facts about the machine that a training card records."""

from __future__ import annotations

from training import machine


def test_the_vector_level_is_the_widest_extension_the_cpu_has():
    assert machine.vector_level({"sse4_2", "avx", "avx2", "avx512f", "avx512bw"}) == "avx512"
    assert machine.vector_level({"sse4_2", "avx", "avx2", "fma"}) == "avx2"
    assert machine.vector_level({"asimd", "fp"}) == "other"  # an ARM CPU's flags


def test_the_description_reads_the_first_cpu_block(tmp_path, monkeypatch):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: Test CPU\nflags\t\t: fpu sse4_2 avx avx2\n\n"
                    "processor\t: 1\nmodel name\t: Other CPU\nflags\t\t: fpu avx512f\n")
    monkeypatch.setattr(machine, "_CPUINFO", info)
    monkeypatch.setenv("TF_ENABLE_ONEDNN_OPTS", "0")
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    got = machine.describe()
    assert got["cpu"] == "Test CPU" and got["vector"] == "avx2" and got["onednn"] == "0"
    assert got["onednn_isa"] == "AVX2"  # a run held to AVX2 on a wider CPU says so
    assert got["cores"] >= 1


def test_without_cpuinfo_the_description_still_has_every_field(tmp_path, monkeypatch):
    monkeypatch.setattr(machine, "_CPUINFO", tmp_path / "missing")
    got = machine.describe()
    assert set(got) == {"cpu", "vector", "cores", "onednn", "onednn_isa", "python"} and got["vector"] == "other"
