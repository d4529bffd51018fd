"""Worlds to simulate: the project's scenes and the worlds users build.

A user's world is a function of the seed that returns a patched `Box2D.b2World` (or a
`(world, dt)` pair, where the seed draws the time step too), named on the command line as
`PATH.py:FUNCTION` or `MODULE:FUNCTION`:

    deepcontact bench iterations --world examples/pyramid.py:build --seeds 901-920 ...

    spec = spec_from_args(args)          # SceneSpec (--scene ...) or WorldSpec (--world ...)
    engine = build(spec, seed)           # an Engine driving that world
    message = world_message(spec, engine)  # what a stream declares: domain, static edges, physics

What the server is told of a user's world is read from the world once, when a
simulation starts (`describe`): the domain is the bounding box of every fixture
then, the static edges are the static bodies' edges, chain segments and polygon
sides, and the gravity is the world's.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import math
import sys
from pathlib import Path

import numpy as np

from deepcontact import wire
from deepcontact.kinematics import Physics
from simclient import scene
from simclient.engine import Box2D, Engine, SolverConfig
from simclient.scene import SceneSpec

#: The fraction of the bounding box added on each side of a user's world's domain: bodies move.
DOMAIN_MARGIN = 0.1


@dataclasses.dataclass(frozen=True)
class WorldSpec:
    """A user's world: `source` names a function of the seed returning a patched b2World
    ("PATH.py:FUNCTION" or "MODULE:FUNCTION"); steps and the solver's settings (dt,
    tolerance, cap) come from the command line, the physics from the world."""

    source: str
    steps: int = 250
    solver: SolverConfig = SolverConfig()

    @property
    def name(self) -> str:
        return self.source

    def validate(self) -> None:
        if self.steps < 1:
            raise ValueError(f"steps must be >= 1, got {self.steps}")
        load_builder(self.source)


def load_builder(source: str):
    """The function `source` names ("PATH.py:FUNCTION" or "MODULE:FUNCTION"); ValueError, in
    one line, for a file or module that does not exist or does not import, or a missing name."""
    where, sep, function = source.rpartition(":")
    if not sep or not where or not function:
        raise ValueError(f"--world takes PATH.py:FUNCTION or MODULE:FUNCTION, got {source!r}")
    if where.endswith(".py") or "/" in where or "\\" in where:
        path = Path(where)
        if not path.is_file():
            raise ValueError(f"--world {source}: there is no file {where}")
        module = _module_from_file(path, source)
    else:
        try:
            module = importlib.import_module(where)
        except ImportError as exc:
            raise ValueError(f"--world {source}: cannot import module {where}: {exc}") from None
        except Exception as exc:
            raise ValueError(f"--world {source}: importing {where} raised {type(exc).__name__}: {exc}") from None
    builder = getattr(module, function, None)
    if builder is None or not callable(builder):
        raise ValueError(f"--world {source}: {where} has no function {function!r}")
    return builder


def _module_from_file(path: Path, source: str):
    """Import a user's file as a module of its own (its folder importable for its own imports)."""
    resolved = path.resolve()
    name = "deepcontact_world_" + "".join(c if c.isalnum() else "_" for c in str(resolved))
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, resolved)
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(resolved.parent))
    try:
        spec.loader.exec_module(module)
    except Exception as exc:
        raise ValueError(f"--world {source}: importing {path} raised {type(exc).__name__}: {exc}") from None
    finally:
        sys.path.remove(str(resolved.parent))
    sys.modules[name] = module
    return module


def build_user_world(source: str, seed: int) -> tuple["Box2D.b2World", float | None]:
    """(the world FUNCTION(seed) builds, its time step or None): FUNCTION returns a world, or a
    (world, dt) pair where the seed draws the time step too (simclient.zoo's classes). ValueError
    when it raises or returns something else."""
    builder = load_builder(source)
    try:
        built = builder(seed)
    except Exception as exc:
        raise ValueError(f"--world {source}: {source.rpartition(':')[2]}({seed}) raised "
                         f"{type(exc).__name__}: {exc}") from None
    world, dt = built if isinstance(built, tuple) and len(built) == 2 else (built, None)
    if not isinstance(world, Box2D.b2World) or not (dt is None or (isinstance(dt, (int, float))
                                                                  and math.isfinite(dt) and dt > 0)):
        raise ValueError(f"--world {source}: {source.rpartition(':')[2]}({seed}) returned "
                         f"{type(built).__name__}, not a Box2D.b2World or a (world, dt > 0) pair")
    return world, None if dt is None else float(dt)


def build(spec, seed: int) -> Engine:
    """The Engine of (spec, seed): a project scene (SceneSpec) or a user's world (WorldSpec; its
    time step the builder's where it draws one, else the spec's)."""
    if isinstance(spec, WorldSpec):
        world, dt = build_user_world(spec.source, seed)
        return Engine(world, spec.solver if dt is None else dataclasses.replace(spec.solver, dt=dt))
    return scene.build_world(spec, seed)


def world_message(spec, engine: Engine):
    """What a stream declares for this simulation (deepcontact.v1.World)."""
    if isinstance(spec, SceneSpec):
        lower, upper = spec.domain
        return wire.encode_world(lower, upper, spec.walls(), spec.physics, spec.solver.stopping_tolerance)
    return describe(engine.world, engine.config.dt, engine.config.stopping_tolerance)


def describe(world: "Box2D.b2World", dt: float, tolerance: float = 0.0):
    """A user's world as a stream declares it: the domain (every fixture's bounding box now,
    widened by DOMAIN_MARGIN), the static bodies' edges, the physics (dt s, the world's
    gravity) and the solver's stopping rule (tolerance, N s; 0: not said). Read once per
    simulation: a loop over the world's fixtures in Python."""
    boxes, edges = [], []
    for body in world.bodies:
        static = body.type == Box2D.b2_staticBody
        for fixture in body.fixtures:
            for child in range(fixture.shape.childCount):
                box = fixture.GetAABB(child)
                boxes.append((*box.lowerBound, *box.upperBound))
            if static:
                edges += _static_edges(body, fixture.shape)
    if boxes:
        b = np.array(boxes, float)
        lower, upper = b[:, :2].min(axis=0), b[:, 2:].max(axis=0)
    else:
        lower, upper = np.zeros(2), np.ones(2)
    margin = np.maximum(DOMAIN_MARGIN * (upper - lower), 1.0)
    lower, upper = lower - margin, upper + margin
    gravity = (float(world.gravity[0]), float(world.gravity[1]))
    return wire.encode_world((float(lower[0]), float(lower[1])), (float(upper[0]), float(upper[1])),
                             np.array(edges, float).reshape(-1, 4), Physics(float(dt), gravity), float(tolerance))


def _static_edges(body, shape) -> list[tuple[float, float, float, float]]:
    """A static fixture's segments in world coordinates (x0, y0, x1, y1): an edge, a chain's
    segments, a polygon's sides; none for a circle."""
    if isinstance(shape, Box2D.b2EdgeShape):
        vertices = list(shape.vertices)
        closed = False
    elif isinstance(shape, Box2D.b2ChainShape):
        vertices = list(shape.vertices)[: shape.childCount + 1]
        closed = False
    elif isinstance(shape, Box2D.b2PolygonShape):
        vertices = list(shape.vertices)
        closed = True
    else:
        return []
    world_vertices = [tuple(body.transform * v) for v in vertices]
    if closed:
        world_vertices.append(world_vertices[0])
    return [(*a, *b) for a, b in zip(world_vertices[:-1], world_vertices[1:])]


# -- command line --------------------------------------------------------------

def add_world_arguments(parser) -> None:
    """The scene flags (simclient.scene) and --world, --dt: what simulate and bench iterations run."""
    scene.add_scene_arguments(parser)
    g = [a for a in parser._action_groups if a.title == "scene"][0]
    g.add_argument("--world", metavar="PATH.py:FUNCTION",
                   help="a world of your own instead of a scene: FUNCTION(seed) in PATH.py (or MODULE:FUNCTION) "
                        "returns a patched Box2D.b2World; --steps, --dt, --tolerance and --max-iterations apply "
                        "(docs/worlds.md)")
    g.add_argument("--dt", type=float, metavar="S", help="time step in s (thesis 0.01)")


#: Flags that describe a project scene's bodies: meaningless for a user's world.
_SCENE_ONLY = ("bodies", "box_size", "radius", "polygons", "friction")


def spec_from_args(args):
    """The SceneSpec or WorldSpec the flags describe; ValueError, in one line, if none fits."""
    if args.dt is not None and not (math.isfinite(args.dt) and args.dt > 0):
        raise ValueError(f"--dt must be a positive number of seconds, got {args.dt}")
    if getattr(args, "world", None) is None:
        spec = scene.spec_from_args(args)
        if args.dt is not None:
            spec = dataclasses.replace(spec, name=spec.name if spec.name.endswith("-custom") else f"{spec.name}-custom",
                                       solver=dataclasses.replace(spec.solver, dt=args.dt))
        return spec
    given = [f"--{k.replace('_', '-')}" for k in _SCENE_ONLY if getattr(args, k, None) is not None]
    if given or args.scene != "thesis":
        raise ValueError(f"{', '.join(given) or '--scene'} describes the project's scenes; --world builds its own")
    solver = SolverConfig()
    overrides = {k: v for k, v in (("velocity_threshold", args.tolerance), ("velocity_iterations", args.max_iterations),
                                   ("dt", args.dt)) if v is not None}
    if overrides.get("velocity_threshold", 1.0) <= 0 or overrides.get("velocity_iterations", 1) < 1:
        raise ValueError(f"--tolerance must be > 0 N s and --max-iterations >= 1, got "
                         f"{args.tolerance} and {args.max_iterations}")
    spec = WorldSpec(args.world, steps=args.steps or 250, solver=dataclasses.replace(solver, **overrides))
    spec.validate()
    return spec


def spec_to_dict(spec) -> dict:
    """JSON-ready form of a SceneSpec or WorldSpec (stored with every result)."""
    if isinstance(spec, WorldSpec):
        return {"kind": "world", **dataclasses.asdict(spec)}
    return scene.spec_to_dict(spec)


def spec_from_dict(d: dict):
    if d.get("kind") == "world":
        d = {k: v for k, v in d.items() if k != "kind"}
        return WorldSpec(d["source"], steps=d["steps"], solver=SolverConfig(**d["solver"]))
    return scene.spec_from_dict(d)
