"""Box2D's warm start extrapolated in time along a stream, point by point, where it moves smoothly.

Box2D begins a step's velocity sweeps from each contact point's impulse of the step before (the
request's `builtin`, already scaled by the time steps' ratio). Where the motion is smooth (a
wheel rolling over hills on a sprung joint, a body swinging on a hinge) a point's impulse moves
steadily from step to step, and the line through its last two impulses lands nearer this step's
than the last one does:

    d1      = builtin_k - builtin_{k-1}                     (N s, normal and tangent)
    d2      = d1 - (builtin_{k-1} - builtin_{k-2})
    start_k = builtin_k + d1   where max|d2| < max|d1|, else builtin_k

The test is the line's own record: on the step before, the line through the two impulses before
it would have missed that step's impulse by d2 and the copy by d1, so the line is drawn only where
it would have beaten the copy then. Where impulses jump (a joint reaching its limit, a body
landing) it is not drawn: drawn at every point, it cost more of Box2D's sweeps on ragdolls
(docs/research/2026-12-06-jointed-points-extrapolated.md).

The server answers it at the points a model cannot speak for, those on jointed bodies
(server.joints), where a card asks for it (its face setting extrapolate_jointed). A point missing
from one of the last three steps, or new on one of them (Box2D carried nothing to it: its start
was exactly zero), and any point after a gap of steps keep Box2D's start as it is.

    history = ImpulseHistory()
    start = history.extrapolated(points, step, where)   # (P, 2) float32 N s

A stream that asks about the same step more than once (several models on one state) gets the
same answer each time: the steps before are the last ones with other indices.
"""

from __future__ import annotations

import numpy as np

#: Steps of Box2D's starts a history keeps: this one and the two before it.
KEPT = 3


class ImpulseHistory:
    """A stream's Box2D starts of its last KEPT steps, by contact point key."""

    __slots__ = ("_steps",)

    def __init__(self):
        # (step, keys (Q,) uint64 sorted, Box2D's starts (Q, 2) float32 N s in the keys' order), oldest first.
        self._steps: list[tuple[int, np.ndarray, np.ndarray]] = []

    def extrapolated(self, points: np.ndarray, step: int, where: np.ndarray | None = None) -> np.ndarray:
        """(P, 2) float32 N s: each point's Box2D start (points["builtin"]; points (P,)
        CONTACT_DTYPE) extrapolated as the module docstring says at the points of `where` ((P,)
        bool; None: every point), and as it is elsewhere. Records this step's starts for the
        steps after it."""
        builtin = np.asarray(points["builtin"], np.float32)
        keys = np.asarray(points["key"], np.uint64)
        self._record(keys, builtin, step)
        start = builtin.copy()
        before, older = self._starts(step - 1, keys), self._starts(step - 2, keys)
        if before is None or older is None:
            return start
        (previous, had_previous), (oldest, had_oldest) = before, older
        d1 = builtin - previous
        d2 = d1 - (previous - oldest)
        drawn = had_previous & had_oldest & builtin.any(axis=1) & (np.abs(d2).max(axis=1) < np.abs(d1).max(axis=1))
        if where is not None:
            drawn &= where
        start[drawn] += d1[drawn]
        return start

    def _starts(self, step: int, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(the starts (P, 2) of step `step` at `keys`' points, (P,) bool: the point was there and
        Box2D carried an impulse to it), or None where that step is not kept."""
        for kept_step, known, starts in self._steps:
            if kept_step == step and len(known) and len(keys):
                at = np.searchsorted(known, keys).clip(max=len(known) - 1)
                found = starts[at]
                return found, (known[at] == keys) & found.any(axis=1)
        return None

    def _record(self, keys: np.ndarray, builtin: np.ndarray, step: int) -> None:
        """Keep step `step`'s starts sorted by key, in place of the same step's asked before."""
        order = np.argsort(keys, kind="stable")
        entry = (step, keys[order], builtin[order])
        if self._steps and self._steps[-1][0] == step:
            self._steps[-1] = entry
        else:
            self._steps = [*self._steps[1 - KEPT:], entry]
