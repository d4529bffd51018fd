"""A settled thesis pile for the tests of deepcontact's kinematics, admission and faces."""

from __future__ import annotations

import numpy as np

from simclient.scene import SceneSpec, settled_world


def sliding_pile():
    """A thesis pile at step 120, with points that let go, stick and slide both ways: its
    bodies, points, the step's solution ((P, 2) N s, the oracle's) and friction (P,)."""
    engine = settled_world(SceneSpec.thesis(), 901, 120)
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    b = points["builtin"]
    exact = engine.oracle(start=(b[:, 0].copy(), b[:, 1].copy())).astype(np.float64)
    return bodies, points, exact, np.full(len(points), 0.5)
