"""Warm-start providers: where each step's starting impulses come from.

    provider = make_provider("copy2", client=None)
    warm = provider.warm_start(engine, bodies, points, step)   # after collide()
    # warm is None (use Box2D's own: builtin or none) or (normal (n,), tangent (n,)) float32, N s

Local providers (thesis §8.2 plus one it lacked):
    none         zeros (Box2D's warm starting off)
    builtin      Box2D's own: last step's impulse of the same point
    copy         the oracle: this step solved from zero to convergence
    copy2        the oracle rounded to two decimals
    copy0        the oracle rounded to integers
    extrapolate  J(t-1) + (J(t-1) - J(t-2)) for points that persist, builtin otherwise
Remote:
    server:NAME  the warm-start server's model or provider NAME (see `ListModels`);
                 `server:grid-identity` is sent the oracle's impulses (thesis's Grid)
"""

from __future__ import annotations

import numpy as np

LOCAL = ("none", "builtin", "copy", "copy2", "copy0", "extrapolate")


class Provider:
    name: str
    uses_server = False

    def prepare(self, engine) -> None:
        """Before the first step (e.g. switch Box2D's own warm starting)."""
        engine.world.warmStarting = True

    def warm_start(self, engine, bodies, points, step):
        return None

    def observe(self, points_after_solve: np.ndarray) -> None:
        """After each solve, with the step's points and their final impulses."""


class NoWarmStart(Provider):
    name = "none"

    def prepare(self, engine) -> None:
        engine.world.warmStarting = False


class Builtin(Provider):
    name = "builtin"


class Copy(Provider):
    """The oracle's impulses, optionally rounded to `decimals`."""

    def __init__(self, name: str, decimals: int | None):
        self.name, self.decimals = name, decimals

    def warm_start(self, engine, bodies, points, step):
        exact = engine.oracle()
        if self.decimals is not None:
            exact = np.round(exact, self.decimals)
        return np.ascontiguousarray(exact[:, 0]), np.ascontiguousarray(exact[:, 1])


class Extrapolate(Provider):
    """Linear extrapolation in time per contact point, matched by key."""

    name = "extrapolate"

    def __init__(self):
        self._keys = np.zeros(0, np.uint64)  # sorted keys of step t-1 ...
        self._impulse_prev2 = np.zeros((0, 2), np.float32)  # ... and their J(t-2)

    def warm_start(self, engine, bodies, points, step):
        builtin = points["builtin"]  # J(t-1) of the same point (0 for new points)
        warm = builtin.copy()
        if len(self._keys):
            idx = np.searchsorted(self._keys, points["key"]).clip(max=len(self._keys) - 1)
            prev2 = self._impulse_prev2[idx]
            ok = (self._keys[idx] == points["key"]) & np.isfinite(prev2).all(axis=1)
            warm[ok] = 2.0 * builtin[ok] - prev2[ok]
        return np.ascontiguousarray(warm[:, 0]), np.ascontiguousarray(warm[:, 1])

    def observe(self, points_after_solve):
        # For the next step, J(t-2) is this step's builtin (= J(t-1) now) of each point
        # that already existed, NaN for points new this step.
        order = np.argsort(points_after_solve["key"])
        keys = points_after_solve["key"][order]
        prev = points_after_solve["builtin"][order].astype(np.float32)
        # A point is new when Box2D had no impulse to carry over; builtin is then exactly 0.
        new = (prev == 0).all(axis=1)
        prev[new] = np.nan
        self._keys, self._impulse_prev2 = keys, prev


class Remote(Provider):
    """A model or provider on the warm-start server (see simclient.simulate)."""

    uses_server = True

    def __init__(self, model: str):
        self.model = model
        self.name = f"server:{model}"
        self.sends_oracle = model == "grid-identity"


def make_provider(name: str) -> Provider:
    """ValueError for an unknown name."""
    if name.startswith("server:"):
        model = name.split(":", 1)[1]
        if not model:
            raise ValueError("server: needs a model name, e.g. server:pressure")
        return Remote(model)
    factories = {
        "none": NoWarmStart,
        "builtin": Builtin,
        "copy": lambda: Copy("copy", None),
        "copy2": lambda: Copy("copy2", 2),
        "copy0": lambda: Copy("copy0", 0),
        "extrapolate": Extrapolate,
    }
    if name not in factories:
        raise ValueError(f"unknown warm start {name!r}: use one of {', '.join(LOCAL)} or server:MODEL")
    return factories[name]()
