"""Particle <-> grid transfer: SPH splatting (P2G) and its reverse (G2P).

This is the one implementation of the thesis's transfer methods (§5), used by
data generation, training, the server and the Grid baseline.

* :func:`p2g` (thesis Algorithm 1): each particle spreads its values over the
  grid nodes within the support radius ``h``, with kernel weights normalized to
  sum to one *per particle*.  The grid total of every channel therefore equals
  the particle total, except for particles with no node in range, which are
  counted in the report (never silently dropped).
* :func:`g2p` with ``method="sph"`` (thesis Algorithm 2): each node spreads its
  values over the particles within ``h``, with weights normalized to sum to one
  *per node*.  The particle total equals the total of the nodes that have at
  least one particle in range; the rest is reported.
* :func:`g2p` with ``method="bilinear"`` (thesis §5.4.1): standard bilinear
  interpolation of the four surrounding nodes.
* :func:`p2g_sets` splats several sets of particles (bodies, contact points,
  several worlds) with one weight computation: what
  :mod:`deepcontact.features` builds the CNN's grids with.
* :func:`plan` computes the kernel weights of a set of particles once, for
  any number of P2G and SPH G2P transfers (:class:`TransferPlan`); P2G and
  G2P of the same particles otherwise compute the same weights twice.
  ``deepcontact.features.world_to_grids(..., return_plan=True)`` hands back
  the contact points' plan from the input splat, so the server's step
  computes them once.

Kernels (thesis eq. 5.2-5.4, 2-D, ``r`` the particle-node distance):

* ``poly6``:    W = 4 / (pi h^8) (h^2 - r^2)^3 for r <= h, else 0 (the default);
* ``spiky``:    W = 15 / (pi h^6) (h - r)^3 for r <= h, else 0 (the thesis's
  constant, which is the 3-D one; it cancels in the normalization);
* ``gaussian``: W = exp(-r^2 / (2 sigma^2)) / (2 pi sigma^2), sigma = h / 3,
  *truncated at r <= h*: the untruncated Gaussian reaches every node, the
  truncation keeps the support finite (the weight at r = h is exp(-4.5), about
  1 % of the peak).

Because weights are always normalized (per particle or per node), only the
kernel's shape matters: the fast path evaluates it as a function of
``m = 1 - (r/h)^2`` and :func:`kernel` gives the full formulas above.  A node
is "in range" of a particle when its weight is positive, so for poly6 and
spiky a node at exactly ``r = h`` (weight 0) is not in range.

Implementation: no Python loop over particles or nodes.  A particle is
anchored at its nearest node and can only touch the (2k+1)^2 nodes around it,
k = floor(h/dx + 1/2); anchors are moved inwards near the edges so that every
stencil lies on the grid (see :class:`_Stencil`), and the stencil's constants
are computed once per grid geometry and cached.  Weights form an (N, S) array
(particle x stencil entry) of flat node indices and weights.  The three inner
loops -- the weights, the P2G splat and the SPH G2P gather -- are compiled
(``deepcontact/_transfer.c``, built by ``make setup``): at the sizes used here
(a few hundred particles, 61 x 61 nodes) NumPy spent most of its time in
per-call overhead, and the server's step paid it again with cold caches after
every inference.  This module keeps the geometry, the checks and the reports;
the C code does arithmetic on arrays it is handed.  Sums are accumulated in
float64 and rounded to float32 once.

Bad input: NaN or infinite positions or values raise ValueError naming what
was bad; particles beyond the domain (by more than ``tolerance``) are counted
and either raise (``outside="raise"``, the default) or are left out
(``outside="drop"``); particles with no node in range are counted in the
:class:`TransferReport`.  Empty inputs give zero grids / empty arrays.

Units: positions in metres (world frame); values in the channel's unit.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple, Sequence

import numpy as np

from deepcontact.gridspec import KERNELS, GridSpec

try:
    from deepcontact import _transfer as _compiled
except ImportError as exc:  # pragma: no cover - a checkout that was never set up
    raise ImportError(
        "deepcontact's compiled transfer kernels (deepcontact/_transfer.c) are not built: "
        "run `make setup` (or `pip install -e .`)"
    ) from exc

__all__ = [
    "DOMAIN_TOLERANCE",
    "ParticleSet",
    "TransferPlan",
    "TransferReport",
    "channel_columns",
    "g2p",
    "kernel",
    "kernel_shape",
    "p2g",
    "p2g_batch",
    "p2g_sets",
    "plan",
]

#: Default slack, m, before a particle counts as outside the domain.  A contact
#: point against a wall is the midpoint of the two touching surfaces, so with
#: penetration it can sit a few millimetres past the wall plane.
DOMAIN_TOLERANCE = 0.01

_OUTSIDE_MODES = ("raise", "drop")
_G2P_METHODS = ("sph", "bilinear")

# x.all() runs a Python-level wrapper in NumPy; on the
# server's per-step path the ufunc reductions are called directly.
_all = functools.partial(np.logical_and.reduce, axis=None)


# --------------------------------------------------------------------------- #
# Kernels
# --------------------------------------------------------------------------- #


def kernel(r: np.ndarray, h: float, name: str = "poly6") -> np.ndarray:
    """Full kernel value W(r, h), thesis eq. 5.2-5.4, 2-D.

    ``r`` is a distance array in m (any shape), ``h`` the support radius in m;
    returns an array of the same shape in 1/m^2.  The Gaussian uses
    sigma = h/3 and is truncated at r <= h.
    """
    r = np.asarray(r, dtype=np.float64)
    inside = r <= h
    if name == "poly6":
        return np.where(inside, 4.0 / (math.pi * h**8) * (h * h - r * r) ** 3, 0.0)
    if name == "spiky":
        return np.where(inside, 15.0 / (math.pi * h**6) * (h - r) ** 3, 0.0)
    if name == "gaussian":
        sigma = h / 3.0
        return np.where(inside, np.exp(-(r * r) / (2 * sigma * sigma)) / (2 * math.pi * sigma * sigma), 0.0)
    raise ValueError(f"unknown kernel {name!r}; known kernels: {list(KERNELS)}")


def kernel_shape(q2: np.ndarray, name: str = "poly6") -> np.ndarray:
    """Kernel up to a constant factor, as a function of ``q2 = (r / h)^2``.

    Proportional to :func:`kernel` (the factor cancels in the normalization);
    zero for ``q2 > 1`` (poly6, spiky) and truncated there (gaussian).
    """
    if name not in _KERNEL_IDS:
        raise ValueError(f"unknown kernel {name!r}; known kernels: {list(KERNELS)}")
    m = np.ascontiguousarray(1.0 - np.asarray(q2, dtype=np.float64))
    out = np.empty_like(m)
    _compiled.shape(m, _KERNEL_IDS[name], out)
    return out


_KERNEL_IDS = {"poly6": _compiled.POLY6, "spiky": _compiled.SPIKY, "gaussian": _compiled.GAUSSIAN}
if set(KERNELS) != set(_KERNEL_IDS):  # keep gridspec's list and this module in step
    raise ImportError("deepcontact.gridspec.KERNELS and deepcontact.transfer disagree")


# --------------------------------------------------------------------------- #
# Report
# --------------------------------------------------------------------------- #


class TransferReport:
    """What a transfer did with each particle.

    Attributes
    ----------
    n_particles:
        Particles passed in.
    outside, n_outside:
        Indices (int64, into the input particles) and number of particles
        beyond the domain by more than the tolerance (raised on, or left out
        with ``outside="drop"``).
    lost, n_lost:
        P2G: particles inside the domain with no node in range; their values
        are not on the grid.  G2P: particles inside the domain that received
        nothing (no node in range for SPH); their values are 0.
    lost_value:
        (C,) float64, per channel, value that did not make it across: the
        values of lost and dropped particles (P2G), or the node values with no
        particle in range (SPH G2P; 0 for bilinear).
    n_nodes_lost:
        SPH G2P only: nodes with a non-zero value and no particle in range.
    n_transferred:
        Particles that took part: neither outside nor lost.

    The SPH G2P diagnostics (``lost``, ``lost_value``, ``n_nodes_lost``) are
    computed on first access, from private copies, so they describe the
    transfer as it happened; computing them eagerly cost about 10 % of a G2P
    call that the server makes every step.
    """

    __slots__ = ("n_particles", "outside", "_lost", "_lost_value", "_n_nodes_lost", "_pending")

    def __init__(self, n_particles, outside, lost=None, lost_value=None, n_nodes_lost=0, *, pending=None):
        self.n_particles = int(n_particles)
        self.outside = outside
        self._lost = lost
        self._lost_value = lost_value
        self._n_nodes_lost = int(n_nodes_lost)
        # pending() -> (lost, lost_value, n_nodes_lost), called once, on first access.
        self._pending = pending

    def _resolve(self) -> None:
        if self._pending is not None:
            lost, lost_value, n_nodes_lost = self._pending()
            self._lost, self._lost_value, self._n_nodes_lost = lost, lost_value, int(n_nodes_lost)
            self._pending = None

    @property
    def lost(self) -> np.ndarray:
        self._resolve()
        return self._lost

    @property
    def lost_value(self) -> np.ndarray:
        self._resolve()
        return self._lost_value

    @property
    def n_nodes_lost(self) -> int:
        self._resolve()
        return self._n_nodes_lost

    @property
    def n_outside(self) -> int:
        return len(self.outside)

    @property
    def n_lost(self) -> int:
        return len(self.lost)

    @property
    def n_transferred(self) -> int:
        return self.n_particles - self.n_outside - self.n_lost

    def to_dict(self) -> dict:
        """Counts, indices and lost values as plain Python values (JSON-able)."""
        return {
            "n_particles": self.n_particles,
            "n_outside": self.n_outside,
            "n_lost": self.n_lost,
            "outside": self.outside.tolist(),
            "lost": self.lost.tolist(),
            "lost_value": self.lost_value.tolist(),
            "n_nodes_lost": self.n_nodes_lost,
        }

    def __repr__(self) -> str:
        return (
            f"TransferReport(n_particles={self.n_particles}, n_outside={self.n_outside}, n_lost={self.n_lost}, "
            f"lost_value={self.lost_value.tolist()}, n_nodes_lost={self.n_nodes_lost})"
        )


_NO_INDEX = np.zeros(0, dtype=np.int64)
_NO_INDEX.flags.writeable = False


# --------------------------------------------------------------------------- #
# Stencil
# --------------------------------------------------------------------------- #


@dataclass(frozen=True)
class _Stencil:
    """Per-geometry constants, computed once per grid geometry and cached.

    A particle's stencil is a window of K x K nodes around its anchor node,
    K = 2k+1, k = floor(h/dx + 1/2): a particle within half a node of its
    nearest node reaches no node farther than k nodes from it along x or y.
    Anchors are clamped to [k, n-1-k] per axis, so every window lies on the
    grid: near an edge the window shifts inwards and still covers every node
    in range (those past the edge are not nodes), and particles slightly
    outside the domain are handled alike.  So no stencil entry ever leaves
    the grid -- no padding, no bounds checks, no masking -- and nodes of the
    window out of range simply get weight 0 from the kernel.  (An axis with
    fewer than K nodes gets a window of all its nodes, completed to K with
    entries at an infinite offset, which get weight 0.)
    """

    ny: int
    nx: int
    o_h: np.ndarray  # (2, K) window offsets per axis (x, y) from the anchor, in units of h (inf: none)
    flat_off: np.ndarray  # (S,) int32 flat offsets oy * nx + ox of the entries, S = K^2 in (ky, kx) order
    # (origin x, origin y (m), 1/resolution (1/m), resolution/h, lowest anchor x, y,
    # highest anchor x, y, nx): the compiled kernel's view of the geometry.
    params: tuple

    @property
    def cells(self) -> int:
        """Nodes in the grid (flat indices run over 0..cells-1)."""
        return self.ny * self.nx

    @property
    def n_stencil(self) -> int:
        """S, stencil entries per particle."""
        return self.flat_off.shape[0]


def _window(n: int, k: int, scale: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """One axis of the window: (offsets in units of h (K,), node offsets (K,) int,
    lowest anchor, highest anchor), for an axis of n nodes."""
    size = 2 * k + 1
    if n >= size:
        o = np.arange(-k, k + 1)
        return o * scale, o, k, n - 1 - k
    # Fewer nodes than the window: all of them, around a fixed anchor, and
    # size - n unused entries (node offset 0, an existing node; weight 0).
    lo = (n - 1) // 2
    o = np.arange(-lo, n - lo)
    o_h = np.concatenate([o * scale, np.full(size - n, np.inf)])
    return o_h, np.concatenate([o, np.zeros(size - n, dtype=o.dtype)]), lo, lo


@lru_cache(maxsize=64)
def _stencil(origin: tuple[float, float], shape: tuple[int, int], resolution: float, h: float) -> _Stencil:
    r = h / resolution  # support radius in node units
    # A particle is at most half a node from its anchor along each axis, so
    # every node within r of it is within r + 1/2 of the anchor along x and y.
    k = int(math.floor(r + 0.5 + 1e-9))
    ny, nx = shape
    scale = resolution / h
    ox_h, ox, x_lo, x_hi = _window(nx, k, scale)
    oy_h, oy, y_lo, y_hi = _window(ny, k, scale)
    flat = oy[:, None] * nx + ox[None, :]  # (Ky, Kx)
    st = _Stencil(
        ny=ny,
        nx=nx,
        o_h=np.ascontiguousarray(np.stack([ox_h, oy_h]), dtype=np.float64),
        flat_off=np.ascontiguousarray(flat.reshape(-1), dtype=np.int32),
        params=(float(origin[0]), float(origin[1]), 1.0 / resolution, scale,
                float(x_lo), float(y_lo), float(x_hi), float(y_hi), nx),
    )
    for a in (st.o_h, st.flat_off):
        a.flags.writeable = False
    return st


def _stencil_for(spec: GridSpec) -> _Stencil:
    return _stencil(spec.origin, spec.shape, spec.resolution, spec.h)


class _Entries(NamedTuple):
    """The stencil entries of M particles, particle-major: row n is particle n.

    These are what P2G and SPH G2P share: computed once, they serve both
    directions (see :class:`TransferPlan`).
    """

    nodes: np.ndarray  # (M, S) int32 flat node index (plus the world's offset in a batch)
    weights: np.ndarray  # (M, S) float64 unnormalized kernel weights, 0 out of range
    lost: np.ndarray  # (M,) bool: no node in range (all weights 0)
    divisor: np.ndarray  # (M,) float64 per-particle weight total, 1 for lost particles

    def particles(self, start: int, stop: int) -> "_Entries":
        """The entries of particles [start, stop) (views, still C-contiguous)."""
        return _Entries(
            self.nodes[start:stop], self.weights[start:stop], self.lost[start:stop], self.divisor[start:stop]
        )


def _stencil_entries(pos: np.ndarray, spec: GridSpec, st: _Stencil, world_of=None,
                     tolerance: float = DOMAIN_TOLERANCE) -> tuple[_Entries, int]:
    """Stencil entries of ``pos`` (M, 2) float64 m; ``world_of`` None or (M,)
    int world per particle (world b's nodes start at ``b * st.cells``).

    Also returns how many particles are not finite or beyond the domain by
    more than ``tolerance`` (their weights are finite, and meaningless).
    """
    n = len(pos)
    nodes = np.empty((n, st.n_stencil), dtype=np.int32)
    weights = np.empty((n, st.n_stencil))
    lost = np.empty(n, dtype=bool)
    divisor = np.empty(n)
    offsets = None if world_of is None else np.multiply(world_of, st.cells, dtype=np.int32)
    n_outside = _compiled.entries(np.ascontiguousarray(pos, dtype=np.float64), offsets, st.o_h, st.flat_off,
                                  st.params, _KERNEL_IDS[spec.kernel], _bounds(spec, tolerance).box,
                                  nodes, weights, lost, divisor)
    return _Entries(nodes, weights, lost, divisor), n_outside


def _splat_grids(e: _Entries, values: np.ndarray, st: _Stencil, batch: int) -> np.ndarray | None:
    """P2G of ``values`` (M, C) with entries ``e``: (batch, ny, nx, C) float32,
    or None if some value is not finite.

    Each particle's values are divided by its weight total, which normalizes
    Algorithm 1's weights without touching them.
    """
    m = len(e.divisor)
    n_channels = values.shape[1]
    if m == 0 or n_channels == 0:
        return np.zeros((batch, st.ny, st.nx, n_channels), dtype=np.float32)
    grids = np.empty((batch, st.ny, st.nx, n_channels), dtype=np.float32)
    finite = _compiled.splat(e.nodes, e.weights, e.divisor, np.ascontiguousarray(values, dtype=np.float64),
                             batch * st.cells, grids)
    return grids if finite else None


# --------------------------------------------------------------------------- #
# Validation
# --------------------------------------------------------------------------- #


def _as_positions(positions, name: str) -> np.ndarray:
    pos = np.asarray(positions, dtype=np.float64)
    if pos.size == 0:
        return pos.reshape(0, 2)
    if pos.ndim != 2 or pos.shape[1] != 2:
        raise ValueError(f"{name} must have shape (N, 2), got {pos.shape}")
    return pos


def _as_values(values, n: int, name: str) -> np.ndarray:
    """(N, C) float64; finiteness is checked later, once for all particle sets."""
    vals = np.asarray(values, dtype=np.float64)
    if vals.ndim == 1:
        vals = vals[:, None]
    if vals.ndim != 2 or vals.shape[0] != n:
        raise ValueError(f"{name} must have shape (N, C) with N = {n} particles, got {np.shape(values)}")
    return vals


def _check_finite_values(vals: np.ndarray, label: str, names: Sequence[str] | None) -> None:
    if np.isfinite(vals).all():
        return
    bad = ~np.isfinite(vals)
    rows = np.flatnonzero(bad.any(axis=1))
    cols = np.flatnonzero(bad.any(axis=0))
    what = [names[c] for c in cols] if names else cols.tolist()
    raise ValueError(f"{label} values contain NaN or infinite values (particles {rows[:10].tolist()}, channels {what})")


def _check_grid(grid, spec: GridSpec, finite: bool = True) -> np.ndarray:
    """``grid`` as (ny, nx, C); ValueError for another shape, and, with
    ``finite``, for NaN or infinite values (SPH G2P checks those itself)."""
    g = np.asarray(grid)
    if g.ndim == 2:
        g = g[:, :, None]
    if g.ndim != 3 or g.shape[:2] != spec.shape:
        raise ValueError(f"grid must have shape (ny, nx, C) = ({spec.ny}, {spec.nx}, C), got {np.shape(grid)}")
    if finite and not _all(np.isfinite(g)):
        _raise_not_finite(g)
    return g


def _raise_not_finite(g: np.ndarray) -> None:
    bad = np.argwhere(~np.isfinite(g))[0]
    raise ValueError(f"grid contains NaN or infinite values (e.g. node (iy, ix) = ({bad[0]}, {bad[1]}), channel {bad[2]})")


def _check_mode(outside: str, tolerance: float) -> None:
    if outside not in _OUTSIDE_MODES:
        raise ValueError(f"outside must be one of {list(_OUTSIDE_MODES)}, got {outside!r}")
    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be a finite distance >= 0 m, got {tolerance!r}")


class _Bounds:
    """The accepted region: the domain grown by the tolerance, corners ``lo``, ``hi`` (2,) m."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray):
        self.lo, self.hi = lo, hi
        self.box = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))  # for the compiled kernel
        # lo and hi repeated (x, y, x, y, ...), grown as needed: comparing the
        # flat (2N,) positions with them runs one long loop, where broadcasting
        # against (2,) runs N loops of two (about twice as slow).  One tuple,
        # replaced whole, so concurrent callers never see a mismatched pair.
        self._tiles = (lo, hi)

    def inside(self, pos: np.ndarray) -> np.ndarray:
        """(N, 2) bool, per coordinate: within the accepted region (False for NaN).

        Plain comparisons, so a particle exactly on an edge or corner is
        inside even with zero tolerance.
        """
        inside = pos >= self.lo
        inside &= pos <= self.hi
        return inside

    def all_inside(self, pos: np.ndarray) -> bool:
        """Are all of ``pos`` (N, 2) inside?  One pass answers two questions in the
        common case: NaN fails every comparison, so "all inside" also means "all finite"."""
        flat = pos.reshape(-1)
        lo_t, hi_t = self._tiles
        if len(lo_t) < len(flat):
            reps = max(len(flat), 2 * len(lo_t)) // 2
            lo_t, hi_t = np.tile(self.lo, reps), np.tile(self.hi, reps)
            lo_t.flags.writeable = hi_t.flags.writeable = False
            self._tiles = (lo_t, hi_t)
        inside = flat >= lo_t[: len(flat)]
        inside &= flat <= hi_t[: len(flat)]
        return bool(_all(inside))


def _bounds(spec: GridSpec, tolerance: float) -> _Bounds:
    """The accepted region for ``spec`` and ``tolerance``."""
    return _bounds_cached(spec.origin, spec.upper, float(tolerance))


@lru_cache(maxsize=64)
def _bounds_cached(origin, upper, tolerance) -> _Bounds:
    lo = np.array([origin[0] - tolerance, origin[1] - tolerance])
    hi = np.array([upper[0] + tolerance, upper[1] + tolerance])
    lo.flags.writeable = hi.flags.writeable = False
    return _Bounds(lo, hi)


def _split_outside(pos: np.ndarray, spec: GridSpec, outside: str, tolerance: float, label: str):
    """Check positions are finite and inside the domain (+ tolerance).

    Returns (positions kept, kept indices or None when all are kept, outside
    indices).  Raises ValueError for NaN/inf, and for particles outside when
    ``outside == "raise"``.
    """
    bounds = _bounds(spec, tolerance)
    if bounds.all_inside(pos):
        return pos, None, _NO_INDEX
    finite = np.isfinite(pos).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise ValueError(f"{label} positions contain NaN or infinite values (particles {bad[:10].tolist()})")
    inside = bounds.inside(pos).all(axis=1)
    out_idx = np.flatnonzero(~inside)
    if outside == "raise":
        up = spec.upper
        raise ValueError(
            f"{len(out_idx)} {label} outside the grid domain x in [{spec.origin[0]}, {up[0]}], "
            f"y in [{spec.origin[1]}, {up[1]}] (tolerance {tolerance} m), e.g. #{out_idx[0]} at "
            f"{pos[out_idx[0]].tolist()}; pass outside='drop' to leave them out"
        )
    keep = np.flatnonzero(inside)
    return pos[keep], keep, out_idx


# --------------------------------------------------------------------------- #
# P2G
# --------------------------------------------------------------------------- #


class ParticleSet(NamedTuple):
    """One set of particles: rows ``start:stop`` of the stacked positions and
    values, splatted into channels ``cols`` of world ``world``'s grid."""

    world: int
    cols: slice | list[int]  # output channels: a slice when contiguous, else a list
    start: int
    stop: int
    label: str  # names the particles in errors: "bodies", "contacts", "particles", ...
    names: Sequence[str] | None = None  # channel names, for errors

    @property
    def width(self) -> int:
        """Number of channels."""
        return self.cols.stop - self.cols.start if isinstance(self.cols, slice) else len(self.cols)


def channel_columns(cols: Sequence[int]) -> slice | list[int]:
    """A slice for a contiguous run of columns (cheaper to index with), else the list."""
    cols = list(cols)
    if cols == list(range(cols[0], cols[-1] + 1)):
        return slice(cols[0], cols[-1] + 1)
    return cols


def p2g_sets(
    pos: np.ndarray,
    values: np.ndarray,
    sets: Sequence[ParticleSet],
    spec: GridSpec,
    batch: int,
    outside: str,
    tolerance: float,
    plan_set: int | None = None,
    reports: bool = True,
):
    """Shared P2G engine: splat every set into ``grids[set.world][..., set.cols]``.

    ``pos`` (N, 2) float64 m and ``values`` (N, C) float64 stack the
    particles of every set (a set's rows hold zeros outside its channels).
    One weight computation and one sparse product cover all sets.  Returns
    ``(grids (B, ny, nx, C) float32, reports, plan)`` with ``reports[b]`` a
    list of the reports of world b's sets, in order (None unless
    ``reports``), and ``plan`` the :class:`TransferPlan` of set
    ``sets[plan_set]`` (sharing the weights computed here; one world only),
    or None.
    """
    _check_mode(outside, tolerance)
    st = _stencil_for(spec)
    if batch * st.cells >= 2**31:
        raise ValueError(f"a batch of {batch} grids is too large for one transfer; split it")
    sizes = [s.stop - s.start for s in sets]
    world_of = np.repeat(np.array([s.world for s in sets], dtype=np.intp), sizes) if batch > 1 else None
    # The common case in one pass each: the weights count the particles that
    # are not finite or outside, the splat says whether every value is finite.
    e, n_outside = _stencil_entries(pos, spec, st, world_of, tolerance)
    grids = _splat_grids(e, values, st, batch) if n_outside == 0 else None
    kept = None  # per set (kept indices or None for all, outside indices), on the careful path
    if grids is None:
        e, kept, sizes, rows = _entries_of_kept(pos, values, sets, spec, st, batch, outside, tolerance)
        grids = _splat_grids(e, values[rows], st, batch)

    plan_ = None
    if plan_set is not None:
        s, start = sets[plan_set], sum(sizes[:plan_set])
        keep, out_idx = (None, _NO_INDEX) if kept is None else kept[plan_set]
        plan_ = TransferPlan(spec, s.stop - s.start, keep, out_idx, e.particles(start, start + sizes[plan_set]))
    if not reports:
        return grids, None, plan_
    return grids, _reports_by_world(e, values, sets, sizes, kept, batch), plan_


def _entries_of_kept(
    pos: np.ndarray, values: np.ndarray, sets: Sequence[ParticleSet], spec: GridSpec, st, batch: int,
    outside: str, tolerance: float,
):
    """The careful path of :func:`p2g_sets`: find what is wrong, raise or drop it.

    Returns ``(entries, kept, sizes, rows)``: the stencil entries of the
    kept particles only, ``kept[j]`` = (kept indices within set j or None
    for all, indices outside the grid), ``sizes[j]`` the number kept, and
    ``rows`` the kept particles' rows of ``pos`` and ``values``.
    Dropped particles' values are checked too: they go into ``lost_value``.
    """
    kept = []
    for s in sets:
        _check_finite_values(values[s.start : s.stop, s.cols], s.label, s.names)
        _, keep, out_idx = _split_outside(pos[s.start : s.stop], spec, outside, tolerance, s.label)
        kept.append((keep, out_idx))
    rows = np.concatenate(
        [np.arange(s.start, s.stop) if k is None else s.start + k for s, (k, _) in zip(sets, kept)]
    )
    sizes = [s.stop - s.start if k is None else len(k) for s, (k, _) in zip(sets, kept)]
    world_of = np.repeat(np.array([s.world for s in sets], dtype=np.intp), sizes) if batch > 1 else None
    e, _ = _stencil_entries(pos[rows], spec, st, world_of, tolerance)
    return e, kept, sizes, rows


def _reports_by_world(
    e, values: np.ndarray, sets: Sequence[ParticleSet], sizes: list[int], kept, batch: int
) -> list[list[TransferReport]]:
    """``reports[b]``: the :class:`TransferReport` of each of world b's sets, in order.

    Cheap unless some particles are lost or outside (``kept`` is None when
    none is outside; ``sizes[j]`` counts set j's kept particles).
    """
    any_lost = bool(e.lost.any())
    per_world: list[list[TransferReport]] = [[] for _ in range(batch)]
    start = 0
    for j, (s, size) in enumerate(zip(sets, sizes)):
        n = s.stop - s.start
        if any_lost or kept is not None:
            keep, out_idx = (None, _NO_INDEX) if kept is None else kept[j]
            lost_local = e.lost[start : start + size] if any_lost else None
            report = _lost_report(n, keep, out_idx, lost_local, values[s.start : s.stop, s.cols])
        else:
            report = TransferReport(n, _NO_INDEX, _NO_INDEX, np.zeros(s.width))
        per_world[s.world].append(report)
        start += size
    return per_world


def _lost_report(n: int, keep, out_idx, lost_local: np.ndarray | None, vals: np.ndarray) -> TransferReport:
    """Report for one particle set; ``lost_local`` indexes the kept particles (None: none lost)."""
    lost_idx = _NO_INDEX
    if lost_local is not None and lost_local.any():
        lost_idx = np.flatnonzero(lost_local)
        if keep is not None:
            lost_idx = keep[lost_idx]
    if len(lost_idx) or len(out_idx):
        lost_value = vals[lost_idx].sum(axis=0) + vals[out_idx].sum(axis=0)
    else:
        lost_value = np.zeros(vals.shape[1])
    return TransferReport(n, out_idx, lost_idx, lost_value)


def p2g(
    positions,
    values,
    spec: GridSpec,
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> tuple[np.ndarray, TransferReport]:
    """Splat particle values onto the grid (thesis Algorithm 1).

    Parameters
    ----------
    positions:
        (N, 2) particle positions (x, y), m, world frame.
    values:
        (N, C) per-particle values (or (N,) for one channel), any unit.
    spec:
        Grid geometry and kernel.
    outside:
        ``"raise"`` (default): ValueError if a particle lies beyond the domain
        by more than ``tolerance``; ``"drop"``: leave such particles out and
        count them in the report.
    tolerance:
        Slack, m, before a particle counts as outside.

    Returns
    -------
    grid:
        (ny, nx, C) float32; per channel, ``grid.sum() == values.sum()`` over
        the particles that are neither outside nor lost.
    report:
        :class:`TransferReport` (lost = particles with no node in range).

    To transfer back to the same particles, :func:`plan` computes the kernel
    weights once for both directions.
    """
    grids, reports = p2g_batch([positions], [values], spec, outside=outside, tolerance=tolerance)
    return grids[0], reports[0]


def p2g_batch(
    positions: Sequence,
    values: Sequence,
    spec: GridSpec,
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> tuple[np.ndarray, list[TransferReport]]:
    """:func:`p2g` over several worlds at once, stacked as (B, ny, nx, C) float32.

    ``positions[b]`` is (N_b, 2) m and ``values[b]`` (N_b, C) with the same C
    for every world.  Small worlds share one weight computation and one
    sparse product.  Returns the grids and one report per world.
    """
    if len(positions) != len(values):
        raise ValueError(f"positions and values list different numbers of worlds: {len(positions)} != {len(values)}")
    if len(positions) == 0:
        raise ValueError("p2g_batch needs at least one world")
    sets, all_pos, all_vals = [], [], []
    start = 0
    for b, (p, v) in enumerate(zip(positions, values)):  # loop over worlds
        label = f"world {b} particles" if len(positions) > 1 else "particles"
        pos = _as_positions(p, label + " positions")
        vals = _as_values(v, len(pos), label + " values")
        if all_vals and vals.shape[1] != all_vals[0].shape[1]:
            raise ValueError(f"world {b} has {vals.shape[1]} value channels, world 0 has {all_vals[0].shape[1]}")
        sets.append(ParticleSet(b, slice(0, vals.shape[1]), start, start + len(pos), label))
        all_pos.append(pos)
        all_vals.append(vals)
        start += len(pos)
    grids, reports, _ = p2g_sets(
        np.concatenate(all_pos), np.concatenate(all_vals), sets, spec, len(sets), outside, tolerance
    )
    return grids, [r for (r,) in reports]


# --------------------------------------------------------------------------- #
# G2P
# --------------------------------------------------------------------------- #


def g2p(
    grid,
    positions,
    spec: GridSpec,
    method: str = "sph",
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> tuple[np.ndarray, TransferReport]:
    """Transfer grid values to particles.

    Parameters
    ----------
    grid:
        (ny, nx, C) node values (or (ny, nx) for one channel).
    positions:
        (M, 2) particle positions (x, y), m, world frame.
    method:
        ``"sph"`` (thesis Algorithm 2, default): each node distributes its
        value over the particles within ``h`` with weights normalized per
        node, so the particle total equals the total of the nodes that have a
        particle in range.  ``"bilinear"`` (thesis §5.4.1): interpolate the
        four surrounding nodes (exact for fields linear in x and y).
    outside, tolerance:
        As in :func:`p2g`; dropped particles get 0.

    Returns
    -------
    values:
        (M, C) float32 per-particle values.
    report:
        :class:`TransferReport`; ``lost`` = particles with no node in range
        (value 0), ``n_nodes_lost``/``lost_value`` = nodes (and their
        per-channel total) that had no particle in range.
    """
    if method not in _G2P_METHODS:
        raise ValueError(f"method must be one of {list(_G2P_METHODS)}, got {method!r}")
    _check_mode(outside, tolerance)
    g = _check_grid(grid, spec, finite=method != "sph")
    if method == "sph":
        return plan(positions, spec, outside=outside, tolerance=tolerance)._g2p(g)
    n_channels = g.shape[2]
    pos = _as_positions(positions, "positions")
    n = len(pos)
    pos_in, keep, out_idx = _split_outside(pos, spec, outside, tolerance, "particles")
    vals = _g2p_bilinear(g, pos_in, spec)
    report = TransferReport(n, out_idx, _NO_INDEX, np.zeros(n_channels))
    if keep is not None:
        full = np.zeros((n, n_channels), dtype=np.float32)
        full[keep] = vals
        vals = full
    return vals, report


def _g2p_sph(g: np.ndarray, e: _Entries, st: _Stencil):
    """SPH G2P (Algorithm 2) from ``g`` (ny, nx, C) to the M particles of entries ``e``.

    Returns ``(values (M, C) float32, diagnose)``; ``diagnose()`` gives
    ``(lost mask (M,), lost node value (C,) float64, lost node count)``.
    """
    ny, nx, n_channels = g.shape
    m = len(e.divisor)
    if m == 0 or n_channels == 0:  # every node is lost
        if not _all(np.isfinite(g)):
            _raise_not_finite(g)
        out = np.zeros((m, n_channels), dtype=np.float32)
        nodes_lost = int(np.count_nonzero(np.abs(g).sum(axis=2))) if n_channels else 0
        lost_value = g.reshape(-1, n_channels).sum(axis=0, dtype=np.float64)
        return out, lambda: (e.lost, lost_value, nodes_lost)
    if g.dtype != np.float32:
        g = g.astype(np.float64, copy=False)
    g = np.ascontiguousarray(g)
    out = np.empty((m, n_channels), dtype=np.float32)
    node_w = np.empty(st.cells)  # per node, the weight total of the particles in range
    kept = np.empty_like(g)  # the grid as it was, for the report
    if not _compiled.gather(e.nodes, e.weights, g, g.dtype == np.float64, out, node_w, kept):
        _raise_not_finite(g)

    def diagnose():
        unreached = kept.reshape(st.cells, n_channels)[node_w <= 0.0].astype(np.float64)
        return e.lost, unreached.sum(axis=0), np.count_nonzero(np.abs(unreached).sum(axis=1))

    return out, diagnose


def _g2p_bilinear(g: np.ndarray, pos: np.ndarray, spec: GridSpec) -> np.ndarray:
    ny, nx, n_channels = g.shape
    if ny < 2 or nx < 2:
        raise ValueError(f"bilinear G2P needs at least 2 x 2 nodes, grid is {ny} x {nx}")
    out = np.empty((len(pos), n_channels), dtype=np.float32)
    if len(pos) == 0:
        return out
    u = (pos.T - np.reshape(spec.origin, (2, 1))) * (1.0 / spec.resolution)  # (2, M) node units
    # Lower-left node of the cell; clipping keeps points on (or within the
    # tolerance past) the last row/column in the last cell, where t <= 1 (or
    # slightly beyond: linear extrapolation over the tolerance).
    i = np.clip(np.floor(u), 0, [[nx - 2], [ny - 2]])
    tx, ty = u - i
    k = (i[1] * nx + i[0]).astype(np.intp)
    flat = g.reshape(ny * nx, n_channels)
    w00, w10, w01, w11 = (1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty
    for c in range(n_channels):  # loop over channels
        f = flat[:, c]
        out[:, c] = w00 * f[k] + w10 * f[k + 1] + w01 * f[k + nx] + w11 * f[k + nx + 1]
    return out


# --------------------------------------------------------------------------- #
# Plans: one weight computation for P2G and G2P
# --------------------------------------------------------------------------- #


class TransferPlan:
    """The stencil weights of a fixed set of particles on one grid, computed once.

    P2G (:func:`p2g`) and SPH G2P (:func:`g2p`) of the same particles need
    the same kernel weights -- the most expensive part of either.  A plan
    computes them once, for any number of transfers in either direction::

        pl = plan(positions, spec, outside="drop")   # (N, 2) m
        grid, report = pl.p2g(values)                # (N, C) -> (ny, nx, C) float32
        back, report = pl.g2p(grid)                  # (ny, nx, C) -> (N, C) float32

    Results equal :func:`p2g` and :func:`g2p` (``method="sph"``) called with
    the same positions, ``outside`` and ``tolerance``.  A plan does not keep
    the positions; it holds about 12 bytes per particle and stencil entry.
    :func:`deepcontact.features.world_to_grids` with ``return_plan=True``
    gives the plan of a world's contact points as a by-product of the input
    splat.

    Attributes
    ----------
    spec:
        The grid.
    n_particles:
        N, particles passed in.
    outside:
        (int64) indices of the particles beyond the domain by more than the
        tolerance (only with ``outside="drop"``): they take no part.
    """

    __slots__ = ("spec", "n_particles", "outside", "_keep", "_entries", "_st")

    def __init__(self, spec: GridSpec, n_particles: int, keep, outside: np.ndarray, entries: _Entries):
        self.spec = spec
        self.n_particles = int(n_particles)
        self.outside = outside
        self._keep = keep  # indices of the particles taking part, or None for all
        self._entries = entries  # of the kept particles, in order
        self._st = _stencil_for(spec)

    def p2g(self, values) -> tuple[np.ndarray, TransferReport]:
        """:func:`p2g` of ``values`` (N, C) (or (N,)): ``(grid (ny, nx, C) float32, report)``."""
        vals = _as_values(values, self.n_particles, "particles values")
        _check_finite_values(vals, "particles", None)
        kept = vals if self._keep is None else vals[self._keep]
        grid = _splat_grids(self._entries, kept, self._st, 1)[0]
        return grid, _lost_report(self.n_particles, self._keep, self.outside, self._entries.lost, vals)

    def g2p(self, grid) -> tuple[np.ndarray, TransferReport]:
        """SPH :func:`g2p` of ``grid`` (ny, nx, C) (or (ny, nx)): ``(values (N, C) float32, report)``."""
        return self._g2p(_check_grid(grid, self.spec, finite=False))

    def _g2p(self, g: np.ndarray) -> tuple[np.ndarray, TransferReport]:
        vals, diagnose = _g2p_sph(g, self._entries, self._st)
        keep = self._keep

        def pending():
            lost_mask, lost_value, nodes_lost = diagnose()
            lost_idx = np.flatnonzero(lost_mask)
            return (lost_idx if keep is None else keep[lost_idx]), lost_value, nodes_lost

        report = TransferReport(self.n_particles, self.outside, pending=pending)
        if keep is not None:
            full = np.zeros((self.n_particles, g.shape[2]), dtype=np.float32)
            full[keep] = vals
            vals = full
        return vals, report

    def g2p_operator(self) -> tuple[np.ndarray, np.ndarray]:
        """SPH G2P as a sparse linear map, for frameworks that differentiate through it.

        Returns ``(nodes (N, S) int32, weights (N, S) float32)`` such that
        ``g2p(grid)[n] = sum_s weights[n, s] * grid.reshape(-1, C)[nodes[n, s]]``
        (flat node index iy * nx + ix); particles that take no part (outside,
        or no node in range) have all-zero weights.
        """
        e, st = self._entries, self._st
        node_w = np.bincount(e.nodes.ravel(), e.weights.ravel(), minlength=st.cells)
        per_node = node_w[e.nodes]
        w = np.divide(e.weights, per_node, out=np.zeros_like(e.weights), where=per_node > 0)
        nodes = np.zeros((self.n_particles, st.n_stencil), np.int32)
        weights = np.zeros((self.n_particles, st.n_stencil), np.float32)
        rows = slice(None) if self._keep is None else self._keep
        nodes[rows], weights[rows] = e.nodes, w
        return nodes, weights

    def rows(self, start: int, stop: int) -> "TransferPlan":
        """The plan of particles ``start:stop`` alone (sharing this plan's weights).

        For example, a plan of bodies and contact points together splats both,
        and ``rows`` of the contact points transfers back to them alone.
        """
        start, stop, _ = slice(start, stop).indices(self.n_particles)
        stop = max(start, stop)
        if self._keep is None:
            r0, r1, keep = start, stop, None
        else:
            r0, r1 = np.searchsorted(self._keep, [start, stop])
            keep = self._keep[r0:r1] - start
        out = self.outside[(self.outside >= start) & (self.outside < stop)] - start
        return TransferPlan(self.spec, stop - start, keep, out, self._entries.particles(int(r0), int(r1)))

    def __repr__(self) -> str:
        return f"TransferPlan(n_particles={self.n_particles}, n_outside={len(self.outside)}, grid={self.spec.shape})"


def plan(
    positions,
    spec: GridSpec,
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> TransferPlan:
    """The :class:`TransferPlan` of particles at ``positions`` (N, 2) m on ``spec``'s grid.

    ``outside`` and ``tolerance`` are as in :func:`p2g` (checked here, once:
    NaN or infinite positions raise ValueError, and so do particles beyond
    the domain unless ``outside="drop"``).
    """
    _check_mode(outside, tolerance)
    pos = _as_positions(positions, "positions")
    pos_in, keep, out_idx = _split_outside(pos, spec, outside, tolerance, "particles")
    entries, _ = _stencil_entries(pos_in, spec, _stencil_for(spec), None, tolerance)
    return TransferPlan(spec, len(pos), keep, out_idx, entries)
