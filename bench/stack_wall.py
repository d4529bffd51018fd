"""A wall of ten stacks of boxes: where a warm start that solves a resting stack saves most of
the solver's sweeps, the world `bench walltime` asks whether it pays for its round trip.

    deepcontact bench walltime --world bench/stack_wall.py:build --tolerance 1e-6 --seeds 901-903
    deepcontact bench walltime --world bench/stack_wall.py:deep --tolerance 1e-6 --seeds 901-910

build(seed): stacks of twelve boxes; deep(seed): of twenty (400 contact points while every
column is awake), where each of Box2D's sweeps costs more and its start still runs to its cap.

build(seed) draws each box's half-width (0.4-0.6 m) and sideways offset (up to 4 cm) from the
seed; the columns stand 2 m apart on a ground edge, each box 1 mm above the one below. Stacks are
Box2D's slow case: its relaxation carries a change of load down a column one box a sweep, so at
a tight tolerance its solver runs near its cap. 240 contact points while every column is
awake (within the face route's 300); from about 0.6 s the columns fall asleep one by one
(Box2D's sleeping, on as by default) and their points leave the solve.
"""

import numpy as np

import Box2D

COLUMNS = 10
BOXES = 12
SPACING = 2.0  # m between the columns' centres: wider than two of the largest boxes


def build(seed: int, boxes: int = BOXES) -> Box2D.b2World:
    """Ten columns of `boxes` boxes each, drawn from the seed."""
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-SPACING * COLUMNS, 0.0), (SPACING * COLUMNS, 0.0)], friction=0.6)
    for column in range(COLUMNS):
        x0, top = SPACING * (column - 0.5 * (COLUMNS - 1)), 0.0
        for half, dx in zip(rng.uniform(0.4, 0.6, boxes), rng.uniform(-0.04, 0.04, boxes)):
            body = world.CreateDynamicBody(position=(x0 + float(dx), top + float(half) + 0.001))
            body.CreatePolygonFixture(box=(float(half), float(half)), density=1.0, friction=0.6)
            top += 2.0 * float(half) + 0.001
    return world


def deep(seed: int) -> Box2D.b2World:
    """Ten columns of twenty boxes: the deepest of the stacks tried (12, 16 and 20 boxes, choosing
    seeds 850-852; docs/performance.md, "Wall time")."""
    return build(seed, boxes=20)
