"""deepcontact.dispatch: what the process pool leaves behind when its caller dies, and a
local Ray that does not start at once.

(Results in task order, failures named, Ray's retry: tests/training/test_generate.py, which
drives the dispatcher through `deepcontact generate`.)"""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from deepcontact import dispatch

ROOT = Path(__file__).resolve().parents[2]


def write_pid_and_wait(folder: str) -> str:
    """A task that never ends by itself: it says which process runs it, then sleeps."""
    Path(folder, f"{os.getpid()}.pid").write_text("")
    time.sleep(600)
    return "never"


CALLER = """
import sys
from deepcontact.dispatch import Dispatcher, Task
from tests.deepcontact.test_dispatch import write_pid_and_wait
with Dispatcher(workers=2) as dispatcher:
    for _ in dispatcher.map(write_pid_and_wait, [Task(f"task {i}", (sys.argv[1],)) for i in range(2)]):
        pass
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie has exited; only its exit status is left to be collected.
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] == "Z")


def _wait_for(condition, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.1)
    return condition()


def test_pool_workers_stop_when_the_caller_is_killed(tmp_path):
    caller = subprocess.Popen([sys.executable, "-c", CALLER, str(tmp_path)], cwd=ROOT)
    try:
        assert _wait_for(lambda: len(list(tmp_path.glob("*.pid"))) == 2, 120), "the two tasks never started"
        workers = [int(p.stem) for p in tmp_path.glob("*.pid")]
        assert all(_alive(pid) for pid in workers)
        caller.send_signal(signal.SIGKILL)  # no cleanup of any kind in the caller
        caller.wait()
        # Generous: a worker looks every PARENT_POLL_S; a loaded machine may take longer.
        assert _wait_for(lambda: not any(_alive(pid) for pid in workers), 30), "a pool worker outlived its caller"
    finally:
        caller.kill()
        for pid in [int(p.stem) for p in tmp_path.glob("*.pid")]:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_local_ray_that_does_not_start_is_started_once_more(monkeypatch, capsys):
    # Ray's own start timeout cannot be provoked on demand, so the first start is made to fail
    # as it does (a bare Exception); the second is Ray's real start.
    ray = pytest.importorskip("ray")

    real_init, calls = ray.init, []

    def init_failing_once(*args, **kwargs):
        calls.append(kwargs)
        if len(calls) == 1:
            raise Exception("The current node timed out during startup.")
        return real_init(*args, **kwargs)

    monkeypatch.setattr(ray, "init", init_failing_once)
    with dispatch.Dispatcher(workers=1, ray="local") as dispatcher:
        assert list(dispatcher.map(str, [dispatch.Task("one", (7,))])) == ["7"]
    assert len(calls) == 2 and "starting it once more" in capsys.readouterr().err

    def init_failing(*args, **kwargs):
        calls.append(kwargs)
        raise Exception("The current node timed out during startup.")

    calls.clear()
    monkeypatch.setattr(ray, "init", init_failing)
    with pytest.raises(dispatch.DispatchError, match=f"tried {dispatch.LOCAL_RAY_STARTS} times"):
        dispatch.Dispatcher(workers=1, ray="local").__enter__()
    assert len(calls) == dispatch.LOCAL_RAY_STARTS
