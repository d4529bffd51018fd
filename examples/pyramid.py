"""Box2D's testbed Pyramid: 20 rows of 1 m boxes (half-width 0.5 m) on a ground edge.

    python examples/pyramid.py                 # builtin against the server's default, seed 901
    deepcontact bench iterations --world examples/pyramid.py:build --seeds 901-920 \
        --warm-starts builtin,server:default --out bench/results/pyramid

build(seed) is the testbed's layout (density 1, friction 0.6) with each box moved by up
to 1 cm and turned by up to 0.5 degrees, drawn from the seed: a stack that stands, where
Box2D's own warm start is at its best.
"""

import numpy as np

import Box2D

ROWS = 20
HALF = 0.5  # m


def build(seed: int) -> Box2D.b2World:
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-40.0, 0.0), (40.0, 0.0)], friction=0.6)
    x = np.array([-7.0, 0.75])
    dx, dy = np.array([0.5625, 1.25]), np.array([1.125, 0.0])
    for i in range(ROWS):
        y = x.copy()
        for _ in range(i, ROWS):
            jitter = rng.uniform(-0.01, 0.01, 2)
            body = world.CreateDynamicBody(position=tuple(map(float, y + jitter)),
                                           angle=float(np.radians(rng.uniform(-0.5, 0.5))))
            body.CreatePolygonFixture(box=(HALF, HALF), density=1.0, friction=0.6)
            y += dy
        x += dx
    return world


if __name__ == "__main__":
    from _compare import main

    raise SystemExit(main(build, __doc__))
