"""What a training run ran on, for its card: the facts a byte-for-byte rebuild depends on.

TensorFlow's CPU kernels (oneDNN's matrix products among them) pick their vector
instructions when they run, so the same run on a CPU with AVX-512 and on one with
AVX2 only adds in other orders and, over thousands of updates, ends at other
weights; so can another TensorFlow build or thread count. A rebuild that differs
from a card's weights is first checked against these.

    describe()
    # {"cpu": "AMD EPYC", "vector": "avx512", "cores": 2, "onednn": "default",
    #  "onednn_isa": "default", "python": "3.11.7"}
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

_CPUINFO = Path("/proc/cpuinfo")


def _cpuinfo() -> tuple[str, set[str]]:
    """(model name, flags) of the first CPU in /proc/cpuinfo; ("unknown", set()) off Linux."""
    try:
        text = _CPUINFO.read_text()
    except OSError:
        return platform.processor() or "unknown", set()
    fields = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if not sep:
            if fields:
                break  # the first CPU's block ends at its blank line
            continue
        fields.setdefault(key.strip(), value.strip())
    return fields.get("model name", "unknown"), set(fields.get("flags", "").split())


def vector_level(flags: set[str]) -> str:
    """The widest x86 vector extension among /proc/cpuinfo's flags: avx512, avx2, avx, sse4_2 or
    "other" (another architecture, or none of these)."""
    for level, flag in (("avx512", "avx512f"), ("avx2", "avx2"), ("avx", "avx"), ("sse4_2", "sse4_2")):
        if flag in flags:
            return level
    return "other"


def describe() -> dict[str, object]:
    """The CPU's model and widest vector extension, the cores this process may use, whether
    TensorFlow's oneDNN kernels were switched (TF_ENABLE_ONEDNN_OPTS) or held to a narrower
    instruction set than the CPU's (ONEDNN_MAX_CPU_ISA; each "default" if unset), and the
    Python version."""
    model, flags = _cpuinfo()
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": model, "vector": vector_level(flags), "cores": cores,
            "onednn": os.environ.get("TF_ENABLE_ONEDNN_OPTS", "default"),
            "onednn_isa": os.environ.get("ONEDNN_MAX_CPU_ISA", "default"), "python": platform.python_version()}
