"""The thesis world scaled in density, gravity and time step, as worlds of the command line:
does a warm start read a heavier, stronger-pulled or coarser-stepped world as the same problem?

    deepcontact bench iterations --world lab.scaled_worlds:density_10 --seeds 901-920 \
        --warm-starts builtin,server:default --no-guard --out bench/results/scaled-density_10

Each function builds the thesis world of its seed (simclient.scene.SceneSpec.thesis: the same
discs at the same places) with one quantity changed, and returns it with its time step. Only
density scales the problem exactly (every mass and impulse times the factor, every velocity the
same); gravity and the time step change the motion too. Box2D's stopping rule is an absolute
impulse (1e-4 N s), so even a denser world takes Box2D's own warm start more sweeps: the ratio
to Builtin, not the count, is what a unit-free warm start keeps.
"""

from __future__ import annotations

import dataclasses

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


reference, density_0p5, density_10, gravity_2, gravity_20, dt_1_120, dt_1_30 = (_world(n) for n in SCALINGS)
