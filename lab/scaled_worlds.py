"""The thesis world scaled in density, gravity and time step, as worlds of the command line:
does a warm start read a heavier, stronger-pulled or coarser-stepped world as the same problem?

    deepcontact bench iterations --world lab.scaled_worlds:density_10 --seeds 901-920 \
        --warm-starts builtin,server:default --no-guard --out bench/results/scaled-density_10

Each function builds the thesis world of its seed (simclient.scene.SceneSpec.thesis: the same
discs at the same places) with one quantity changed, and returns it with its time step. Only
density scales the problem exactly (every mass and impulse times the factor, every velocity the
same); gravity and the time step change the motion too. Box2D's stopping rule is an absolute
impulse (1e-4 N s), so even a denser world takes Box2D's own warm start more sweeps: the ratio
to Builtin, not the count, is what a unit-free warm start keeps. With the stopping rule scaled as
the step's impulses are (`relative_tolerance`: 1e-4 N s times the world's density, gravity and
time step over the thesis world's), the dense world is the thesis world to the sweep, and the
others differ from it only in their motion. Gravity and the time step changed together, gravity
times k with the time step over sqrt(k) (`similar_...`), keep the motion too: every body passes
through the same positions step by step, its velocities and impulses times sqrt(k):

    python -m lab.scaled_worlds        # each world's command with its relative stopping rule
"""

from __future__ import annotations

import dataclasses
import math

from simclient.scene import SceneSpec, build_world

#: Each world's change to the thesis world: density (kg/m^2), gravity (m/s^2) or dt (s).
SCALINGS = {
    "reference": {},
    "density_0p5": {"density": 0.5},
    "density_10": {"density": 10.0},
    "gravity_2": {"gravity": 2.0},
    "gravity_20": {"gravity": 20.0},
    "dt_1_120": {"dt": 1 / 120},
    "dt_1_30": {"dt": 1 / 30},
    # Similar in time: gravity times k with the time step over sqrt(k) moves every body through the
    # same positions step by step (x = g t^2 / 2), its velocities and impulses times sqrt(k): the
    # thesis world's problem in other units, as far as Box2D's velocity thresholds (sleep) allow.
    "similar_gravity_2": {"gravity": 2.0, "dt": 0.01 * math.sqrt(9.8 / 2.0)},
    "similar_dt_1_120": {"gravity": 9.8 * 1.2 ** 2, "dt": 1 / 120},
}


def _scaled(seed: int, density: float = 1.0, gravity: float = 9.8, dt: float = 0.01):
    thesis = SceneSpec.thesis()
    spec = dataclasses.replace(thesis, density=density, gravity=gravity,
                               solver=dataclasses.replace(thesis.solver, dt=dt))
    return build_world(spec, seed).world, dt


def _world(name: str):
    def build(seed: int):
        return _scaled(seed, **SCALINGS[name])
    build.__name__ = name
    build.__doc__ = f"The thesis world of the seed with {SCALINGS[name] or 'nothing'} changed: (world, dt)."
    return build


(reference, density_0p5, density_10, gravity_2, gravity_20, dt_1_120, dt_1_30, similar_gravity_2,
 similar_dt_1_120) = (_world(n) for n in SCALINGS)

#: The thesis world's stopping rule (N s) and the quantities its impulses scale with.
THESIS_TOLERANCE, THESIS = 1e-4, {"density": 1.0, "gravity": 9.8, "dt": 0.01}


def relative_tolerance(name: str) -> float:
    """The stopping rule (N s) that is to the world `name`'s impulses (mass times gravity times
    the time step, m g dt) what the thesis world's 1e-4 N s is to its own. KeyError for no such world."""
    scale = {**THESIS, **SCALINGS[name]}
    return THESIS_TOLERANCE * (scale["density"] / THESIS["density"]) * (scale["gravity"] / THESIS["gravity"]) * (
        scale["dt"] / THESIS["dt"])


if __name__ == "__main__":
    for name in SCALINGS:
        print(f"deepcontact bench iterations --world lab.scaled_worlds:{name} --seeds 901-910 --workers 1 --no-guard "
              f"--tolerance {relative_tolerance(name):.5g} --warm-starts builtin,server:default --out OUT-{name}")
