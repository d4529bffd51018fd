"""Warm-start providers: where each step's starting impulses come from, and the registry of their names.

    provider = make_provider("copy2")
    warm = provider.warm_start(engine, bodies, points, step)   # after collide()
    # warm is None (use Box2D's own: builtin or none) or (normal (n,), tangent (n,)) float32, N s

The product's warm starts (thesis §8.2 plus one it lacked), registered here:
    none         zeros (Box2D's warm starting off)
    builtin      Box2D's own: last step's impulse of the same point
    copy         the oracle: this step solved from zero to convergence
    copy2        the oracle rounded to two decimals
    copy0        the oracle rounded to integers
    extrapolate  J(t-1) + (J(t-1) - J(t-2)) for points that persist, builtin otherwise
    server:NAME  the warm-start server's model or provider NAME (see `ListModels`);
                 `server:grid-identity` is sent the oracle's impulses (thesis's Grid)

The registry: make_provider knows a name registered whole (register_name) or by its prefix
(register_prefix, e.g. "server:"); the longest registered prefix a name starts with makes it.
Other packages add theirs when imported: `import lab` registers the research warm starts
(oracle:VARIANT, the probes, the composites pick:W1+W2+... and the like; lab/README.md).
A composite's prefix is registered with composite=True: its names read HEAD:W1+W2+...
(composite_parts). A process started afresh (a pool worker, a Ray task) knows only the
product's names until it imports the modules that registered the others (extensions,
load_extensions). The interface is simclient.provider.Provider.
"""

from __future__ import annotations

import importlib
from typing import Callable, NamedTuple

import numpy as np

from simclient.provider import Provider


class Registered(NamedTuple):
    """One registered warm start: a whole name or a prefix."""

    usage: str  # how the help writes it, e.g. "server:NAME"
    make: Callable[[str], Provider]  # the whole name -> a provider (ValueError when it cannot make one)
    help: str  # one line
    module: str  # the module that registered it (a fresh process imports it to know the name)
    composite: bool = False  # HEAD:W1+W2+...: a warm start over the warm starts W1, W2, ...


_NAMES: dict[str, Registered] = {}
_PREFIXES: dict[str, Registered] = {}
_ORDER: dict[tuple[str, str], Registered] = {}  # both, in the order they were registered


def register_name(name: str, factory: Callable[[], Provider], help: str) -> None:
    """Make `name` mean factory() (a fresh provider per call). Registering a name again replaces it."""
    _NAMES[name] = _ORDER["name", name] = Registered(name, lambda _name: factory(), help, _module_of(factory))


def register_prefix(prefix: str, factory: Callable[[str], Provider], help: str, *, usage: str | None = None,
                    composite: bool = False) -> None:
    """Make every name that starts with `prefix` mean factory(name), the whole name; factory
    raises ValueError, with a one-line message, for a name it cannot make. usage: how help
    writes it (default PREFIX...). composite: names read HEAD:W1+W2+..., the warm starts W1,
    W2, ... priced by the engine's trial solves (a simclient.provider.Composite)."""
    _PREFIXES[prefix] = _ORDER["prefix", prefix] = Registered(usage or f"{prefix}...", factory, help,
                                                              _module_of(factory), composite)


def _module_of(factory) -> str:
    return getattr(factory, "__module__", None) or __name__


def registered() -> list[Registered]:
    """Every registered warm start in the order it was registered (the product's first)."""
    return list(_ORDER.values())


def usage() -> str:
    """The registered names as a help text writes them, comma-separated."""
    return ", ".join(r.usage for r in registered())


def extensions() -> tuple[str, ...]:
    """The modules other than this one that registered warm starts (e.g. lab's), sorted."""
    return tuple(sorted({r.module for r in registered()} - {__name__}))


def load_extensions(modules) -> None:
    """Import each of `modules` (extensions() of another process), so that their names are known here."""
    for module in modules:
        importlib.import_module(module)


def _prefix_of(name: str) -> Registered | None:
    """The registered prefix `name` starts with, the longest; None if none."""
    matches = [p for p in _PREFIXES if name.startswith(p)]
    return _PREFIXES[max(matches, key=len)] if matches else None


def composite_parts(name: str) -> tuple[str, list[str]] | None:
    """(HEAD, [W1, W2, ...]) of a composite's name HEAD:W1+W2+..., or None for any other name."""
    entry = None if name in _NAMES else _prefix_of(name)
    if entry is None or not entry.composite:
        return None
    head, _, rest = name.partition(":")
    return head, rest.split("+")


def make_provider(name: str) -> Provider:
    """A fresh provider for a registered name; ValueError for a name nothing registered."""
    if name in _NAMES:
        return _NAMES[name].make(name)
    entry = _prefix_of(name)
    if entry is None:
        raise ValueError(f"unknown warm start {name!r}: use one of {usage()}")
    return entry.make(name)


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
        # Points outside every awake island (NaN) are not solved this step: Box2D's own start there.
        asleep = ~np.isfinite(exact).all(axis=1)
        if asleep.any():
            exact[asleep] = np.asarray(points["builtin"], np.float32)[asleep]
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

    @property
    def models(self) -> tuple[str, ...]:
        """Every model this provider asks the server for."""
        return (self.model,)


def _remote(name: str) -> Remote:
    model = name.split(":", 1)[1]
    if not model:
        raise ValueError("server: needs a model name, e.g. server:default")
    return Remote(model)


register_name("none", NoWarmStart, "zeros (Box2D's warm starting off)")
register_name("builtin", Builtin, "Box2D's own: last step's impulse of the same point")
register_name("copy", lambda: Copy("copy", None), "the oracle: this step solved from zero to convergence")
register_name("copy2", lambda: Copy("copy2", 2), "the oracle rounded to two decimals")
register_name("copy0", lambda: Copy("copy0", 0), "the oracle rounded to integers")
register_name("extrapolate", Extrapolate, "J(t-1) + (J(t-1) - J(t-2)) at points that persist, builtin at new ones")
register_prefix("server:", _remote, "the warm-start server's model or provider NAME (ListModels); "
                "server:grid-identity is sent the oracle's impulses", usage="server:NAME")
