"""Attach deepcontact to a world of your own. Start a server first: deepcontact serve --models models/"""
import sys

import Box2D
from simclient import WarmStartSession

world = Box2D.b2World(gravity=(0, -9.8))
world.CreateStaticBody().CreateEdgeFixture(vertices=[(-20, 0), (20, 0)], friction=0.6)
for i in range(40):
    world.CreateDynamicBody(position=(0.3 * (i % 5) - 0.6, 0.5 + i)).CreateCircleFixture(radius=0.5, density=1, friction=0.5)

with WarmStartSession(world, sys.argv[1] if len(sys.argv) > 1 else "127.0.0.1:50051", model="default") as session:
    for _ in range(250):
        session.step(0.01, 1000, 10)  # in place of world.Step(0.01, 1000, 10)
    print(session.summary())
