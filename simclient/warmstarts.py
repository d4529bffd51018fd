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
Oracle experiments (where a warm start's value lies; docs/results.md):
    oracle:persisting   the oracle at points that persist, zero at new ones
    oracle:new          the oracle at new points, builtin where the point persists
    oracle:normal       the oracle's normal impulse, builtin's tangent
    oracle:tangent      builtin's normal impulse, the oracle's tangent
    oracle:heavy        the oracle at the more heavily loaded half of the points, builtin elsewhere
    oracle:half         builtin + half the oracle's correction (oracle - builtin)
    oracle:grid@RES     builtin + the oracle's correction through a grid of RES m
                        (h = 2 RES, poly6): what smoothing at that scale keeps
Remote:
    server:NAME  the warm-start server's model or provider NAME (see `ListModels`);
                 `server:grid-identity` is sent the oracle's impulses (thesis's Grid)
"""

from __future__ import annotations

import numpy as np

LOCAL = ("none", "builtin", "copy", "copy2", "copy0", "extrapolate")
ORACLES = ("persisting", "new", "normal", "tangent", "heavy", "half", "grid@RES")


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


class OracleMix(Provider):
    """The oracle's impulses where they say most, builtin elsewhere (see the module docstring)."""

    def __init__(self, variant: str):
        self.variant = variant
        self.name = f"oracle:{variant}"
        if variant.startswith("grid@"):
            try:
                res = float(variant[5:])
            except ValueError:
                res = -1.0
            if not res > 0:
                raise ValueError(f"oracle:grid@RES needs a grid spacing in m, e.g. oracle:grid@0.5, got {variant!r}")
            self.res = res
        elif variant not in ORACLES:
            raise ValueError(f"unknown oracle variant {variant!r}: use one of {', '.join(ORACLES)}")

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            return None  # nothing to warm-start
        exact = np.nan_to_num(engine.oracle()).astype(np.float64)  # NaN: outside every awake island
        builtin = points["builtin"].astype(np.float64)
        new = ~builtin.any(axis=1)
        v = self.variant
        if v == "persisting":
            warm = np.where(new[:, None], 0.0, exact)
        elif v == "new":
            warm = np.where(new[:, None], exact, builtin)
        elif v in ("normal", "tangent"):
            warm = builtin.copy()
            col = 0 if v == "normal" else 1
            warm[:, col] = exact[:, col]
        elif v == "heavy":
            heavy = exact[:, 0] >= np.median(exact[:, 0])
            warm = np.where(heavy[:, None], exact, builtin)
        elif v == "half":
            warm = builtin + 0.5 * (exact - builtin)
        else:
            from deepcontact.gridspec import GridSpec
            from deepcontact.transfer import plan

            # A grid from the scenes' origin (their box's lower-left corner) over every point.
            reach = np.ceil(points["point"].max(axis=0) / self.res) * self.res + self.res
            spec = GridSpec.for_domain((0.0, 0.0), tuple(np.maximum(reach, self.res)), self.res, 2 * self.res)
            pl = plan(points["point"], spec, outside="drop")
            warm = builtin + pl.g2p(pl.p2g(exact - builtin)[0])[0]
        warm = warm.astype(np.float32)
        return np.ascontiguousarray(warm[:, 0]), np.ascontiguousarray(warm[:, 1])


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
    if name.startswith("oracle:"):
        return OracleMix(name.split(":", 1)[1])
    factories = {
        "none": NoWarmStart,
        "builtin": Builtin,
        "copy": lambda: Copy("copy", None),
        "copy2": lambda: Copy("copy2", 2),
        "copy0": lambda: Copy("copy0", 0),
        "extrapolate": Extrapolate,
    }
    if name not in factories:
        raise ValueError(f"unknown warm start {name!r}: use one of {', '.join(LOCAL)}, oracle:VARIANT "
                         f"({', '.join(ORACLES)}) or server:MODEL")
    return factories[name]()
