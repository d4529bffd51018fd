"""A zoo of scenes: worlds like the ones users build, to train and judge a learned warm start on.

The thesis world is one pile of equal discs in a box. A warm start served to users meets
stacks, pyramids, chains, ragdolls, hills and moving containers, with their own gravity, time
step and materials. Each class here builds such worlds from a seed, so that training data,
model selection and reports can cover them, and a model's card can say which it has seen
(`envelope_of`, the format deepcontact.envelope.Envelope.from_dict reads).

    world, dt = CLASSES["pyramid"](901)
    for _ in range(250):
        world.Step(dt, 1000, 10)

The classes, in CLASSES order:

    discs      60-200 discs of one size range dropped into a static open-top box of edges
    pyramid    Box2D testbed's pyramid: 8-20 rows of equal square boxes on a ground edge
    stack      1-3 columns of 4-15 boxes each on a ground edge
    polygons   40-120 mixed convex bodies (some of two fixtures) poured into a bin of edges
    jointed    a chain or bridge of thin links on revolute joints, sliders on prismatic joints
               and welded pairs, over a heap of mixed bodies in a bin
    ragdolls   3-8 ragdolls (ten parts on limited revolute joints) and a few loose boxes
    terrain    30-100 mixed bodies dropped onto hills of a static chain shape (and edges)
    rotating   30-100 mixed bodies inside a slowly turning kinematic ring of thin boxes

Each class is a function NAME(seed) -> (world, dt): a Box2D.b2World and the seed's time step
(s). Every class first draws the same physics from its seed (`_Physics`): gravity 2-20 m/s^2
pointing down, dt log-uniform in 1/120-1/30 s, density log-uniform in 0.5-10 kg/m^2 (the
world's, or each body's within a factor of 2 of it), friction 0.1-0.9 (the world's, or each
body's) and restitution 0-0.3; then its own layout. Sleeping is Box2D's default (on). A world
holds at most about 250 dynamic bodies, the lowest of them placed just above what they fall
on, so that contacts start within the first hundred steps whatever the draws.

Seeds (simclient.seeds): 1-799 train, 800-849 validate, 850-899 choose, 900-999 report;
10000 and up are never used by the project. The same seed builds the same world bit for bit
(positions, angles, shapes): all randomness comes from numpy.random.default_rng(seed).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

import Box2D

GRAVITY = (2.0, 20.0)  # m/s^2, uniform
DT = (1.0 / 120.0, 1.0 / 30.0)  # s, log-uniform
DENSITY = (0.5, 10.0)  # kg/m^2, log-uniform
FRICTION = (0.1, 0.9)  # uniform
RESTITUTION = (0.0, 0.3)  # uniform
SKIN = 0.01  # m: Box2D's polygon radius (b2_polygonRadius), the skin around polygons and edges
GAP = 2.0 * SKIN  # m: the least room left between bodies placed at the start, and below the lowest

# Mixed bodies (polygons, jointed, terrain, rotating): each body's size is its bounding radius
# about its origin (m) or a little more, drawn around a centre drawn per seed.
MIXED_SIZE = (0.2, 0.6)  # m, the seed's centre
MIXED_SPREAD = 0.3  # sizes within +-30 % of the centre
# Kinds of mixed bodies, drawn equally: about 1 in 6 of two fixtures.
DISC, TRIANGLE, BOX, PENTAGON, HEXAGON, COMPOUND = range(6)


@dataclasses.dataclass(frozen=True)
class _Physics:
    """The physics every class draws first from its seed, and the materials of its bodies.

    per_body: each dynamic body draws its own density (within a factor of 2 around the world's,
    kept in DENSITY) and friction (anywhere in FRICTION); otherwise all share the world's."""

    gravity: float  # m/s^2, magnitude, pointing down
    dt: float  # s
    density: float  # kg/m^2
    friction: float
    restitution: float
    per_body: bool

    @classmethod
    def draw(cls, rng: np.random.Generator) -> "_Physics":
        def log_uniform(lo: float, hi: float) -> float:
            return float(np.clip(math.exp(rng.uniform(math.log(lo), math.log(hi))), lo, hi))

        return cls(gravity=float(rng.uniform(*GRAVITY)), dt=log_uniform(*DT), density=log_uniform(*DENSITY),
                   friction=float(rng.uniform(*FRICTION)), restitution=float(rng.uniform(*RESTITUTION)),
                   per_body=bool(rng.random() < 0.5))

    @property
    def static(self) -> dict:
        """Fixture keywords of static and kinematic bodies (their density is not used)."""
        return {"friction": self.friction, "restitution": self.restitution}

    def body(self, rng: np.random.Generator) -> dict:
        """Fixture keywords of one dynamic body (all its fixtures): drawn where per_body."""
        if not self.per_body:
            return {"density": self.density, "friction": self.friction, "restitution": self.restitution}
        density = float(np.clip(self.density * 2.0 ** rng.uniform(-0.5, 0.5), *DENSITY))
        return {"density": density, "friction": float(rng.uniform(*FRICTION)), "restitution": self.restitution}


def _start(seed: int) -> tuple[np.random.Generator, _Physics, Box2D.b2World]:
    """The seed's generator, its physics (the first draws of every class) and the empty world."""
    rng = np.random.default_rng(seed)
    physics = _Physics.draw(rng)
    return rng, physics, Box2D.b2World(gravity=(0.0, -physics.gravity))


# -- placement ----------------------------------------------------------------------------------

def _place(rng: np.random.Generator, reach: np.ndarray, x_range: tuple[float, float],
           floor: Callable[[np.ndarray, np.ndarray], np.ndarray],
           inside: Callable[[np.ndarray, float], np.ndarray] | None = None) -> np.ndarray:
    """Centres (N, 2) m for bodies of bounding radius `reach` (N,), apart, in creation order.

    A grid of square cells, each as wide as the largest body plus GAP, fills the columns of
    x_range (GAP from its ends) from the bottom up, lowest rows first; floor(x_lo, x_hi) gives
    the ground's highest point under each column (arrays), and a column's first cell sits GAP
    above it. inside(centres, half), where given, keeps only the cells whose square of half-side
    `half` lies in a container. Each body moves at random within its cell, keeping GAP from the
    others. Setup code, run once per world."""
    n = len(reach)
    cell = 2.0 * float(reach.max()) + GAP
    room = x_range[1] - x_range[0] - 2.0 * GAP  # m: GAP from either end
    columns = int(room // cell)
    if columns < 1:
        raise ValueError(f"bodies of reach {reach.max():.3g} m do not fit in {x_range}")
    x = 0.5 * (x_range[0] + x_range[1]) + cell * (np.arange(columns) - 0.5 * (columns - 1))
    base = floor(x - 0.5 * cell, x + 0.5 * cell) + 0.5 * cell + GAP
    rows = -(-n // columns)
    while True:  # as many rows as hold n cells inside the container (no draws here)
        centres = np.stack(np.broadcast_arrays(x[None, :], base[None, :] + cell * np.arange(rows)[:, None]), -1)
        centres = centres.reshape(-1, 2)
        if inside is not None:
            centres = centres[inside(centres, 0.5 * cell)]
        if len(centres) >= n:
            break
        if rows > 10 * n:
            raise ValueError(f"no room for {n} bodies of reach up to {reach.max():.3g} m")
        rows += max(1, rows // 4)
    slack = 0.5 * cell - reach - 0.5 * GAP  # (N,) m, each body's room to move within its cell
    return centres[:n] + rng.uniform(-1.0, 1.0, (n, 2)) * slack[:, None]


def _flat(height: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """A floor for _place: level ground at `height` (m)."""
    return lambda lo, hi: np.full(len(lo), height)


def _bin(world: Box2D.b2World, physics: _Physics, width: float, height: float) -> Box2D.b2Body:
    """A static open-top box of three edges on one body: its floor at y = 0 from x = 0 to
    `width`, its walls `height` high (m)."""
    ground = world.CreateStaticBody()
    for a, b in (((0.0, 0.0), (width, 0.0)), ((0.0, 0.0), (0.0, height)), ((width, 0.0), (width, height))):
        ground.CreateEdgeFixture(vertices=[a, b], **physics.static)
    return ground


def _bin_width(reach: np.ndarray, lo: float, hi: float, rng: np.random.Generator) -> float:
    """A bin width (m) drawn in [lo, hi], widened (up to hi) so that the bodies' grid stands at
    most about three widths tall."""
    cell = 2.0 * float(reach.max()) + GAP
    return float(min(hi, max(rng.uniform(lo, hi), cell * math.sqrt(len(reach) / 3.0) + cell)))


# -- mixed bodies -------------------------------------------------------------------------------

def _mixed(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Kinds (N,) and sizes (N,) m of n mixed bodies: the seed's centre size, each within the spread."""
    centre = float(rng.uniform(*MIXED_SIZE))
    kinds = rng.integers(0, 6, n)
    sizes = centre * rng.uniform(1.0 - MIXED_SPREAD, 1.0 + MIXED_SPREAD, n)
    return kinds, sizes


def _add_mixed(world: Box2D.b2World, physics: _Physics, rng: np.random.Generator, kind: int, size: float,
               position: np.ndarray) -> Box2D.b2Body:
    """One mixed body of bounding radius at most `size` (m) about its origin, turned at random.

    DISC a disc; TRIANGLE, PENTAGON, HEXAGON polygons whose corners lie 0.8-1 of size out; BOX a
    rectangle of aspect 0.47-2.1; COMPOUND two fixtures: a box with a disc at one end, or an L
    of two boxes."""
    body = world.CreateDynamicBody(position=(float(position[0]), float(position[1])),
                                   angle=float(rng.uniform(0.0, 2.0 * math.pi)))
    material = physics.body(rng)
    if kind == DISC:
        body.CreateCircleFixture(radius=size, **material)
    elif kind == BOX:
        turn = float(rng.uniform(math.radians(25.0), math.radians(65.0)))
        body.CreatePolygonFixture(box=(size * math.cos(turn), size * math.sin(turn)), **material)
    elif kind == COMPOUND:
        if rng.random() < 0.5:  # a hammer: a box with a disc at one end
            body.CreatePolygonFixture(box=(0.55 * size, 0.3 * size), **material)
            body.CreateCircleFixture(radius=0.4 * size, pos=(0.55 * size, 0.0), **material)
        else:  # an L of two boxes
            body.CreatePolygonFixture(box=(0.6 * size, 0.15 * size, (0.0, -0.45 * size), 0.0), **material)
            body.CreatePolygonFixture(box=(0.15 * size, 0.4 * size, (-0.45 * size, 0.1 * size), 0.0), **material)
    else:
        sides = {TRIANGLE: 3, PENTAGON: 5, HEXAGON: 6}[kind]
        angles = float(rng.uniform(0.0, 2.0 * math.pi)) + 2.0 * np.pi * np.arange(sides) / sides
        radii = size * rng.uniform(0.8, 1.0, sides)
        body.CreatePolygonFixture(vertices=[(float(p), float(q)) for p, q in
                                            zip(radii * np.cos(angles), radii * np.sin(angles))], **material)
    return body


def _heap(world: Box2D.b2World, physics: _Physics, rng: np.random.Generator, kinds: np.ndarray, sizes: np.ndarray,
          centres: np.ndarray) -> None:
    """The mixed bodies at their centres, in order."""
    for kind, size, centre in zip(kinds, sizes, centres):
        _add_mixed(world, physics, rng, int(kind), float(size), centre)


# -- the classes --------------------------------------------------------------------------------

def discs(seed: int) -> tuple[Box2D.b2World, float]:
    """60-200 discs (radii within up to +-30 % of a centre of 0.2-0.8 m) dropped into a static
    open-top box 8-25 m wide, apart on a jittered grid from its floor up; walls as high as the grid."""
    rng, physics, world = _start(seed)
    n = int(rng.integers(60, 201))
    centre, spread = float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.0, 0.3))
    radii = centre * rng.uniform(1.0 - spread, 1.0 + spread, n)
    width = _bin_width(radii, 8.0, 25.0, rng)
    centres = _place(rng, radii, (0.0, width), _flat(0.0))
    _bin(world, physics, width, float((centres[:, 1] + radii).max()) + 1.0)
    for (x, y), r in zip(centres, radii):
        body = world.CreateDynamicBody(position=(float(x), float(y)))
        body.CreateCircleFixture(radius=float(r), **physics.body(rng))
    return world, physics.dt


def pyramid(seed: int) -> tuple[Box2D.b2World, float]:
    """Box2D testbed's pyramid: 8-20 rows of equal square boxes (half-size 0.2-0.7 m) on a ground
    edge, each row a box shorter and offset by half a box, every box moved by up to 2 % of its
    size and turned by up to half a degree."""
    rng, physics, world = _start(seed)
    rows, half = int(rng.integers(8, 21)), float(rng.uniform(0.2, 0.7))
    step_x, step_y = 2.25 * half, 2.12 * half + GAP  # m: the testbed's spacing; rows closer, room for the jitter
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-step_x * rows - 20.0, 0.0), (step_x * rows + 20.0, 0.0)], **physics.static)
    for i in range(rows):
        for j in range(rows - i):
            jitter = rng.uniform(-0.04 * half, 0.04 * half, 2)  # +-2 % of the size, 2 * half
            x = step_x * (j + 0.5 * i - 0.5 * (rows - 1)) + jitter[0]
            y = half + GAP + 0.05 * half + step_y * i + jitter[1]
            body = world.CreateDynamicBody(position=(float(x), float(y)),
                                           angle=float(np.radians(rng.uniform(-0.5, 0.5))))
            body.CreatePolygonFixture(box=(half, half), **physics.body(rng))
    return world, physics.dt


def stack(seed: int) -> tuple[Box2D.b2World, float]:
    """1-3 columns of 4-15 boxes each (half-sizes 0.2-0.8 m; on half the seeds each side varies
    by up to +-20 % per box) on a ground edge, the columns 0.5-3 m apart, each box moved sideways
    by up to 5 % of its half-width and starting GAP above the one below."""
    rng, physics, world = _start(seed)
    columns, half = int(rng.integers(1, 4)), float(rng.uniform(0.2, 0.8))
    vary = 0.2 if rng.random() < 0.5 else 0.0
    heights = rng.integers(4, 16, columns)
    spacing = 2.0 * 1.2 * half + float(rng.uniform(0.5, 3.0))  # m between the columns' centres
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-spacing * columns - 20.0, 0.0), (spacing * columns + 20.0, 0.0)],
                             **physics.static)
    for c in range(columns):
        x0, top = spacing * (c - 0.5 * (columns - 1)), 0.0
        for _ in range(int(heights[c])):
            hw, hh = (float(h) for h in half * rng.uniform(1.0 - vary, 1.0 + vary, 2))
            body = world.CreateDynamicBody(position=(x0 + float(rng.uniform(-0.05, 0.05)) * hw, top + GAP + hh))
            body.CreatePolygonFixture(box=(hw, hh), **physics.body(rng))
            top += GAP + 2.0 * hh
    return world, physics.dt


def polygons(seed: int) -> tuple[Box2D.b2World, float]:
    """40-120 mixed bodies (discs, triangles, boxes, pentagons, hexagons, and about 1 in 6 of two
    fixtures) poured into a bin of edges 6-20 m wide, from its floor up."""
    rng, physics, world = _start(seed)
    kinds, sizes = _mixed(rng, int(rng.integers(40, 121)))
    width = _bin_width(sizes, 6.0, 20.0, rng)
    centres = _place(rng, sizes, (0.0, width), _flat(0.0))
    _bin(world, physics, width, float((centres[:, 1] + sizes).max()) + 1.0)
    _heap(world, physics, rng, kinds, sizes, centres)
    return world, physics.dt


def jointed(seed: int) -> tuple[Box2D.b2World, float]:
    """A heap of 20-60 mixed bodies in a bin 8-16 m wide; just over it a bridge across the bin or
    a chain hung from one end, of 15-40 thin links on revolute joints (about a quarter with a
    motor at rest, that is joint friction, a quarter with angle limits); above that a row of 1-3
    boxes on prismatic joints that slide down onto the heap (half of them driven) and 1-2 pairs
    of a box and a disc welded together."""
    rng, physics, world = _start(seed)
    kinds, sizes = _mixed(rng, int(rng.integers(20, 61)))
    width = float(rng.uniform(8.0, 16.0))
    centres = _place(rng, sizes, (0.0, width), _flat(0.0))
    level = float((centres[:, 1] + sizes).max()) + 0.3  # m, the links' height: 0.3 m over the heap
    ground = _bin(world, physics, width, level)
    _heap(world, physics, rng, kinds, sizes, centres)

    links, bridge = int(rng.integers(15, 41)), bool(rng.random() < 0.5)
    span = width - 0.2 if bridge else float(rng.uniform(0.6, 0.9)) * width  # m
    length = span / links  # m, a link's
    thick = min(0.1, 0.2 * length)  # m, half a link's thickness
    x0 = 0.1 if bridge else float(rng.uniform(0.1, width - span - 0.1))  # m, the first joint's
    previous = ground if bridge else world.CreateStaticBody(position=(x0, level))
    for i in range(links):
        link = world.CreateDynamicBody(position=(x0 + length * (i + 0.5), level))
        link.CreatePolygonFixture(box=(0.5 * length, thick), **physics.body(rng))
        role, extra = rng.random(), {}
        if role < 0.25:  # a motor at rest: joint friction
            extra = {"enableMotor": True, "motorSpeed": 0.0,
                     "maxMotorTorque": float(rng.uniform(0.1, 1.0)) * link.mass * physics.gravity * length}
        elif role < 0.5:
            bend = math.radians(float(rng.uniform(15.0, 60.0)))
            extra = {"enableLimit": True, "lowerAngle": -bend, "upperAngle": bend}
        world.CreateRevoluteJoint(bodyA=previous, bodyB=link, anchor=(x0 + length * i, level), **extra)
        previous = link
    if bridge:
        world.CreateRevoluteJoint(bodyA=previous, bodyB=ground, anchor=(x0 + span, level))

    # The row above the links: sliders first, then welded pairs, each in its slot.
    sliders, pairs = int(rng.integers(1, 4)), int(rng.integers(1, 3))
    half = float(rng.uniform(0.2, 0.4))  # m, the row's half-size
    y = level + thick + GAP + 2.0 * half
    for k, x in enumerate((np.arange(sliders + pairs) + 0.5) * (width / (sliders + pairs))):
        x = float(x)
        if k < sliders:
            body = world.CreateDynamicBody(position=(x, y))
            body.CreatePolygonFixture(box=(half, half), **physics.body(rng))
            tilt = math.radians(float(rng.uniform(-20.0, 20.0)))  # the axis's, from the vertical
            drive = {"enableMotor": True, "motorSpeed": float(rng.uniform(-1.0, 0.0)),
                     "maxMotorForce": float(rng.uniform(0.2, 1.0)) * body.mass * physics.gravity
                     } if rng.random() < 0.5 else {}
            world.CreatePrismaticJoint(bodyA=ground, bodyB=body, anchor=(x, y), axis=(math.sin(tilt), math.cos(tilt)),
                                       enableLimit=True, lowerTranslation=-y, upperTranslation=0.5, **drive)
        else:  # a box and a disc beside it, welded where they meet
            box = world.CreateDynamicBody(position=(x - 0.5 * half, y))
            box.CreatePolygonFixture(box=(0.5 * half, 0.5 * half), **physics.body(rng))
            disc = world.CreateDynamicBody(position=(x + 0.5 * half + GAP, y))
            disc.CreateCircleFixture(radius=0.5 * half, **physics.body(rng))
            world.CreateWeldJoint(bodyA=box, bodyB=disc, anchor=(x + 0.5 * GAP, y))
    return world, physics.dt


# A ragdoll standing, at scale 1 (m): its parts (name, centre, a box's half-sizes or a disc's
# radius) and its joints (part A, part B, anchor, lower and upper angle in degrees). The right
# side mirrors the left (_ragdoll_layout).
_PARTS = (("torso", (0.0, 0.0), (0.18, 0.3)), ("head", (0.0, 0.43), 0.12),
          ("upper_arm", (-0.26, 0.13), (0.06, 0.15)), ("lower_arm", (-0.26, -0.175), (0.05, 0.14)),
          ("upper_leg", (-0.09, -0.51), (0.07, 0.2)), ("lower_leg", (-0.09, -0.92), (0.06, 0.2)))
_JOINTS = (("torso", "head", (0.0, 0.3), -40.0, 40.0),
           ("torso", "upper_arm", (-0.26, 0.28), -150.0, 90.0),
           ("upper_arm", "lower_arm", (-0.26, -0.025), -130.0, 0.0),
           ("torso", "upper_leg", (-0.09, -0.3), -100.0, 30.0),
           ("upper_leg", "lower_leg", (-0.09, -0.715), 0.0, 130.0))


def _ragdoll_layout() -> tuple[list, list]:
    """_PARTS and _JOINTS with the right side added (names ending in _r, x and angles mirrored);
    centres and anchors as arrays."""
    parts, joints = [], []
    for name, centre, size in _PARTS:
        parts.append((name, np.array(centre), size))
        if centre[0] != 0.0:
            parts.append((name + "_r", np.array((-centre[0], centre[1])), size))
    for a, b, anchor, lo, hi in _JOINTS:
        joints.append((a, b, np.array(anchor), lo, hi))
        if anchor[0] != 0.0:
            joints.append((a if a == "torso" else a + "_r", b + "_r", np.array((-anchor[0], anchor[1])), -hi, -lo))
    return parts, joints


def ragdolls(seed: int) -> tuple[Box2D.b2World, float]:
    """3-8 ragdolls (a box torso, a disc head, box upper and lower arms and legs: ten bodies on
    nine revolute joints with angle limits, about a third with a little joint friction; one
    material a ragdoll), each 1.2-2.2 m tall and turned at random, stacked loosely one over the
    other above 2-6 loose boxes on a ground edge, so that they fall onto the boxes and each other."""
    rng, physics, world = _start(seed)
    ground = world.CreateStaticBody()
    ground.CreateEdgeFixture(vertices=[(-40.0, 0.0), (40.0, 0.0)], **physics.static)
    spread = float(rng.uniform(1.0, 4.0))  # m: the ragdolls' centres within +-spread of x = 0
    boxes = int(rng.integers(2, 7))
    halves = rng.uniform(0.2, 0.6, boxes)  # m
    pitch = max((2.0 * spread + 2.0) / boxes, 2.0 * float(halves.max()) + 0.2)  # m between the boxes
    for x, h in zip((np.arange(boxes) - 0.5 * (boxes - 1)) * pitch, halves):
        box = world.CreateDynamicBody(position=(float(x), float(h) + GAP))
        box.CreatePolygonFixture(box=(float(h), float(h)), **physics.body(rng))
    floor = 2.0 * float(halves.max()) + GAP  # m: the top of the tallest box

    parts, joints = _ragdoll_layout()
    extents = np.array([size if np.isscalar(size) else math.hypot(*size) for _, _, size in parts])  # m, at scale 1
    for _ in range(int(rng.integers(3, 9))):
        scale, turn = float(rng.uniform(0.7, 1.3)), float(rng.uniform(0.0, 2.0 * math.pi))
        rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        centres = scale * np.array([centre for _, centre, _ in parts]) @ rotation.T
        offset = np.array([float(rng.uniform(-spread, spread)),
                           floor + GAP - float((centres[:, 1] - scale * extents).min())])
        material = physics.body(rng)
        bodies = {}
        for (name, _, size), centre in zip(parts, centres + offset):
            body = world.CreateDynamicBody(position=(float(centre[0]), float(centre[1])), angle=turn)
            if np.isscalar(size):
                body.CreateCircleFixture(radius=scale * size, **material)
            else:
                body.CreatePolygonFixture(box=(scale * size[0], scale * size[1]), **material)
            bodies[name] = body
        for a, b, anchor, lo, hi in joints:
            friction = {"enableMotor": True, "motorSpeed": 0.0,
                        "maxMotorTorque": float(rng.uniform(0.01, 0.1)) * bodies[b].mass * physics.gravity * scale
                        } if rng.random() < 0.3 else {}
            world.CreateRevoluteJoint(bodyA=bodies[a], bodyB=bodies[b],
                                      anchor=tuple(float(v) for v in scale * rotation @ anchor + offset),
                                      enableLimit=True, lowerAngle=math.radians(lo), upperAngle=math.radians(hi),
                                      **friction)
        floor = float((centres[:, 1] + scale * extents).max() + offset[1])
    return world, physics.dt


def terrain(seed: int) -> tuple[Box2D.b2World, float]:
    """30-100 mixed bodies dropped onto hills: a profile of 40-80 segments, 0.5-1.5 m each,
    sloping at most 10-30 degrees (a sum of three waves), closed by two walls higher than the
    bodies. A static chain shape holds it; on half the seeds the outer 1-6 segments of each end
    are single edges instead."""
    rng, physics, world = _start(seed)
    segments, dx = int(rng.integers(40, 81)), float(rng.uniform(0.5, 1.5))  # -, m
    steepest = math.tan(math.radians(float(rng.uniform(10.0, 30.0))))
    xs = dx * (np.arange(segments + 1) - 0.5 * segments)  # m, the profile's corners
    mid = 0.5 * (xs[1:] + xs[:-1])
    waves = rng.uniform(0.02, 0.12, 3) / dx  # 1/m, three waves of 8-50 segments
    slope = (rng.uniform(0.5, 1.0, 3)[:, None]
             * np.cos(2.0 * np.pi * waves[:, None] * mid + rng.uniform(0.0, 2.0 * np.pi, 3)[:, None])).sum(0)
    slope *= steepest / np.abs(slope).max()
    heights = np.concatenate([[0.0], np.cumsum(slope * dx)])  # m

    kinds, sizes = _mixed(rng, int(rng.integers(30, 101)))

    def floor(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        samples = np.linspace(lo, hi, 33)  # (33, columns); between samples the profile rises less than the margin
        return np.interp(samples, xs, heights).max(0) + steepest * (hi - lo) / 32.0

    centres = _place(rng, sizes, (float(xs[0]), float(xs[-1])), floor)
    top = float((centres[:, 1] + sizes).max()) + 1.0  # m, the walls'
    profile = np.concatenate([[[xs[0], top]], np.stack([xs, heights], 1), [[xs[-1], top]]])
    left, right = (int(rng.integers(1, 7)), int(rng.integers(1, 7))) if rng.random() < 0.5 else (0, 0)
    ground = world.CreateStaticBody()
    end = len(profile) - 1 - right  # the chain's last corner
    ground.CreateChainFixture(vertices_chain=[(float(x), float(y)) for x, y in profile[left:end + 1]],
                              **physics.static)
    for k in list(range(left)) + list(range(end, len(profile) - 1)):
        a, b = profile[k], profile[k + 1]
        ground.CreateEdgeFixture(vertices=[(float(a[0]), float(a[1])), (float(b[0]), float(b[1]))], **physics.static)
    _heap(world, physics, rng, kinds, sizes, centres)
    return world, physics.dt


def rotating(seed: int) -> tuple[Box2D.b2World, float]:
    """30-100 mixed bodies inside a closed container turning at 0.2-1.5 rad/s either way: a
    kinematic body whose fixtures are 4 thin boxes (a square) or 5-10 (a polygon ring), a side
    flat at the bottom at the start, with the bodies on its floor filling about a third of it."""
    rng, physics, world = _start(seed)
    kinds, sizes = _mixed(rng, int(rng.integers(30, 101)))
    sides = 4 if rng.random() < 0.5 else int(rng.integers(5, 11))
    spin = float(rng.uniform(0.2, 1.5)) * (1.0 if rng.random() < 0.5 else -1.0)  # rad/s
    cell = 2.0 * float(sizes.max()) + GAP
    # m, from the centre to a wall's inside: the container three times the bodies' cells in area
    apothem = math.sqrt(3.0 * len(sizes) * cell**2 / (sides * math.tan(math.pi / sides))) + cell
    thick = 0.1 + 0.02 * apothem  # m, half a wall's thickness
    normals = -0.5 * math.pi + 2.0 * math.pi * np.arange(sides) / sides  # rad, outward, the first down
    container = world.CreateKinematicBody(position=(0.0, 0.0), angularVelocity=spin)
    half_length = (apothem + 2.0 * thick) * math.tan(math.pi / sides)  # m: the outer side's half, corners closed
    for a in normals:
        centre = ((apothem + thick) * math.cos(a), (apothem + thick) * math.sin(a))
        container.CreatePolygonFixture(box=(half_length, thick, centre, float(a) + 0.5 * math.pi), **physics.static)
    outward = np.stack([np.cos(normals), np.sin(normals)], 1)  # (sides, 2)

    def inside(centres: np.ndarray, half: float) -> np.ndarray:
        return (centres @ outward.T + half * np.abs(outward).sum(1) <= apothem - GAP).all(1)

    centres = _place(rng, sizes, (-apothem, apothem), _flat(-apothem), inside)
    _heap(world, physics, rng, kinds, sizes, centres)
    return world, physics.dt


CLASSES: dict[str, Callable[[int], tuple[Box2D.b2World, float]]] = {
    "discs": discs, "pyramid": pyramid, "stack": stack, "polygons": polygons,
    "jointed": jointed, "ragdolls": ragdolls, "terrain": terrain, "rotating": rotating,
}

# Each class's dynamic bodies' bounding radius about their origin (m), generous: the draws'
# extremes, Box2D's polygon skin (0.01 m) and a margin.
_MIXED_RADIUS = [0.1, 0.85]  # sizes 0.14-0.78 m; a triangle's corners at least 0.8 of its size out
_RADIUS = {
    "discs": [0.1, 1.1],  # radii 0.14-1.04 m
    "pyramid": [0.25, 1.05],  # half-sizes 0.2-0.7 m: half-diagonals 0.28-0.99 m
    "stack": [0.2, 1.4],  # sides' halves 0.16-0.96 m: half-diagonals 0.23-1.36 m
    "polygons": _MIXED_RADIUS,
    "jointed": [0.05, 1.0],  # links 0.12-1.05 m long; the heap's; the row's 0.1-0.57 m
    "ragdolls": [0.07, 0.9],  # heads from 0.08 m, torsos up to 0.46 m, loose boxes up to 0.86 m
    "terrain": _MIXED_RADIUS,
    "rotating": _MIXED_RADIUS,
}


def source(name: str) -> str:
    """The class as a --world source ("simclient.zoo:NAME", simclient.worlds); ValueError for no class."""
    if name not in CLASSES:
        raise ValueError(f"no zoo class {name!r}; the zoo has {', '.join(CLASSES)}")
    return f"simclient.zoo:{name}"


def envelope_of(name: str) -> dict:
    """What the worlds of class `name` can hold, as deepcontact.envelope.Envelope.from_dict reads
    it: shapes, the dynamic bodies' bounding radius (m), density (kg/m^2), friction, gravity
    (m/s^2), dt (s), and whether they hold joints and kinematic bodies. KeyError for no class."""
    if name not in CLASSES:
        raise KeyError(f"no zoo class {name!r}; the zoo has {', '.join(CLASSES)}")
    shapes = {"discs": ["disc"], "pyramid": ["other"], "stack": ["other"]}.get(name, ["disc", "other"])
    return {"shapes": shapes, "radius": list(_RADIUS[name]), "density": list(DENSITY), "friction": list(FRICTION),
            "gravity": list(GRAVITY), "dt": list(DT), "joints": name in ("jointed", "ragdolls"),
            "kinematic": name == "rotating"}
