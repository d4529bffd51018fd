"""Run one function over many tasks: in this process, in a process pool, or on Ray.

    tasks = [Task(f"seed {s}", (spec_dict, s)) for s in seeds]
    with Dispatcher(workers=2, ray=None) as dispatcher:
        for result in dispatcher.map(simulate, tasks, progress="generate"):
            ...  # results in task order, whatever order they finished in

One task is one simulation. The caller gets the results in the order of its
tasks, so what it writes does not depend on scheduling; a tqdm bar counts the
tasks as they complete. Three backends, one loop:

    workers=1, ray=None   this process, one task after the other
    workers=N, ray=None   N spawned processes on this machine (spawn, not fork:
                          the parent may hold gRPC channels, which do not survive
                          a fork)
    ray="local"           a Ray started for this run with N CPUs, stopped after it
    ray=ADDRESS           an existing Ray cluster: "auto", "HOST:PORT" from one of
                          its nodes, or "ray://HOST:10001" (Ray Client) from anywhere

What a task returns must be a dict of NumPy arrays or a str (e.g. JSON text):
pool workers hand arrays over as a temporary .npz, Ray carries them in its
object store; nothing is written to or read from a file with pickle. At most
4 tasks per CPU are in flight, so results waiting for an earlier task stay
bounded.

Faults: on Ray a task whose worker dies, or that raises, runs once more
(`max_retries=1`, `retry_exceptions=True`); a task that fails twice raises
`TaskFailed` naming it, and the tasks still pending are cancelled. Without
Ray there are no retries: the first failure names its task. A dead pool
worker breaks the whole pool, so that error lists the tasks left unfinished,
the one it ran among them. Pool workers end themselves within a second of
the process that started them dying, so a run killed by a signal Python does
not catch (SIGKILL; SIGTERM's default) leaves no simulation running on.

Test hook (workers only, never this process): with DEEPCONTACT_TEST_KILL_TASK
set to a task's name, the worker running it exits at once with status 1; with
DEEPCONTACT_TEST_KILL_ONCE set to a file path as well, only the first attempt
does (the file marks that it happened).
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import logging
import multiprocessing
import os
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

RAY_VERSION = "2.60.0"
INSTALL_RAY = f"--ray needs Ray: pip install '.[ray]' (ray[client]=={RAY_VERSION}) in this environment"
TEST_KILL_TASK = "DEEPCONTACT_TEST_KILL_TASK"
TEST_KILL_ONCE = "DEEPCONTACT_TEST_KILL_ONCE"
TASKS_PER_CPU = 4  # in flight: enough to keep every CPU busy while the earliest task finishes
PARENT_POLL_S = 0.5  # how often a pool worker looks whether the process that started it is still there


class Task(NamedTuple):
    name: str  # how errors name it, e.g. "seed 12"
    args: tuple


class DispatchError(RuntimeError):
    """Ray could not start or be reached, or a task failed; the message says which."""


class TaskFailed(DispatchError):
    """A task failed on every attempt; the message names the task."""


def add_arguments(parser: argparse.ArgumentParser, *, workers_default: str) -> None:
    """--workers and --ray, as `generate` and `bench iterations` share them."""
    parser.add_argument("--workers", type=int, metavar="N",
                        help=f"processes on this machine, one simulation each at a time (default: {workers_default}); "
                             "with --ray and no address, the CPUs of the Ray started for the run (default: all cores)")
    parser.add_argument("--ray", nargs="?", const="local", metavar="ADDRESS",
                        help="one Ray task per simulation. No ADDRESS: start a local Ray for this run (no dashboard, "
                             "no usage stats) and stop it after; 'auto' or HOST:PORT: the cluster this machine belongs "
                             "to; ray://HOST:10001: a cluster through Ray Client. A simulation whose worker dies runs "
                             "once more. Needs Ray: pip install '.[ray]'")


def check_arguments(args: argparse.Namespace) -> None:
    """ValueError with a one-line message if --workers/--ray cannot work here."""
    if args.workers is not None and args.workers < 1:
        raise ValueError("--workers must be >= 1")
    if args.ray is not None:
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ValueError(INSTALL_RAY) from None


class Dispatcher:
    """A context that runs tasks on one backend (see the module docstring)."""

    def __init__(self, *, workers: int | None = None, ray: str | None = None):
        """workers: processes on this machine (None or 1: this process), or the
        CPUs of a local Ray (None: all cores). ray: None, "local" or an address."""
        self.workers = workers
        self.ray = ray
        self._backend: _InProcess | _Pool | _Ray | None = None

    def __enter__(self) -> "Dispatcher":
        if self.ray is not None:
            self._backend = _Ray(self.ray, self.workers)
        elif (self.workers or 1) > 1:
            self._backend = _Pool(self.workers)
        else:
            self._backend = _InProcess()
        return self

    def __exit__(self, *exc) -> None:
        self._backend.close()

    @property
    def description(self) -> str:
        """For a command's summary line, e.g. '2 worker processes' or 'Ray at ray://head:10001 with 8 CPUs'."""
        return self._backend.description

    def map(self, fn: Callable[..., Any], tasks: Sequence[Task], *, progress: str | None = None) -> Iterator[Any]:
        """fn(*task.args) for every task; yields the results in task order.

        fn: a module-level function (workers import it by name) returning a
        dict of NumPy arrays or a str. progress: the tqdm bar's label, or
        None for no bar. Raises TaskFailed naming the first task that failed.
        """
        backend = self._backend
        kill = _kill_hook()
        pending: dict[Any, int] = {}  # handle -> task index
        finished: dict[int, Any] = {}  # task index -> result, completed but not yet yielded
        submitted = 0
        with _progress(len(tasks), progress) as bar:
            for i in range(len(tasks)):
                # Keep at most `width` tasks between submission and being yielded.
                while submitted < len(tasks) and submitted - i < backend.width:
                    pending[backend.submit(fn, tasks[submitted], kill)] = submitted
                    submitted += 1
                while i not in finished:
                    for handle in backend.wait(list(pending)):
                        index = pending.pop(handle)
                        # Raises as soon as any task has failed, not when its turn comes.
                        finished[index] = backend.collect(handle, tasks[index])
                        bar.update(1)
                yield finished.pop(i)


# -- backends ------------------------------------------------------------------
# Each has: width (tasks in flight), description, submit(fn, task, kill) -> handle,
# wait(handles) -> some completed handles, collect(handle, task) -> result (or
# TaskFailed naming the task), and close().

class _InProcess:
    """Runs each task as it is submitted; the handle is its outcome."""

    width = 1
    description = "1 process"

    def submit(self, fn, task: Task, kill) -> "_Outcome":
        try:
            return _Outcome(fn(*task.args), None)
        except Exception as exc:  # noqa: BLE001 - collect() reports it with the task's name
            return _Outcome(None, exc)

    def wait(self, handles):
        return handles

    def collect(self, handle: "_Outcome", task: Task):
        if handle.error is not None:
            raise TaskFailed(f"{task.name} failed: {_reason(handle.error)}") from handle.error
        return handle.value

    def close(self) -> None:
        pass


class _Outcome:
    """A task's value or error (hashed by identity: it is a handle)."""

    def __init__(self, value: Any, error: Exception | None):
        self.value, self.error = value, error


class _Pool:
    """Spawned worker processes on this machine; arrays come back as .npz."""

    def __init__(self, workers: int):
        self.width = TASKS_PER_CPU * workers
        self.description = f"{workers} worker processes"
        self._tmp = tempfile.TemporaryDirectory(prefix="deepcontact-dispatch-")
        self._pool = cf.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                            initializer=_exit_with_parent, initargs=(os.getpid(),))
        self._unfinished: dict[cf.Future, str] = {}  # submitted, not yet collected -> task name

    def submit(self, fn, task: Task, kill) -> cf.Future:
        future = self._pool.submit(_run_in_pool, fn, task, kill, self._tmp.name)
        self._unfinished[future] = task.name
        return future

    def wait(self, handles):
        return cf.wait(handles, return_when=cf.FIRST_COMPLETED).done

    def collect(self, handle: cf.Future, task: Task):
        exc = handle.exception()
        if isinstance(exc, cf.process.BrokenProcessPool):
            # Every unfinished task fails alike; which of them the dead worker ran is not known.
            names = list(self._unfinished.values())
            listed = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
            raise TaskFailed(f"a worker process died running one of: {listed} "
                             "(no retries without --ray)") from exc
        del self._unfinished[handle]
        if exc is not None:
            raise TaskFailed(f"{task.name} failed: {_reason(exc)}") from exc
        value = handle.result()
        if isinstance(value, _NpzPath):
            with np.load(value, allow_pickle=False) as z:
                value_arrays = {k: z[k] for k in z.files}
            os.unlink(value)
            return value_arrays
        return value

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._tmp.cleanup()


class _NpzPath(str):
    """A pool worker's result, written to this .npz (told apart from a str result)."""


#: starts of a local Ray before giving up: on two busy cores one start in a few timed out
LOCAL_RAY_STARTS = 2


class _Ray:
    """Ray tasks with one retry; a local Ray is started here and stopped in close()."""

    def _start_local(self, workers: int | None) -> None:
        ray = self._ray
        # No network at run time: no usage-stats reporter, no dashboard.
        os.environ["RAY_USAGE_STATS_ENABLED"] = "0"
        # Ray waits 30 s for its GCS to write its port file; on two cores busy with training,
        # a start took longer (a CI run of 2026-11-27 failed so). A user's setting wins.
        os.environ.setdefault("RAY_gcs_server_port_wait_time_s", "120")
        # Its wait for the raylet to register is a fixed 30 s, which a start beside another Ray on
        # two busy cores also overran (a CI run of 2026-11-30): a second start, from nothing, then.
        for attempt in range(LOCAL_RAY_STARTS):
            try:
                ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, include_dashboard=False,
                         log_to_driver=False, logging_level=logging.WARNING)
                return
            except Exception:  # noqa: BLE001 - Ray raises a bare Exception for the timeout
                ray.shutdown()
                if attempt == LOCAL_RAY_STARTS - 1:
                    raise
                print("a local Ray did not start; starting it once more", file=sys.stderr)

    def __init__(self, address: str, workers: int | None):
        import ray

        self._ray = ray
        try:
            if address == "local":
                self._start_local(workers)
            else:
                ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        except Exception as exc:  # noqa: BLE001 - unreachable, refused, bad token: all end the run the same way
            ray.shutdown()
            if address == "local":
                raise DispatchError(f"could not start a local Ray (tried {LOCAL_RAY_STARTS} times): "
                                    f"{_reason(exc)}") from exc
            # Ray sends no token to an address named explicitly unless told to (it does for auto); a refused token
            # then looks like a timeout.
            hint = ("" if address == "auto" or os.environ.get("RAY_AUTH_MODE") else
                    " (a cluster with token authentication, Ray's default, also needs RAY_AUTH_MODE=token "
                    "and its token in RAY_AUTH_TOKEN or ~/.ray/auth_token)")
            raise DispatchError(f"could not connect to Ray at {address}: {_reason(exc)}{hint}") from exc
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        self.width = TASKS_PER_CPU * cpus
        self.description = ("a local Ray" if address == "local" else f"Ray at {address}") + f" with {cpus} CPUs"
        # Two attempts per task: a worker that dies (or an error raised) gets one more try.
        self._remote = ray.remote(max_retries=1, retry_exceptions=True)(_run_in_worker)
        self._pending: set = set()

    def submit(self, fn, task: Task, kill):
        ref = self._remote.remote(fn, task, kill)
        self._pending.add(ref)
        return ref

    def wait(self, handles):
        ready, _ = self._ray.wait(handles, num_returns=1)
        return ready

    def collect(self, handle, task: Task):
        self._pending.discard(handle)
        errors = self._ray.exceptions
        try:
            return self._ray.get(handle)
        except errors.RayTaskError as exc:
            raise TaskFailed(f"{task.name} failed twice: {_reason(exc.cause)}") from None
        except errors.WorkerCrashedError:
            raise TaskFailed(f"{task.name} failed twice: its worker process died") from None
        except errors.RayError as exc:
            raise TaskFailed(f"{task.name} failed: {_reason(exc)}") from None

    def close(self) -> None:
        for ref in self._pending:
            self._ray.cancel(ref)
        self._ray.shutdown()


# -- in the workers ------------------------------------------------------------

def _exit_with_parent(parent: int) -> None:
    """Pool worker initializer: exit once `parent` (the pool's process) is gone.

    A parent killed by SIGKILL, or by SIGTERM with Python's default handling, never
    shuts its pool down, and its workers would run their simulations to the end, minutes
    of two busy cores that nobody reads. Ctrl-C reaches the whole process group and
    needs none of this. Orphans are re-parented, so a changed parent pid is the sign."""
    def watch():
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _run_in_worker(fn, task: Task, kill: tuple[str, str | None] | None):
    if kill is not None and kill[0] == task.name:
        marker = kill[1]
        if marker is None or _first_time(marker):
            os._exit(1)  # as a crash would: no exception, no cleanup
    return fn(*task.args)


def _run_in_pool(fn, task: Task, kill, tmpdir: str):
    value = _run_in_worker(fn, task, kill)
    if isinstance(value, dict):
        # Hand arrays over as a file, not through the pool's pickled pipe.
        path = Path(tmpdir) / f"{uuid.uuid4().hex}.npz"
        np.savez(path, **value)
        return _NpzPath(path)
    return value


def _first_time(marker: str) -> bool:
    try:
        with open(marker, "x"):
            return True
    except FileExistsError:
        return False


def _kill_hook() -> tuple[str, str | None] | None:
    name = os.environ.get(TEST_KILL_TASK)
    return (name, os.environ.get(TEST_KILL_ONCE)) if name else None


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1]}" if text else type(exc).__name__


class _progress:
    """A tqdm bar over completed tasks on stderr; a no-op without a label."""

    def __init__(self, total: int, label: str | None):
        self.bar = None
        if label is not None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, unit="sim", desc=label, file=sys.stderr)

    def __enter__(self) -> "_progress":
        return self

    def update(self, n: int) -> None:
        if self.bar is not None:
            self.bar.update(n)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.close()

