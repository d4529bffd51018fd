"""What every warm-start provider is: the interface the simulation loop calls, and the
helpers for the contact limits that several providers share.

    provider.prepare(engine)                                  # before the first step
    warm = provider.warm_start(engine, bodies, points, step)  # after collide()
    # warm is None (use Box2D's own: builtin or none) or (normal (n,), tangent (n,)) float32, N s
    provider.observe(engine.contacts())                       # after the solve

A composite (`Composite`) is a warm start over warm starts: the engine's trial solves price
Box2D's warm start and each of its candidates on the same state, and it says which is served.

The product's providers and the registry of names (make_provider) are in simclient.warmstarts;
the lab's (oracles, probes, the composites) register there when `lab` is imported.
"""

from __future__ import annotations

import numpy as np

#: A normal impulse above this (N s) presses; at or below, the contact is open.
SWITCH_IMPULSE = 1e-6
#: Friction at this share of its limit or more slides (oracle:near-cone, solve-active@K).
CONE_SHARE = 0.99


class Provider:
    """A warm start: `name` is what make_provider was given; a provider that asks the server
    sets `uses_server`, one that needs the engine's trial solves sets `picks` (a Composite)."""

    name: str
    uses_server = False
    picks = False  # a Composite: the engine's trial solves choose among builtin and candidates

    def prepare(self, engine) -> None:
        """Before the first step (e.g. switch Box2D's own warm starting)."""
        engine.world.warmStarting = True

    def warm_start(self, engine, bodies, points, step):
        return None

    def observe(self, points_after_solve: np.ndarray) -> None:
        """After each solve, with the step's points and their final impulses."""


class Composite(Provider):
    """A warm start over warm starts: each step with contacts the stepping loop asks every
    one of `candidates` (a server one over the simulation's stream), hands their answers to
    pick(), which prices them by the engine's trial solves (the world unchanged) and returns
    the start the step is served. What the loop, run_simulation and bench iterations read:

        candidates   [Provider], in the order of the name (HEAD:W1+W2+...)
        pick(engine, points, served) -> (normal (P,), tangent (P,)) float32 N s
                     served: each candidate's answer, None where it fell back (Box2D's)
        trials       per step with contacts: each priced start's iterations, builtin's first
        reach        the same steps: each one's sweeps to Builtin's accuracy
        notes        the same steps: what note_labels names (empty for most)
        labels       what each entry of a trials row priced: ["builtin", candidates..., derived...]
        note_labels  what each entry of a notes row counts
        serves       whose start the steps were served, as a table says it ("Builtin's")

    The composites themselves are the lab's (lab.composites).
    """

    picks = True
    sends_oracle = False
    serves = "the picked"

    def __init__(self, candidates: list[Provider]):
        self.candidates = list(candidates)
        self.uses_server = any(c.uses_server for c in self.candidates)
        self.trials: list[list[int]] = []
        self.reach: list[list[int]] = []
        self.notes: list[list[float]] = []

    @property
    def models(self) -> tuple[str, ...]:
        """Every model the candidates ask the server for."""
        return tuple(m for c in self.candidates if c.uses_server for m in c.models)

    @property
    def model(self) -> str:
        return self.models[0] if self.models else ""

    @property
    def labels(self) -> list[str]:
        return ["builtin", *(c.name for c in self.candidates)]

    @property
    def note_labels(self) -> list[str]:
        return []

    def prepare(self, engine) -> None:
        for c in self.candidates:
            c.prepare(engine)

    def observe(self, points_after_solve):
        for c in self.candidates:
            c.observe(points_after_solve)

    def pick(self, engine, points, served: list):
        raise NotImplementedError


class ReadsFriction(Provider):
    """A provider that needs each point's friction coefficient (point_friction): it reads
    the bodies' from the world before the first step."""

    _friction = np.zeros(0)  # (B,) per body, creation order; set by prepare()

    def prepare(self, engine) -> None:
        super().prepare(engine)
        # pybox2d lists the bodies in creation order, the records' body index.
        self._friction = body_friction(engine)


def body_friction(engine) -> np.ndarray:
    """(B,) each body's friction coefficient, creation order (the records' body index): Engine.body_friction."""
    return engine.body_friction()


def point_friction(friction: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) the friction coefficient at each point: Box2D mixes two fixtures' as sqrt(f_A f_B)."""
    return np.sqrt(friction[points["body_a"]] * friction[points["body_b"]])


def at_friction_cone(impulses: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(P,) bool: the point presses (normal > SWITCH_IMPULSE) and its tangent impulse is at
    CONE_SHARE of mu times the normal one or more. impulses: (P, 2) N s."""
    return (impulses[:, 0] > SWITCH_IMPULSE) & (np.abs(impulses[:, 1]) >= CONE_SHARE * mu * impulses[:, 0])


def persisting_rows(keys: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(idx (P,), persisting (P,) bool): each point's row in `keys`, a previous step's sorted
    point keys, and whether it is there and Box2D carries an impulse into it (not a new point)."""
    idx = np.searchsorted(keys, points["key"]).clip(max=max(len(keys) - 1, 0))
    persisting = (keys[idx] == points["key"]) & points["builtin"].any(axis=1) if len(keys) else np.zeros(len(points), bool)
    return idx, persisting


def as_warm_start(warm: np.ndarray):
    """(P, 2) impulses (N s) as the (normal, tangent) float32 pair the engine takes."""
    warm = warm.astype(np.float32)
    return np.ascontiguousarray(warm[:, 0]), np.ascontiguousarray(warm[:, 1])
