"""Grid geometry, kernel choice and channel layout shared by training and serving.

A :class:`GridSpec` says everything needed to turn a world (bodies and contact
points) into the CNN's input grid and to turn the CNN's output grid back into
per-contact impulses: where the grid lies, how fine it is, which SPH kernel and
support radius splat the particles, which channels go in and come out (and in
what order), and how each channel is normalized.  One spec is written into
every exported model's card and read back by the server, so serving transfers
exactly as training did; ``to_json``/``from_json`` round-trip it exactly.

Channels are named here and defined in :mod:`deepcontact.channels` (plain
definitions imported by training and serving alike); the spec only checks
that the names it lists exist there.

Conventions
-----------
* Units: metres, seconds, kilograms (the engine's units).
* A grid covers its domain *including both end points*: node ``(iy, ix)`` sits
  at ``(origin[0] + ix * resolution, origin[1] + iy * resolution)``, so a
  15 m x 15 m domain at 0.25 m has 61 x 61 nodes (thesis §8.1).
* Grid arrays are ``(ny, nx, C)`` float32, channels last (the CNN is NHWC).

This module imports neither Box2D nor the engine wrapper: the structured
arrays are only read by field name.
"""

from __future__ import annotations


import json
import math
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from types import MappingProxyType
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from deepcontact.channels import CHANNELS, DEFAULT_INPUTS, DEFAULT_TARGETS

__all__ = ["GridSpec", "KERNELS", "WALL_SIDES"]

#: Format version written into every serialized spec; bump on incompatible change.
SPEC_VERSION = 1

#: Kernel names understood by :mod:`deepcontact.transfer` (thesis eq. 5.2-5.4).
KERNELS = ("poly6", "spiky", "gaussian")

#: Sides of the grid that can carry the static box's wall mass (the box has no top).
WALL_SIDES = ("bottom", "left", "right", "top")


# --------------------------------------------------------------------------- #
# GridSpec
# --------------------------------------------------------------------------- #


@lru_cache(maxsize=32)
def _wall_nodes(shape: tuple[int, int], walls: tuple[str, ...]) -> np.ndarray:
    """Flat indices (iy * nx + ix) of the wall nodes, each once (corners are shared)."""
    ny, nx = shape
    mask = np.zeros(shape, dtype=bool)
    if "bottom" in walls:
        mask[0, :] = True
    if "top" in walls:
        mask[-1, :] = True
    if "left" in walls:
        mask[:, 0] = True
    if "right" in walls:
        mask[:, -1] = True
    nodes = np.flatnonzero(mask)
    nodes.flags.writeable = False
    return nodes


def _finite(name: str, value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v!r}")
    return v


def _pair(name: str, value: Any) -> tuple[float, float]:
    try:
        a, b = value
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (x, y), got {value!r}") from None
    return _finite(f"{name}[0]", a), _finite(f"{name}[1]", b)


def _names(name: str, value: Any) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Iterable):
        raise ValueError(f"{name} must be a sequence of channel names, got {value!r}")
    names = tuple(value)
    for n in names:
        if n not in CHANNELS:
            raise ValueError(f"{name}: unknown channel {n!r}; known channels: {sorted(CHANNELS)}")
    if len(set(names)) != len(names):
        raise ValueError(f"{name}: duplicate channel names in {list(names)}")
    return names


@dataclass(frozen=True)
class GridSpec:
    """Geometry, kernel, channels and normalization of the particle/grid transfer.

    Build one with :meth:`for_domain` (or :meth:`thesis`) rather than by hand.

    Attributes
    ----------
    origin:
        World position (x, y) m of node (0, 0), the domain's lower-left corner.
    resolution:
        Node spacing dx = dy, m.
    shape:
        (ny, nx) number of nodes; the grid spans ``origin`` to
        ``origin + (shape[::-1] - 1) * resolution`` inclusive.
    h:
        SPH support radius, m: a particle and a node interact iff their
        distance is at most ``h`` (and the kernel weight is positive).
    kernel:
        One of :data:`KERNELS`: ``"poly6"`` (default, thesis), ``"spiky"``,
        ``"gaussian"`` (sigma = h/3, truncated at h).
    inputs, targets:
        Channel names, in grid-channel order (keys of :data:`deepcontact.channels.CHANNELS`).
        Targets must be contact-point channels (they are transferred back to
        the contact points).
    normalization:
        channel name -> (mean, std); :meth:`normalize` maps ``v`` to
        ``(v - mean) / std``.  Channels not listed are left as they are.
    wall_mass:
        Mass, kg, added to the nodes on the static box's edges in every
        ``walls=True`` channel (``"mass"``) by
        :func:`deepcontact.features.world_to_grids`; 0 disables it.  Thesis
        §8.1 uses 100.
    walls:
        Grid sides carrying the wall mass, from :data:`WALL_SIDES`; the thesis
        box is a bottom and two sides on the domain's edges, with no top.
    version:
        Serialization format version (:data:`SPEC_VERSION`).
    """

    origin: tuple[float, float]
    resolution: float
    shape: tuple[int, int]
    h: float
    kernel: str = "poly6"
    inputs: tuple[str, ...] = DEFAULT_INPUTS
    targets: tuple[str, ...] = DEFAULT_TARGETS
    normalization: Mapping[str, tuple[float, float]] = field(default_factory=dict, hash=False)
    wall_mass: float = 100.0
    walls: tuple[str, ...] = ("bottom", "left", "right")
    version: int = SPEC_VERSION

    def __post_init__(self) -> None:
        # Normalize types (lists from JSON -> tuples) and validate; frozen, so
        # go through object.__setattr__.
        set_ = object.__setattr__
        set_(self, "origin", _pair("origin", self.origin))
        res = _finite("resolution", self.resolution)
        if res <= 0:
            raise ValueError(f"resolution must be > 0 m, got {res!r}")
        set_(self, "resolution", res)
        try:
            ny, nx = self.shape
        except (TypeError, ValueError):
            raise ValueError(f"shape must be (ny, nx), got {self.shape!r}") from None
        if not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 1 for v in (ny, nx)):
            raise ValueError(f"shape must be two positive integers (ny, nx), got {self.shape!r}")
        set_(self, "shape", (int(ny), int(nx)))
        h = _finite("h", self.h)
        if h <= 0:
            raise ValueError(f"support radius h must be > 0 m, got {h!r}")
        set_(self, "h", h)
        if not isinstance(self.kernel, str) or self.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {self.kernel!r}; known kernels: {list(KERNELS)}")
        set_(self, "inputs", _names("inputs", self.inputs))
        set_(self, "targets", _names("targets", self.targets))
        for n in self.targets:
            if CHANNELS[n].source != "contacts":
                raise ValueError(
                    f"target channel {n!r} is a {CHANNELS[n].source} channel; targets must be contact-point channels"
                )
        if not isinstance(self.normalization, Mapping):
            raise ValueError(f"normalization must be a mapping channel -> (mean, std), got {self.normalization!r}")
        norm: dict[str, tuple[float, float]] = {}
        for n, ms in self.normalization.items():
            if n not in self.inputs and n not in self.targets:
                raise ValueError(f"normalization: channel {n!r} is neither an input nor a target")
            mean, std = _pair(f"normalization[{n!r}]", ms)
            if std <= 0:
                raise ValueError(f"normalization[{n!r}]: std must be > 0, got {std!r}")
            norm[n] = (mean, std)
        set_(self, "normalization", MappingProxyType(norm))
        set_(self, "wall_mass", _finite("wall_mass", self.wall_mass))
        walls = tuple(self.walls) if not isinstance(self.walls, str) else (self.walls,)
        for w in walls:
            if w not in WALL_SIDES:
                raise ValueError(f"walls: unknown side {w!r}; known sides: {list(WALL_SIDES)}")
        set_(self, "walls", walls)
        if isinstance(self.version, bool) or not isinstance(self.version, int) or not 1 <= self.version <= SPEC_VERSION:
            raise ValueError(f"unsupported GridSpec version {self.version!r}; this code reads versions 1..{SPEC_VERSION}")

    # -- construction ------------------------------------------------------- #

    @classmethod
    def for_domain(
        cls,
        lower: Sequence[float],
        upper: Sequence[float],
        resolution: float,
        h: float,
        kernel: str = "poly6",
        **kwargs: Any,
    ) -> "GridSpec":
        """A spec whose nodes cover the box ``lower``..``upper`` (m) including both ends.

        ``nx = round(width / resolution) + 1`` when the width is a whole number
        of cells (to 1e-9 relative), otherwise ``ceil(width / resolution) + 1``
        so the grid still covers the domain; likewise ``ny``.  Other keyword
        arguments (``inputs``, ``targets``, ``normalization``, ``wall_mass``,
        ``walls``) are passed to the constructor.
        """
        x0, y0 = _pair("lower", lower)
        x1, y1 = _pair("upper", upper)
        res = _finite("resolution", resolution)
        if res <= 0:
            raise ValueError(f"resolution must be > 0 m, got {res!r}")
        if not (x1 > x0 and y1 > y0):
            raise ValueError(f"upper {upper!r} must be above and to the right of lower {lower!r}")

        def count(width: float) -> int:
            cells = width / res
            nearest = round(cells)
            if abs(cells - nearest) <= 1e-9 * max(1.0, cells):
                return int(nearest) + 1
            return int(math.ceil(cells)) + 1

        return cls(origin=(x0, y0), resolution=res, shape=(count(y1 - y0), count(x1 - x0)), h=h, kernel=kernel, **kwargs)

    @classmethod
    def thesis(cls, **kwargs: Any) -> "GridSpec":
        """The thesis grid (§8.1): 15 m x 15 m box at (0, 0), 0.25 m, h = 0.5 m, poly6: 61 x 61."""
        return cls.for_domain((0.0, 0.0), (15.0, 15.0), 0.25, 0.5, **kwargs)

    def with_normalization(self, normalization: Mapping[str, tuple[float, float]]) -> "GridSpec":
        """A copy with ``normalization`` (channel -> (mean, std)) instead of the current one."""
        return replace(self, normalization=dict(normalization))

    # -- geometry ----------------------------------------------------------- #

    @property
    def ny(self) -> int:
        return self.shape[0]

    @property
    def nx(self) -> int:
        return self.shape[1]

    @property
    def lower(self) -> tuple[float, float]:
        """World position (x, y) m of node (0, 0)."""
        return self.origin

    @property
    def upper(self) -> tuple[float, float]:
        """World position (x, y) m of the last node (ny-1, nx-1)."""
        return (
            self.origin[0] + (self.nx - 1) * self.resolution,
            self.origin[1] + (self.ny - 1) * self.resolution,
        )

    @property
    def n_nodes(self) -> int:
        return self.shape[0] * self.shape[1]

    def node_positions(self) -> np.ndarray:
        """World positions of all nodes, (ny, nx, 2) float64 m, last axis (x, y)."""
        xs = self.origin[0] + np.arange(self.nx) * self.resolution
        ys = self.origin[1] + np.arange(self.ny) * self.resolution
        gx, gy = np.meshgrid(xs, ys)  # 'xy' indexing: (ny, nx)
        return np.stack([gx, gy], axis=-1)

    def wall_mask(self) -> np.ndarray:
        """(ny, nx) bool: the nodes on the static box's edges (sides in :attr:`walls`)."""
        mask = np.zeros(self.n_nodes, dtype=bool)
        mask[_wall_nodes(self.shape, self.walls)] = True
        return mask.reshape(self.shape)

    def add_wall_mass(self, grid: np.ndarray, channels: Sequence[str] | None = None) -> np.ndarray:
        """Add :attr:`wall_mass` in place to the wall nodes of every ``walls=True`` channel.

        ``grid`` is (ny, nx, C) (or (B, ny, nx, C)) laid out as ``channels``
        (default :attr:`inputs`).  Returns ``grid``.
        """
        channels = self.inputs if channels is None else tuple(channels)
        if self.wall_mass == 0.0:
            return grid
        cols = [j for j, n in enumerate(channels) if CHANNELS[n].walls]
        if cols:
            nodes = _wall_nodes(self.shape, self.walls)
            flat = grid.reshape(-1, self.n_nodes, grid.shape[-1])  # (B, ny * nx, C) view
            for j in cols:  # loop over channels only
                flat[:, nodes, j] += self.wall_mass
        return grid

    # -- normalization ------------------------------------------------------ #

    def normalization_arrays(self, channels: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """(mean (C,), std (C,)) float32 for ``channels``; unlisted channels get (0, 1)."""
        mean = np.array([self.normalization.get(n, (0.0, 1.0))[0] for n in channels], dtype=np.float32)
        std = np.array([self.normalization.get(n, (0.0, 1.0))[1] for n in channels], dtype=np.float32)
        return mean, std

    def normalize(self, grid: np.ndarray, which: str = "inputs") -> np.ndarray:
        """``(grid - mean) / std`` per channel, float32; ``which`` is "inputs" or "targets".

        grid: (..., nx, C) with C the channels of ``which``."""
        grid = np.asarray(grid)
        mean, inv_std = _row_normalization(self, which, grid.shape[-2])
        rows = grid.reshape(*grid.shape[:-2], -1)  # (..., nx * C): long inner loops
        out = np.subtract(rows, mean, dtype=np.float32)
        out *= inv_std
        return out.reshape(grid.shape)

    def denormalize(self, grid: np.ndarray, which: str = "targets") -> np.ndarray:
        """Inverse of :meth:`normalize`: ``grid * std + mean`` per channel, float32."""
        grid = np.asarray(grid)
        mean, inv_std = _row_normalization(self, which, grid.shape[-2])
        rows = grid.reshape(*grid.shape[:-2], -1)
        out = np.divide(rows, inv_std, dtype=np.float32)
        out += mean
        return out.reshape(grid.shape)

    def _channels(self, which: str) -> tuple[str, ...]:
        if which == "inputs":
            return self.inputs
        if which == "targets":
            return self.targets
        raise ValueError(f"which must be 'inputs' or 'targets', got {which!r}")

    # -- serialization ------------------------------------------------------ #

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able dict (lists, floats, strings); :meth:`from_dict` inverts it exactly."""
        return {
            "version": self.version,
            "origin": list(self.origin),
            "resolution": self.resolution,
            "shape": list(self.shape),
            "h": self.h,
            "kernel": self.kernel,
            "inputs": list(self.inputs),
            "targets": list(self.targets),
            "normalization": {n: {"mean": m, "std": s} for n, (m, s) in self.normalization.items()},
            "wall_mass": self.wall_mass,
            "walls": list(self.walls),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "GridSpec":
        """Build from :meth:`to_dict` output; unknown or missing keys raise ValueError."""
        if not isinstance(data, Mapping):
            raise ValueError(f"GridSpec data must be a mapping, got {type(data).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"GridSpec: unknown keys {sorted(unknown)}")
        required = {"origin", "resolution", "shape", "h"}
        missing = required - set(data)
        if missing:
            raise ValueError(f"GridSpec: missing keys {sorted(missing)}")
        kw = dict(data)
        norm = kw.get("normalization", {})
        if not isinstance(norm, Mapping):
            raise ValueError(f"normalization must be a mapping, got {norm!r}")
        parsed = {}
        for n, ms in norm.items():
            if isinstance(ms, Mapping):
                if set(ms) != {"mean", "std"}:
                    raise ValueError(f"normalization[{n!r}] must have exactly 'mean' and 'std', got {sorted(ms)}")
                parsed[n] = (ms["mean"], ms["std"])
            else:
                parsed[n] = ms
        kw["normalization"] = parsed
        return cls(**kw)

    def to_json(self, indent: int | None = 2) -> str:
        """JSON text of :meth:`to_dict` (floats written with Python's exact repr)."""
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> "GridSpec":
        """Inverse of :meth:`to_json`; malformed JSON or bad values raise ValueError."""
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"GridSpec JSON is malformed: {exc}") from None
        return cls.from_dict(data)


@lru_cache(maxsize=256)
def _row_normalization(spec: GridSpec, which: str, nx: int) -> tuple[np.ndarray, np.ndarray]:
    """(mean, 1/std) tiled over one grid row, (nx * C,) float32, built once per
    (spec, which, nx). Broadcasting over a last axis of 2-6 channels runs NumPy's
    inner loop a few elements at a time; a whole row at once is ~4x faster."""
    mean, std = spec.normalization_arrays(spec._channels(which))
    mean, inv_std = np.tile(mean, nx), np.tile(np.float32(1.0) / std, nx)
    mean.flags.writeable = False
    inv_std.flags.writeable = False
    return mean, inv_std
