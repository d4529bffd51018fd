"""A vertical stack of twelve boxes on the ground, each a little off the one below.

    python examples/stack.py
    deepcontact bench iterations --world examples/stack.py:build --seeds 901-920 \
        --warm-starts builtin,server:default --out bench/results/stack

build(seed) draws each box's offset (up to 4 cm) and size (0.4-0.6 m half-width) from the
seed; the boxes start 1 mm apart and settle into a column that stands.
"""

import numpy as np

import Box2D

BOXES = 12


def build(seed: int) -> Box2D.b2World:
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-20.0, 0.0), (20.0, 0.0)], friction=0.6)
    top = 0.0
    for _ in range(BOXES):
        half = float(rng.uniform(0.4, 0.6))
        body = world.CreateDynamicBody(position=(float(rng.uniform(-0.04, 0.04)), top + half + 0.001))
        body.CreatePolygonFixture(box=(half, half), density=1.0, friction=0.6)
        top += 2 * half + 0.001
    return world


if __name__ == "__main__":
    from _compare import main

    raise SystemExit(main(build, __doc__))
