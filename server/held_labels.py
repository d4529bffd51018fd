"""A stream's classifier labels, held by contact point for the steps whose own do not fit.

On a large step the face route's classifier is a third to a half of its cost (on Box2D's
Pyramid, 700 points: features 0.6 ms and inference 2.7 ms of about 7 ms), and where the whole
route would not end by the request's deadline the step gets the fallback's answer, on a user's
world mostly Box2D's own start. A pile's points persist from step to step: the labels the
classifier gave them a step or two before, solved on this step's own equations, are nearer this
step's than Box2D's start is. So a stream keeps, by point key, the last labels its classifier
gave; a step that the route would not end in time with its classifier, but would without it,
and whose every point has labels held from the last MAX_AGE steps, is solved on those (with the
card's held_from_builtin, a point with none held, new on the step, is read from Box2D's start
instead, and every such step is solved on labels). The classifier then labels that step after
its reply has gone, on the spare core, for the steps after it:

    held = memory.setdefault(("held", name), HeldLabels())
    labels = held.lookup(points, step)          # (P, 2) or None: a point new, or labels too old
    labels = held.lookup(points, step, fill)    # (P, 2): `fill`'s where none are held
    ...                                         # the step answered, on them or otherwise
    held.label_later(executor, classify, points, step)   # classify() -> (P, 2), run there

Only the stream's own thread calls these, one step at a time; the classifier's run in the
background hands its answer over through a Future that the next lookup reads once it is done
(never waited on: a step does not wait for an earlier step's labels).
"""

from __future__ import annotations

import concurrent.futures
import logging

import numpy as np

log = logging.getLogger("deepcontact.server")

#: Labels given this many steps before a step or fewer are held for it: a pile's points change
#: label as it settles, and labels older than this speak less for the step than Box2D's start.
MAX_AGE = 3


class HeldLabels:
    """The last labels a stream's classifier gave, by contact point key (module docstring)."""

    __slots__ = ("_keys", "_labels", "_step", "_pending")

    def __init__(self):
        self._keys, self._labels, self._step = np.empty(0, np.uint64), np.empty((0, 2), np.float32), None
        self._pending: tuple[concurrent.futures.Future, np.ndarray, int] | None = None

    def keep(self, points: np.ndarray, step: int, labels: np.ndarray) -> None:
        """Hold the classifier's answer `labels` (P, 2) for step `step`'s points (P,)
        CONTACT_DTYPE, in place of what was held."""
        keys = np.asarray(points["key"], np.uint64)
        order = np.argsort(keys, kind="stable")
        self._keys, self._labels, self._step = keys[order], np.asarray(labels, np.float32)[order], step

    def lookup(self, points: np.ndarray, step: int, fill: np.ndarray | None = None) -> np.ndarray | None:
        """The held labels (P, 2) of step `step`'s points (P,) CONTACT_DTYPE, or None where one
        of its points has none, or what is held is older than MAX_AGE steps (or not earlier).
        fill: (P, 2) labels for the points with none held (all of them where what is held is too
        old), so that the answer is never None; None: none."""
        self._collect()
        if self._step is None or not 0 < step - self._step <= MAX_AGE or len(self._keys) == 0:
            return None if fill is None else np.asarray(fill, np.float32)
        keys = np.asarray(points["key"], np.uint64)
        at = np.minimum(np.searchsorted(self._keys, keys), len(self._keys) - 1)
        found = self._keys[at] == keys
        if found.all():
            return self._labels[at]
        if fill is None:
            return None
        return np.where(found[:, None], self._labels[at], np.asarray(fill, np.float32))

    def label_later(self, executor: concurrent.futures.Executor, classify, points: np.ndarray, step: int) -> bool:
        """Run classify() -> (P, 2) labels of step `step`'s points (P,) on `executor`, to be
        held once it is done; not where an earlier step's run is still going (False then)."""
        if self._pending is not None and not self._pending[0].done():
            return False
        self._collect()
        self._pending = (executor.submit(classify), np.array(points["key"], np.uint64), step)
        return True

    def _collect(self) -> None:
        """Hold a finished background run's labels (newer than those held); drop a failed one."""
        if self._pending is None or not self._pending[0].done():
            return
        future, keys, step = self._pending
        self._pending = None
        try:
            labels = future.result()
        except Exception:  # a step's labels lost: the steps after it are answered as without them
            log.exception("labelling a step in the background failed")
            return
        if self._step is None or step > self._step:
            order = np.argsort(keys, kind="stable")
            self._keys, self._labels, self._step = keys[order], np.asarray(labels, np.float32)[order], step
