"""Scene definitions: the thesis world and the family it belongs to.

Data generation, the simulation client and every benchmark build their worlds
here, so the same (spec, seed) always gives the same world, bit for bit.

The thesis world (§8.1): a static 15 x 15 m box open at the top (bottom and two
sides), 100 dynamic circles of radius 0.5 m, density 1, friction 0.5,
restitution 0, placed at random without overlap; gravity 9.8 m/s^2, dt 0.01 s,
250 steps, at most 1000 velocity iterations, stopping threshold 1e-4 N s,
continuous collision and sleeping off.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from deepcontact.kinematics import Physics
from simclient.engine import Box2D, Engine, SolverConfig

MAX_PLACEMENT_TRIES = 200_000
MAX_RANDOM_COVER = 0.5
"""Random placement without overlap stalls well before the packing limit: bodies
are placed at random in a region they cover at most this share of."""
MAX_PILE_COVER = 0.8
"""Discs settle no denser than about 0.82 of the area they fill (random close
packing in 2-D): a world whose bodies would cover more of the box cannot fit."""


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """Parameters of one world in the scene family (SI units).

    box_size: (width, height) of the static box, lower-left corner at (0, 0).
    radius: (min, max) circle radius; boxes (polygons) get the same area.
    polygons: share of bodies that are boxes instead of circles, in [0, 1].
    friction: (min, max), drawn per body.
    """

    name: str = "thesis"
    bodies: int = 100
    box_size: tuple[float, float] = (15.0, 15.0)
    radius: tuple[float, float] = (0.5, 0.5)
    polygons: float = 0.0
    friction: tuple[float, float] = (0.5, 0.5)
    density: float = 1.0
    restitution: float = 0.0
    gravity: float = 9.8
    steps: int = 250
    solver: SolverConfig = SolverConfig()

    @classmethod
    def thesis(cls) -> "SceneSpec":
        return cls()

    @property
    def domain(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((x_min, y_min), (x_max, y_max)) of the static box (m)."""
        return (0.0, 0.0), (float(self.box_size[0]), float(self.box_size[1]))

    def validate(self) -> None:
        """Raise ValueError for parameters no world can be built from."""
        w, h = self.box_size
        rmin, rmax = self.radius
        fmin, fmax = self.friction
        if self.bodies < 0:
            raise ValueError(f"bodies must be >= 0, got {self.bodies}")
        if not (w > 0 and h > 0):
            raise ValueError(f"box size must be positive, got {self.box_size}")
        if not (0 < rmin <= rmax):
            raise ValueError(f"radius range must satisfy 0 < min <= max, got {self.radius}")
        if not (0.0 <= self.polygons <= 1.0):
            raise ValueError(f"polygons must be a fraction in [0, 1], got {self.polygons}")
        if not (0.0 <= fmin <= fmax):
            raise ValueError(f"friction range must satisfy 0 <= min <= max, got {self.friction}")
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        if 2 * rmax >= min(w, h):
            raise ValueError(f"bodies of radius {rmax} do not fit in a {w} x {h} box")
        cover = self.bodies * math.pi * rmax**2 / (w * h)
        if cover > MAX_PILE_COVER:
            raise ValueError(
                f"no room for {self.bodies} bodies of radius up to {rmax} in a {w} x {h} box: they would "
                f"cover {cover:.0%} of it, and a pile of discs covers at most about {MAX_PILE_COVER:.0%}; "
                "use a larger --box-size, fewer --bodies or a smaller --radius"
            )

    @property
    def spawn_height(self) -> float:
        """Height (m) of the region the bodies are placed in at random.

        The box itself when they cover at most MAX_RANDOM_COVER of it (the
        thesis world); otherwise a taller region over the same floor, so that
        they cover that share of it, from which they fall into the box (a
        dense world). The side walls rise to this height."""
        w, h = self.box_size
        need = self.bodies * math.pi * self.radius[1] ** 2 / (MAX_RANDOM_COVER * w)
        return float(h) if need <= h else float(need)

    @property
    def physics(self) -> Physics:
        """The step's time and gravity, as the solver applies them (and the server's channels need)."""
        return Physics(self.solver.dt, (0.0, -float(self.gravity)))

    def walls(self) -> np.ndarray:
        """The static box's edges, (3, 4) float (x0, y0, x1, y1) m: floor, left
        and right side, the sides as high as the spawn region."""
        w, top = float(self.box_size[0]), self.spawn_height
        return np.array([[0.0, 0.0, w, 0.0], [0.0, 0.0, 0.0, top], [w, 0.0, w, top]])


def build_world(spec: SceneSpec, seed: int) -> Engine:
    """Build the world for (spec, seed) and wrap it in an Engine.

    Bodies are created in placement order, so body index i (creation order,
    after the static box at index 0) is the i-th placed body.
    """
    spec.validate()
    rng, radii, is_box, friction, angles = _draws(spec, seed)
    w = spec.box_size[0]

    world = Box2D.b2World(gravity=(0.0, -spec.gravity), doSleep=False)
    # pybox2d 2.3.8 has no `allowSleeping` property (doSleep= only sets a plain
    # Python attribute); the C++ setter is the one that takes effect.
    world.SetAllowSleeping(False)
    world.continuousPhysics = False

    box = world.CreateStaticBody(position=(0.0, 0.0))
    for x0, y0, x1, y1 in spec.walls().tolist():
        box.CreateEdgeFixture(vertices=[(x0, y0), (x1, y1)], friction=spec.friction[1], restitution=spec.restitution)

    # Boxes are placed by their circumscribed circle so nothing overlaps.
    half_side = 0.5 * math.sqrt(math.pi) * radii
    reach = np.where(is_box, half_side * math.sqrt(2.0), radii)
    centres = _place_without_overlap(rng, reach, w, spec.spawn_height)

    for i in range(spec.bodies):
        body = world.CreateDynamicBody(position=tuple(map(float, centres[i])), angle=float(angles[i]))
        if is_box[i]:
            body.CreatePolygonFixture(
                box=(float(half_side[i]), float(half_side[i])),
                density=spec.density, friction=float(friction[i]), restitution=spec.restitution,
            )
        else:
            body.CreateCircleFixture(
                radius=float(radii[i]), density=spec.density, friction=float(friction[i]),
                restitution=spec.restitution,
            )
    return Engine(world, spec.solver)


def _draws(spec: SceneSpec, seed: int) -> tuple[np.random.Generator, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The seed's draws of each dynamic body's properties, (N,) each, in creation order:
    radius (m), is a box, friction, angle (rad); and the generator, which places them next."""
    rng = np.random.default_rng(seed)
    radii = rng.uniform(spec.radius[0], spec.radius[1], size=spec.bodies)
    is_box = rng.random(spec.bodies) < spec.polygons
    friction = rng.uniform(spec.friction[0], spec.friction[1], size=spec.bodies)
    angles = rng.uniform(0.0, 2.0 * math.pi, size=spec.bodies)
    return rng, radii, is_box, friction, angles


def body_friction(spec: SceneSpec, seed: int) -> np.ndarray:
    """(B,) each body's friction coefficient in the world build_world(spec, seed) makes,
    creation order (the records' body index, the static box first), without building it:
    what recorded data, which carries none, is read with (Engine.body_friction of the same world;
    float32 values, as Box2D keeps them)."""
    return np.concatenate([[float(spec.friction[1])], _draws(spec, seed)[3]]).astype(np.float32).astype(np.float64)


def _place_without_overlap(rng: np.random.Generator, reach: np.ndarray, w: float, h: float) -> np.ndarray:
    """Rejection-sample centres (N, 2) so discs of radius `reach` stay inside
    the box and apart. Setup code, run once per world."""
    n = len(reach)
    centres = np.empty((n, 2))
    tries = 0
    for i in range(n):
        r = reach[i]
        while True:
            tries += 1
            if tries > MAX_PLACEMENT_TRIES:
                raise ValueError(f"could not place {n} bodies without overlap in a {w} x {h} box")
            c = rng.uniform((r, r), (w - r, h - r))
            d2 = np.sum((centres[:i] - c) ** 2, axis=1)
            if np.all(d2 >= (reach[:i] + r) ** 2):
                centres[i] = c
                break
    return centres


# -- command line -----------------------------------------------------------

SCENES = {"thesis": SceneSpec.thesis}


def add_scene_arguments(parser) -> None:
    """The scene-family flags shared by generate, simulate and the benchmarks.

    `--scene` picks a base scene; each flag given overrides one of its values.
    """
    g = parser.add_argument_group("scene", "the world to simulate (defaults: the thesis world)")
    g.add_argument("--scene", default="thesis", choices=sorted(SCENES), help="base scene (default thesis)")
    g.add_argument("--bodies", type=int, metavar="N", help="number of dynamic bodies (thesis 100)")
    g.add_argument("--box-size", type=float, nargs=2, metavar=("W", "H"), help="static box size in m (thesis 15 15)")
    g.add_argument("--radius", type=float, nargs=2, metavar=("MIN", "MAX"), help="body radius range in m (thesis 0.5 0.5)")
    g.add_argument("--polygons", type=float, metavar="FRACTION",
                   help="share of bodies that are boxes of the same area as their circle (thesis 0)")
    g.add_argument("--friction", type=float, nargs=2, metavar=("MIN", "MAX"), help="friction range (thesis 0.5 0.5)")
    g.add_argument("--steps", type=int, metavar="N", help="steps per simulation (thesis 250)")
    g.add_argument("--tolerance", type=float, metavar="NS",
                   help="the solver stops after the first sweep whose largest impulse change is at most this "
                        "(N s; thesis 1e-4)")
    g.add_argument("--max-iterations", type=int, metavar="N",
                   help="the solver's cap on velocity iterations a step (thesis 1000)")


def spec_from_args(args) -> SceneSpec:
    """The SceneSpec the flags describe; ValueError if no world fits them."""
    spec = SCENES[args.scene]()
    overrides = {
        "bodies": args.bodies,
        "box_size": tuple(args.box_size) if args.box_size else None,
        "radius": tuple(args.radius) if args.radius else None,
        "polygons": args.polygons,
        "friction": tuple(args.friction) if args.friction else None,
        "steps": args.steps,
    }
    overrides = {k: v for k, v in overrides.items() if v is not None}
    solver = {k: v for k, v in (("velocity_threshold", args.tolerance), ("velocity_iterations", args.max_iterations))
              if v is not None}
    if solver:
        if solver.get("velocity_threshold", 1.0) <= 0 or solver.get("velocity_iterations", 1) < 1:
            raise ValueError(f"--tolerance must be > 0 N s and --max-iterations >= 1, got "
                             f"{args.tolerance} and {args.max_iterations}")
        overrides["solver"] = dataclasses.replace(spec.solver, **solver)
    if overrides:
        spec = dataclasses.replace(spec, name=f"{spec.name}-custom", **overrides)
    spec.validate()
    return spec


def spec_to_dict(spec: SceneSpec) -> dict:
    """JSON-ready form of a spec (stored with every data file and result)."""
    return dataclasses.asdict(spec)


def spec_from_dict(d: dict) -> SceneSpec:
    d = dict(d)
    d["solver"] = SolverConfig(**d["solver"])
    for key in ("box_size", "radius", "friction"):
        d[key] = tuple(d[key])
    return SceneSpec(**d)


def settled_world(spec: SceneSpec, seed: int, steps: int, **solver_overrides) -> Engine:
    """The world for (spec, seed) after `steps` builtin steps (a settled pile
    for the thesis world after ~150), with solver settings overridden, e.g.
    `settled_world(spec, 900, 200, statistics=False)`."""
    if solver_overrides:
        spec = dataclasses.replace(spec, solver=dataclasses.replace(spec.solver, **solver_overrides))
    engine = build_world(spec, seed)
    for _ in range(steps):
        engine.step()
    return engine
