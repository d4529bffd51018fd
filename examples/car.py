"""A car on chain-shape terrain: a chassis on two wheel joints with a motor, over hills, past loose boxes.

    python examples/car.py
    deepcontact bench iterations --world examples/car.py:build --seeds 901-920 \
        --warm-starts builtin,server:default --out bench/results/car

The terrain is one static chain of 60 segments whose heights build(seed) draws; ten boxes
and a kinematic platform lifting one more sit on the way. The wheels turn at
8 rad/s under a motor of 40 N m on springy wheel joints (Box2D's testbed Car, smaller).
"""

import numpy as np

import Box2D

SEGMENTS = 60


def build(seed: int) -> Box2D.b2World:
    rng = np.random.default_rng(seed)
    world = Box2D.b2World(gravity=(0.0, -9.8))
    xs = np.linspace(-10.0, 110.0, SEGMENTS + 1)
    heights = np.concatenate([[0.0, 0.0], np.cumsum(rng.uniform(-0.35, 0.35, SEGMENTS - 1))])
    ground = world.CreateStaticBody()
    ground.CreateChainFixture(vertices_chain=[(float(x), float(h)) for x, h in zip(xs, heights)], friction=0.8)
    for k in range(10):
        x = float(4.0 + 3.0 * k + rng.uniform(-0.5, 0.5))
        y = float(np.interp(x, xs, heights)) + 0.6
        box = world.CreateDynamicBody(position=(x, y))
        box.CreatePolygonFixture(box=(0.4, 0.4), density=0.5, friction=0.6)
    lift = float(np.interp(12.0, xs, heights)) + 2.0
    platform = world.CreateKinematicBody(position=(12.0, lift), linearVelocity=(0.0, 0.4))
    platform.CreatePolygonFixture(box=(2.0, 0.2), friction=0.6)
    rider = world.CreateDynamicBody(position=(12.0, lift + 0.61))  # rides the kinematic platform up
    rider.CreatePolygonFixture(box=(0.4, 0.4), density=0.5, friction=0.6)
    chassis = world.CreateDynamicBody(position=(0.0, 1.2))
    chassis.CreatePolygonFixture(vertices=[(-1.5, -0.5), (1.5, -0.5), (1.5, 0.0), (0.0, 0.9), (-1.15, 0.9), (-1.5, 0.2)],
                                 density=1.0, friction=0.6)
    for x in (-1.0, 1.0):
        wheel = world.CreateDynamicBody(position=(x, 0.45))
        wheel.CreateCircleFixture(radius=0.4, density=1.0, friction=0.9)
        world.CreateWheelJoint(bodyA=chassis, bodyB=wheel, anchor=wheel.position, axis=(0.0, 1.0),
                               motorSpeed=-8.0, maxMotorTorque=40.0, enableMotor=True,
                               frequencyHz=4.0, dampingRatio=0.7)
    return world


if __name__ == "__main__":
    from _compare import main

    raise SystemExit(main(build, __doc__))
