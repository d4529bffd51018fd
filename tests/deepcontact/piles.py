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


def pyramid_of_boxes(rows: int = 12, steps: int = 20):
    """Box2D's testbed Pyramid (rows of 0.5 m boxes, each row half a box in, on a ground edge)
    settled for `steps` steps of 0.01 s: a pile held at about twice the points its bodies have
    freedoms, two points to each face on a face. Its bodies, points, the step's solution ((P, 2)
    N s, the oracle's) and friction (P,)."""
    import Box2D

    from simclient.engine import Engine, SolverConfig

    world = Box2D.b2World(gravity=(0.0, -9.8))
    world.CreateStaticBody().CreateEdgeFixture(vertices=[(-20.0, 0.0), (20.0, 0.0)], friction=0.6)
    for row in range(rows):
        for k in range(rows - row):
            body = world.CreateDynamicBody(position=(-0.5 * (rows - row - 1) + k, 0.5 + row))
            body.CreatePolygonFixture(box=(0.5, 0.5), density=1.0, friction=0.6)
    engine = Engine(world, SolverConfig())
    for _ in range(steps):
        engine.step()
    engine.collide()
    bodies, points = engine.bodies(), engine.contacts()
    exact = engine.oracle(threshold=1e-9, max_iterations=100000).astype(np.float64)
    return bodies, points, exact, points["friction"].astype(np.float64)

