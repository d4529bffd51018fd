"""Install what you use: serving and simulating need no TensorFlow, and a command whose part needs
an extra that is not installed says which one, in one line."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("tensorflow", "tf2onnx", "keras", "h5py", "matplotlib", "hdrh", "ray")

SERVE_AND_SIMULATE = """
import sys
from server.serve import Server
from simclient.client import WarmStartClient
from simclient.guard import Guard
from simclient.scene import SceneSpec
from simclient.simulate import run_simulation
from simclient.warmstarts import make_provider
import dataclasses
server = Server(models="models").start()
try:
    with WarmStartClient(server.address) as client:
        spec = dataclasses.replace(SceneSpec.thesis(), steps=120)
        result = run_simulation(spec, 901, make_provider("server:default"), client=client, deadline_ms=2000,
                                guard=Guard())
    assert result["summary"]["steps_with_contacts"] > 0 and result["summary"]["fallback_steps"] == 0
finally:
    server.stop()
print(" ".join(m for m in {heavy!r} if m in sys.modules) or "none")
"""


def test_serving_and_simulating_import_no_tensorflow_nor_the_benches_packages():
    run = subprocess.run([sys.executable, "-c", SERVE_AND_SIMULATE.format(heavy=HEAVY)], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip().splitlines()[-1] == "none"


def test_a_command_whose_part_needs_a_missing_extra_says_which_extra(tmp_path):
    # None in sys.modules: the import fails as it does where the extra is not installed.
    env = {k: v for k, v in os.environ.items() if k != "DEEPCONTACT_DEBUG"}
    for package, argv, extra in (("h5py", ["generate", "--seeds", "1", "--out", str(tmp_path / "x.h5")], "train"),
                                 ("matplotlib", ["bench", "iterations", "--seeds", "901", "--steps", "5",
                                                 "--warm-starts", "none,builtin", "--quiet", "--out", str(tmp_path / "it")],
                                  "bench")):
        code = f"import sys; sys.modules[{package!r}] = None; from commands import main; sys.exit(main({argv!r}))"
        run = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, env=env,
                             timeout=120)
        said = run.stderr.strip().splitlines()
        assert run.returncode == 2 and len(said) == 1, (package, run.stderr)
        assert said[0].endswith(f"needs {package}, which this install lacks: pip install 'deepcontact[{extra}]'")
        assert said[0].startswith(f"deepcontact {argv[0]}")
