"""A chain of 30 links on revolute joints, hung from one end, falling onto a heap of discs and boxes.

    python examples/chain.py
    deepcontact bench iterations --world examples/chain.py:build --seeds 901-920 \
        --warm-starts builtin,server:default --out bench/results/chain

The chain swings down from a static anchor and drapes over 60 bodies (circles and convex
polygons: triangles, boxes and hexagons, several fixtures on the heavy ones) poured into
a bin of edges. build(seed) draws the heap's shapes and places from the seed.
"""

import math

import numpy as np

import Box2D

LINKS = 30
HEAP = 60


def _polygon(sides: int, radius: float, phase: float) -> list[tuple[float, float]]:
    return [(radius * math.cos(phase + 2 * math.pi * k / sides), radius * math.sin(phase + 2 * math.pi * k / sides))
            for k in range(sides)]


def build(seed: int) -> Box2D.b2World:
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    for a, b in (((-8.0, 0.0), (8.0, 0.0)), ((-8.0, 0.0), (-8.0, 6.0)), ((8.0, 0.0), (8.0, 6.0))):
        ground.CreateEdgeFixture(vertices=[a, b], friction=0.5)
    for i in range(HEAP):
        x, y = float(rng.uniform(-7.0, 7.0)), float(0.5 + 0.45 * i)
        body = world.CreateDynamicBody(position=(x, y), angle=float(rng.uniform(0, 2 * math.pi)))
        kind = int(rng.integers(5))  # a disc, a triangle, a box, a hexagon, or a box with a disc on one end
        size = float(rng.uniform(0.25, 0.4))
        if kind == 0:
            body.CreateCircleFixture(radius=size, density=1.0, friction=0.5)
        elif kind == 4:
            body.CreatePolygonFixture(box=(size, 0.5 * size), density=1.0, friction=0.5)
            body.CreateCircleFixture(radius=0.5 * size, pos=(size, 0.0), density=1.0, friction=0.5)
        else:
            sides = (3, 4, 6)[kind - 1]
            body.CreatePolygonFixture(vertices=_polygon(sides, size, float(rng.uniform(0, 1))), density=1.0,
                                      friction=0.5)
    anchor = world.CreateStaticBody(position=(-6.0, 12.0))
    previous = anchor
    for i in range(LINKS):
        link = world.CreateDynamicBody(position=(-6.0 + 0.25 + 0.5 * i, 12.0))
        link.CreatePolygonFixture(box=(0.25, 0.06), density=2.0, friction=0.4)
        world.CreateRevoluteJoint(bodyA=previous, bodyB=link, anchor=(-6.0 + 0.5 * i, 12.0))
        previous = link
    return world


if __name__ == "__main__":
    from _compare import main

    raise SystemExit(main(build, __doc__))
