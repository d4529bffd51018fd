"""Dynamic micro-batching across concurrent streams, like Triton's dynamic batcher.

Steps from different simulations arrive on different threads. Instead of one
ONNX call each, the batcher waits at most `max_delay_us` after the first
queued input for up to `max_batch` inputs of the same grid shape, runs them
as one batch and hands each caller its row. Past `max_queue` waiting inputs it
refuses new work (QueueFull) so the server can answer RESOURCE_EXHAUSTED
promptly instead of letting latency grow without bound.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np


class QueueFull(RuntimeError):
    pass


class MicroBatcher:
    """Wraps `run(x (B, ny, nx, C)) -> (B, ny, nx, Cout)` for single inputs.

        batcher = MicroBatcher(predictor.run_session, max_batch=8, max_delay_us=500)
        y = batcher(x)          # x (1, ny, nx, C); blocks until its batch ran
    """

    def __init__(self, run: Callable[[np.ndarray], np.ndarray], *, max_batch: int, max_delay_us: int,
                 max_queue: int = 1024):
        if max_batch < 1 or max_delay_us < 0:
            raise ValueError("max_batch must be >= 1 and max_delay_us >= 0")
        self._run = run
        self.max_batch = max_batch
        self.max_delay = max_delay_us / 1e6
        self.max_queue = max_queue
        self._queue: collections.deque[tuple[np.ndarray, Future]] = collections.deque()
        self._cond = threading.Condition()
        self._closed = False
        self.batches = 0  # batches run, for metrics and tests
        self._thread = threading.Thread(target=self._loop, name="micro-batcher", daemon=True)
        self._thread.start()

    def __call__(self, x: np.ndarray) -> np.ndarray:
        fut: Future = Future()
        with self._cond:
            if self._closed:
                raise RuntimeError("batcher closed")
            if len(self._queue) >= self.max_queue:
                raise QueueFull(f"{len(self._queue)} inputs already wait for inference (limit {self.max_queue})")
            self._queue.append((x, fut))
            self._cond.notify()
        return fut.result()

    def close(self, timeout: float = 5.0) -> None:
        """Refuse new inputs; the batcher thread (a daemon) runs what is
        queued and ends. Waits for it at most `timeout` seconds."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=timeout)

    def _take_batch(self) -> list[tuple[np.ndarray, Future]] | None:
        with self._cond:
            while not self._queue and not self._closed:
                self._cond.wait()
            if not self._queue:
                return None
            deadline = time.monotonic() + self.max_delay
            while len(self._queue) < self.max_batch and not self._closed:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cond.wait(left)
            # Same grid shape only: the first input decides; others wait their turn.
            shape = self._queue[0][0].shape
            batch, rest = [], collections.deque()
            while self._queue and len(batch) < self.max_batch:
                item = self._queue.popleft()
                (batch if item[0].shape == shape else rest).append(item)
            self._queue.extendleft(reversed(rest))
            return batch

    def _loop(self) -> None:
        while True:
            batch = self._take_batch()
            if batch is None:
                return
            try:
                y = self._run(np.concatenate([x for x, _ in batch]))
                self.batches += 1
                row = 0
                for x, fut in batch:
                    fut.set_result(y[row:row + len(x)])
                    row += len(x)
            except Exception as exc:  # the callers get the error; the batcher lives on
                for _, fut in batch:
                    fut.set_exception(exc)
