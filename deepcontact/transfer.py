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
* :func:`world_to_grids` / :func:`targets_to_grids` build the CNN's input and
  target grids from the engine's structured arrays, channel by channel as
  listed in the :class:`~deepcontact.gridspec.GridSpec`.

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
k = floor(h/dx + 1/2); the stencil's constants are computed once per grid
geometry and cached.  Weights form an (S, N) array (stencil entry x particle)
indexing a grid padded by k + 1 nodes, so no bounds checks are needed (the
padding gets weight 0 and is cropped off).  P2G scatters all channels with one
sparse (nodes x particles) product; SPH G2P sums weights per node with
``np.bincount``, divides each weight by its node's sum, and gathers with the
transposed product.  At the
sizes used here (a few hundred particles, 61 x 61 nodes) the cost is mostly
per NumPy call, so the code keeps the number of calls small; large inputs are
processed in chunks whose temporaries stay around 128 KiB, because larger
short-lived allocations are returned to the OS and page-faulted back in on
every call.

Bad input: NaN or infinite positions or values raise ValueError naming what
was bad; particles beyond the domain (by more than ``tolerance``) are counted
and either raise (``outside="raise"``, the default) or are left out
(``outside="drop"``); particles with no node in range are counted in the
:class:`TransferReport`.  Empty inputs give zero grids / empty arrays.

Units: positions in metres (world frame); values in the channel's unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple, Sequence

import numpy as np
from scipy import sparse

from deepcontact.gridspec import CHANNELS, KERNELS, SOURCES, GridSpec, channel_values

__all__ = [
    "DOMAIN_TOLERANCE",
    "TransferReport",
    "g2p",
    "kernel",
    "kernel_shape",
    "p2g",
    "p2g_batch",
    "targets_to_grids",
    "world_to_grids",
    "worlds_to_grids",
]

#: Default slack, m, before a particle counts as outside the domain.  A contact
#: point against a wall is the midpoint of the two touching surfaces, so with
#: penetration it can sit a few millimetres past the wall plane.
DOMAIN_TOLERANCE = 0.01

_OUTSIDE_MODES = ("raise", "drop")
_G2P_METHODS = ("sph", "bilinear")

#: Stencil entries (S x N) per chunk: float64 temporaries of about 128 KiB.
_CHUNK_ENTRIES = 16384


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
    return _shape_of_m(1.0 - np.asarray(q2, dtype=np.float64), name)


def _shape_of_m(m: np.ndarray, name: str) -> np.ndarray:
    """Kernel shape as a function of ``m = 1 - (r/h)^2``, in ``m``'s dtype.

    The fast path builds ``m`` directly (see :func:`_weights`); ``m`` is
    overwritten.  ``m <= 0`` means out of range.
    """
    if name == "poly6":
        np.maximum(m, 0.0, out=m)
        w = m * m
        w *= m
        return w
    if name == "spiky":
        np.subtract(1.0, m, out=m)  # q^2
        np.maximum(m, 0.0, out=m)
        np.sqrt(m, out=m)
        np.subtract(1.0, m, out=m)
        np.maximum(m, 0.0, out=m)
        w = m * m
        w *= m
        return w
    if name == "gaussian":
        # sigma = h/3  =>  r^2 / (2 sigma^2) = 4.5 q^2 = 4.5 (1 - m); truncated at q = 1.
        w = np.exp(4.5 * (m - 1.0))
        w[m < 0.0] = 0.0
        return w
    raise ValueError(f"unknown kernel {name!r}; known kernels: {list(KERNELS)}")


if set(KERNELS) != {"poly6", "spiky", "gaussian"}:  # keep gridspec's list and this module in step
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

    Particles are anchored at their nearest node and touch the (2k+1)^2 nodes
    around it.  Indices refer to the grid padded by ``pad`` nodes on every
    side, so a stencil never leaves the index range and no per-entry bounds
    check or index clipping is needed; padding nodes get weight 0 and are
    cropped off.

    Arrays are laid out stencil-major, particle-minor ((2, K, N), (S, N)):
    with the particle axis innermost every NumPy operation runs long
    contiguous loops, several times faster than (N, S) for small stencils.
    At the sizes used here the cost is mostly per NumPy call, so the
    constants below are arranged to keep the number of calls down.
    """

    k: int  # half-width: offsets -k..k in x and in y, K = 2k+1, S = K^2
    pad: int
    ny: int
    nx: int
    nyp: int  # padded shape
    nxp: int
    o_h: np.ndarray  # (1, K, 1) offsets, in units of h
    off_centre: np.ndarray  # (2, K, 1): anchor a puts node a+o on the grid iff |a - centre| <= half
    off_half: np.ndarray  # (2, 1, 1)
    flat_off: np.ndarray  # (S, 1) int32 flat offsets in the padded grid (pad included), S in (ky, kx) order
    base_w: np.ndarray  # (2,): anchor (ax, ay) -> flat index ax + ay * nxp
    origin: np.ndarray  # (2, 1) m
    inv_dx: float  # 1 / resolution, 1/m
    scale: float  # resolution / h: node units -> units of h
    anchor_hi: np.ndarray  # (2, 1): anchors are clipped to [-1, n] per axis

    @property
    def cells(self) -> int:
        """Nodes in the padded grid."""
        return self.nyp * self.nxp

    def crop(self, padded: np.ndarray) -> np.ndarray:
        """(..., nyp, nxp, C) -> the real nodes (..., ny, nx, C) (a view)."""
        p = self.pad
        return padded[..., p : p + self.ny, p : p + self.nx, :]


@lru_cache(maxsize=64)
def _stencil(origin: tuple[float, float], shape: tuple[int, int], resolution: float, h: float) -> _Stencil:
    r = h / resolution  # support radius in node units
    # A particle is at most half a node from its anchor along each axis, so
    # every node within r of it is within r + 1/2 of the anchor along x and y.
    k = int(math.floor(r + 0.5 + 1e-9))
    # Anchors are clipped to [-1, n] (particles slightly outside the domain),
    # so a pad of k + 1 keeps every stencil inside the padded grid.
    pad = k + 1
    ny, nx = shape
    nyp, nxp = ny + 2 * pad, nx + 2 * pad
    o = np.arange(-k, k + 1)
    oy, ox = np.meshgrid(o, o, indexing="ij")
    last = np.array([nx - 1.0, ny - 1.0]).reshape(2, 1, 1)
    st = _Stencil(
        k=k,
        pad=pad,
        ny=ny,
        nx=nx,
        nyp=nyp,
        nxp=nxp,
        o_h=(o * (resolution / h)).reshape(1, -1, 1),
        # 0 <= a + o <= n - 1  <=>  |a - (n - 1 - 2 o) / 2| <= (n - 1) / 2
        off_centre=(last - 2.0 * o.reshape(1, -1, 1)) / 2.0,
        off_half=last / 2.0,
        flat_off=((oy + pad) * nxp + (ox + pad)).astype(np.int32).reshape(-1, 1),
        base_w=np.array([1.0, float(nxp)]),
        origin=np.array(origin, dtype=np.float64).reshape(2, 1),
        inv_dx=1.0 / resolution,
        scale=resolution / h,
        anchor_hi=np.array([[nx], [ny]], dtype=np.float64),
    )
    for a in (st.o_h, st.off_centre, st.off_half, st.flat_off, st.base_w, st.origin, st.anchor_hi):
        a.flags.writeable = False
    return st


def _stencil_for(spec: GridSpec) -> _Stencil:
    return _stencil(spec.origin, spec.shape, spec.resolution, spec.h)


def _weights(
    pos: np.ndarray, spec: GridSpec, st: _Stencil, world_offset=None, clip: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalized kernel weights of particles to the nodes of their stencils.

    ``pos`` (N, 2) float64 m; ``world_offset`` optional (N,) int added to the
    indices (batching: world b's nodes start at ``b * st.cells``).  ``clip``
    may be False when every particle is known to lie within half a node of
    the domain (its anchor is then a real node).  Returns ``idx`` (S, N)
    int32 flat indices into the padded grid (``(iy + pad) * nxp + ix +
    pad``) and ``w`` (S, N) float64 weights, 0 for nodes out of range or in
    the padding.
    """
    n = len(pos)
    # C order matters: everything below inherits u's layout, and ufuncs on
    # the transposed (Fortran-ordered) view run several times slower.
    u = np.subtract(pos.T, st.origin, order="C")  # (2, N)
    u *= st.inv_dx  # node units
    a = np.rint(u)  # anchor node per axis
    if clip:  # keeps far-outside particles' stencils in the padding
        np.maximum(a, -1.0, out=a)
        np.minimum(a, st.anchor_hi, out=a)
    u -= a
    u *= st.scale  # particle offset from its anchor, units of h
    # Per axis, per offset: t = 1/2 - (distance along the axis / h)^2, so that
    # t_y + t_x = 1 - (r/h)^2 = m, which every kernel is a function of.
    t = st.o_h - u[:, None, :]  # (2, K, N)
    np.multiply(t, t, out=t)
    np.subtract(0.5, t, out=t)
    # Nodes off the real grid (the padding): t = -1 makes m < 0, out of range.
    off = np.abs(a[:, None, :] - st.off_centre)
    np.putmask(t, off > st.off_half, -1.0)
    m = (t[1][:, None, :] + t[0][None, :, :]).reshape(-1, n)  # (S, N), S in (ky, kx) order
    w = _shape_of_m(m, spec.kernel)
    base = (st.base_w @ a).astype(np.int32)  # (N,) anchor's flat index, less the padding
    if world_offset is not None:
        base += world_offset
    # int32: half the memory traffic, and scipy.sparse's index type.
    return st.flat_off + base, w


def _chunks(n: int, st: _Stencil) -> list[tuple[int, int]]:
    """Particle ranges [p0, p1) of at most ~_CHUNK_ENTRIES stencil entries each."""
    size = max(64, _CHUNK_ENTRIES // st.flat_off.shape[0])
    return [(p0, min(p0 + size, n)) for p0 in range(0, n, size)]


# --------------------------------------------------------------------------- #
# Scatter and gather
# --------------------------------------------------------------------------- #
#
# The stencil weights of N particles form a sparse (nodes x N) matrix A whose
# column n holds particle n's weights: P2G is A @ values and SPH G2P gathers
# with A^T.  In particle-major order (the transposes of the (S, N) arrays)
# every particle's S entries are contiguous, so the CSC index pointer is just
# 0, S, 2S, ...  One sparse product handles every channel at once: one
# np.bincount per channel was about 2.5x slower for the six input channels.
#
# scipy builds and checks a csc_array in Python, which costs about 30 us per
# call here -- a fifth of a whole world's P2G.  So the compiled kernels behind
# `csc_array @ dense` / `csr_array @ dense` are called directly when this
# SciPy still has them with the expected signature (checked against the
# public API once, at import); otherwise the public API is used.

try:
    from scipy.sparse import _sparsetools
except ImportError:  # pragma: no cover - depends on the SciPy version
    _sparsetools = None


class _Entries(NamedTuple):
    """Stencil entries in particle-major (CSC / CSR) order."""

    indptr: np.ndarray  # (N + 1,) int32: 0, S, 2S, ...
    nodes: np.ndarray  # (N * S,) int32 node index of each entry
    weights: np.ndarray  # (N * S,) float64


def _entries(idx: np.ndarray, w: np.ndarray) -> _Entries:
    s, n = w.shape
    return _Entries(np.arange(0, s * n + 1, s, dtype=np.int32), idx.T.ravel(), w.T.ravel())


def _splat_public(e: _Entries, v: np.ndarray, n_rows: int) -> np.ndarray:
    return sparse.csc_array((e.weights, e.nodes, e.indptr), shape=(n_rows, len(v))) @ v


def _gather_public(e: _Entries, x: np.ndarray) -> np.ndarray:
    return sparse.csr_array((e.weights, e.nodes, e.indptr), shape=(len(e.indptr) - 1, len(x))) @ x


def _splat_compiled(e: _Entries, v: np.ndarray, n_rows: int) -> np.ndarray:
    v = np.ascontiguousarray(v, dtype=np.float64)
    y = np.zeros((n_rows, v.shape[1]))
    _sparsetools.csc_matvecs(n_rows, len(v), v.shape[1], e.indptr, e.nodes, e.weights, v.ravel(), y.ravel())
    return y


def _gather_compiled(e: _Entries, x: np.ndarray) -> np.ndarray:
    x = np.ascontiguousarray(x, dtype=np.float64)
    n = len(e.indptr) - 1
    y = np.zeros((n, x.shape[1]))
    _sparsetools.csr_matvecs(n, len(x), x.shape[1], e.indptr, e.nodes, e.weights, x.ravel(), y.ravel())
    return y


def _compiled_kernels_work() -> bool:
    """Do the private kernels exist and agree with the public API on a small case?"""
    if _sparsetools is None:
        return False
    try:
        rng = np.random.default_rng(0)
        e = _entries(rng.integers(0, 9, (4, 5)).astype(np.int32), rng.random((4, 5)))
        v, x = rng.random((5, 3)), rng.random((9, 2))
        return bool(
            np.allclose(_splat_compiled(e, v, 9), _splat_public(e, v, 9))
            and np.allclose(_gather_compiled(e, x), _gather_public(e, x))
        )
    except Exception:  # any change in the private API: use the public one
        return False


if _compiled_kernels_work():
    _splat, _gather = _splat_compiled, _gather_compiled
else:  # pragma: no cover - depends on the SciPy version
    _splat, _gather = _splat_public, _gather_public
_splat.__doc__ = "(n_rows, C) float64: row r = sum of weight * v[particle] over entries at node r (P2G)."
_gather.__doc__ = "(N, C) float64: row n = sum over particle n's entries of weight * x[node] (G2P)."


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


def _check_grid(grid, spec: GridSpec) -> np.ndarray:
    g = np.asarray(grid)
    if g.ndim == 2:
        g = g[:, :, None]
    if g.ndim != 3 or g.shape[:2] != spec.shape:
        raise ValueError(f"grid must have shape (ny, nx, C) = ({spec.ny}, {spec.nx}, C), got {np.shape(grid)}")
    if not np.isfinite(g).all():
        bad = np.argwhere(~np.isfinite(g))[0]
        raise ValueError(f"grid contains NaN or infinite values (e.g. node (iy, ix) = ({bad[0]}, {bad[1]}), channel {bad[2]})")
    return g


def _check_mode(outside: str, tolerance: float) -> None:
    if outside not in _OUTSIDE_MODES:
        raise ValueError(f"outside must be one of {list(_OUTSIDE_MODES)}, got {outside!r}")
    if not (isinstance(tolerance, (int, float)) and math.isfinite(tolerance) and tolerance >= 0):
        raise ValueError(f"tolerance must be a finite distance >= 0 m, got {tolerance!r}")


def _bounds(spec: GridSpec, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) corners (2,) m of the accepted region: the domain grown by ``tolerance``."""
    return _bounds_cached(spec.origin, spec.upper, float(tolerance))


@lru_cache(maxsize=64)
def _bounds_cached(origin, upper, tolerance):
    lo = np.array([origin[0] - tolerance, origin[1] - tolerance])
    hi = np.array([upper[0] + tolerance, upper[1] + tolerance])
    lo.flags.writeable = hi.flags.writeable = False
    return lo, hi


def _inside(pos: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N, 2) bool, per coordinate: within the accepted region (False for NaN).

    Plain comparisons, so a particle exactly on an edge or corner is inside
    even with zero tolerance.
    """
    inside = pos >= lo
    inside &= pos <= hi
    return inside


def _all_inside(pos: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    # One pass answers two questions in the common case: NaN fails every
    # comparison, so "all inside" also means "all finite".
    return bool(_inside(pos, lo, hi).all())


def _split_outside(pos: np.ndarray, spec: GridSpec, outside: str, tolerance: float, label: str):
    """Check positions are finite and inside the domain (+ tolerance).

    Returns (positions kept, kept indices or None when all are kept, outside
    indices).  Raises ValueError for NaN/inf, and for particles outside when
    ``outside == "raise"``.
    """
    lo, hi = _bounds(spec, tolerance)
    if _all_inside(pos, lo, hi):
        return pos, None, _NO_INDEX
    finite = np.isfinite(pos).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise ValueError(f"{label} positions contain NaN or infinite values (particles {bad[:10].tolist()})")
    inside = _inside(pos, lo, hi).all(axis=1)
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


class _Set(NamedTuple):
    """One set of particles splatted into some channels of one world's grid."""

    world: int
    cols: Sequence[int]  # output channels, one per column of vals
    pos: np.ndarray  # (N, 2) float64 m
    vals: np.ndarray  # (N, len(cols)) float64
    label: str  # names the particles in errors: "bodies", "contacts", "particles", ...
    names: Sequence[str] | None = None  # channel names, for errors


def _columns(cols: Sequence[int]):
    """A slice for a contiguous run of columns (cheaper to assign through), else the list."""
    cols = list(cols)
    if cols == list(range(cols[0], cols[-1] + 1)):
        return slice(cols[0], cols[-1] + 1)
    return cols


def _p2g_sets(sets: Sequence[_Set], spec: GridSpec, batch: int, n_channels: int, outside: str, tolerance: float):
    """Shared P2G engine: splat every set into ``grids[set.world][..., set.cols]``.

    One weight computation and one sparse product cover all sets (per chunk
    of particles).  Returns ``(grids (B, ny, nx, C) float32, reports)`` with
    ``reports[b]`` a tuple of the reports of world b's sets, in order.
    """
    st = _stencil_for(spec)
    if batch * st.cells >= 2**31:
        raise ValueError(f"a batch of {batch} grids is too large for one transfer; split it")
    all_pos = sets[0].pos if len(sets) == 1 else np.concatenate([s.pos for s in sets])
    if _all_inside(all_pos, *_bounds(spec, tolerance)):  # the common case: one check for every set
        kept = [(None, _NO_INDEX)] * len(sets)
    else:
        kept = []
        for s in sets:
            _check_finite_values(s.vals, s.label, s.names)  # dropped values still go into lost_value
            pos_in, keep, out_idx = _split_outside(s.pos, spec, outside, tolerance, s.label)
            kept.append((keep, out_idx))
        all_pos = np.concatenate([s.pos if k is None else s.pos[k] for s, (k, _) in zip(sets, kept)])
    sizes = [len(s.pos) if k is None else len(k) for s, (k, _) in zip(sets, kept)]
    total = len(all_pos)

    # Unnormalized values of every kept particle, laid out in output channels.
    if len(sets) == 1 and kept[0][0] is None and list(sets[0].cols) == list(range(n_channels)):
        values = sets[0].vals
    else:
        values = np.zeros((total, n_channels))
        start = 0
        for s, (keep, _), size in zip(sets, kept, sizes):
            values[start : start + size, _columns(s.cols)] = s.vals if keep is None else s.vals[keep]
            start += size
    if not np.isfinite(values).all():
        for s in sets:
            _check_finite_values(s.vals, s.label, s.names)

    lost = np.zeros(total, dtype=bool)
    chunks = _chunks(total, st)
    world_of = np.repeat(np.array([s.world for s in sets], dtype=np.intp), sizes) if batch > 1 else None
    out = None if len(chunks) == 1 else np.zeros((batch, spec.ny, spec.nx, n_channels), dtype=np.float32)
    # Inside the domain + tolerance, anchors are real nodes unless the
    # tolerance reaches half a node.
    clip = tolerance >= 0.5 * spec.resolution
    for p0, p1 in chunks:
        b0 = b1 = 0
        offsets = None
        if world_of is not None:
            b0, b1 = int(world_of[p0]), int(world_of[p1 - 1])
            offsets = (world_of[p0:p1] - b0) * st.cells
        idx, w = _weights(all_pos[p0:p1], spec, st, offsets, clip)
        wsum = w.sum(axis=0)
        lost_c = wsum <= 0.0
        lost[p0:p1] = lost_c
        # Dividing each particle's values by its weight sum normalizes
        # Algorithm 1's weights without touching the (S, N) array.  Lost
        # particles have all-zero weights, so any finite divisor will do.
        v = values[p0:p1] / (wsum + lost_c)[:, None]
        padded = _splat(_entries(idx, w), v, (b1 - b0 + 1) * st.cells)
        grid = st.crop(padded.reshape(b1 - b0 + 1, st.nyp, st.nxp, n_channels))
        if out is None and b1 - b0 + 1 == batch:  # the common case: one chunk covers every world
            out = np.ascontiguousarray(grid, dtype=np.float32)
        else:
            if out is None:
                out = np.zeros((batch, spec.ny, spec.nx, n_channels), dtype=np.float32)
            out[b0 : b1 + 1] += grid
    if out is None:  # no particles at all
        out = np.zeros((batch, spec.ny, spec.nx, n_channels), dtype=np.float32)

    per_world: list[list[TransferReport]] = [[] for _ in range(batch)]
    start = 0
    for s, (keep, out_idx), size in zip(sets, kept, sizes):
        per_world[s.world].append(_lost_report(len(s.pos), keep, out_idx, lost[start : start + size], s.vals))
        start += size
    return out, [tuple(r) for r in per_world]


def _lost_report(n: int, keep, out_idx, lost_local: np.ndarray, vals: np.ndarray) -> TransferReport:
    """Report for one particle set; ``lost_local`` indexes the kept particles."""
    lost_idx = _NO_INDEX
    if lost_local.any():
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
    _check_mode(outside, tolerance)
    sets = []
    n_channels = None
    for b, (p, v) in enumerate(zip(positions, values)):  # loop over worlds
        label = f"world {b} particles" if len(positions) > 1 else "particles"
        pos = _as_positions(p, label + " positions")
        vals = _as_values(v, len(pos), label + " values")
        if n_channels is None:
            n_channels = vals.shape[1]
        elif vals.shape[1] != n_channels:
            raise ValueError(f"world {b} has {vals.shape[1]} value channels, world 0 has {n_channels}")
        sets.append(_Set(b, range(vals.shape[1]), pos, vals, label))
    grids, reports = _p2g_sets(sets, spec, len(sets), n_channels, outside, tolerance)
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
    g = _check_grid(grid, spec)
    n_channels = g.shape[2]
    pos = _as_positions(positions, "positions")
    n = len(pos)
    pos_in, keep, out_idx = _split_outside(pos, spec, outside, tolerance, "particles")
    if method == "bilinear":
        vals = _g2p_bilinear(g, pos_in, spec)
        report = TransferReport(n, out_idx, _NO_INDEX, np.zeros(n_channels))
    else:
        vals, diagnose = _g2p_sph(g, pos_in, spec, clip=tolerance >= 0.5 * spec.resolution)

        def pending():
            lost_mask, lost_value, nodes_lost = diagnose()
            lost_idx = np.flatnonzero(lost_mask)
            return (lost_idx if keep is None else keep[lost_idx]), lost_value, nodes_lost

        report = TransferReport(n, out_idx, pending=pending)
    if keep is not None:
        full = np.zeros((n, n_channels), dtype=np.float32)
        full[keep] = vals
        vals = full
    return vals, report


def _g2p_sph(g: np.ndarray, pos: np.ndarray, spec: GridSpec, clip: bool = True):
    """SPH G2P of ``pos`` (M, 2) from ``g`` (ny, nx, C).

    Returns ``(values (M, C) float32, diagnose)``; ``diagnose()`` gives
    ``(lost mask (M,), lost node value (C,), lost node count)``.
    """
    ny, nx, n_channels = g.shape
    st = _stencil_for(spec)
    # The grid, padded like the indices (padding stays 0); a private copy, so
    # the lazy diagnostics see the grid as it was.
    gp = np.zeros((st.nyp, st.nxp, n_channels))
    gp[st.pad : st.pad + ny, st.pad : st.pad + nx] = g
    gp = gp.reshape(st.cells, n_channels)
    out = np.empty((len(pos), n_channels), dtype=np.float32)
    parts = [(p0, p1, _entries(*_weights(pos[p0:p1], spec, st, None, clip))) for p0, p1 in _chunks(len(pos), st)]
    if parts:
        # Per-node weight totals, to normalize each node's weights to sum 1.
        node_w = np.bincount(parts[0][2].nodes, parts[0][2].weights, minlength=st.cells)
        for _, _, e in parts[1:]:
            node_w += np.bincount(e.nodes, e.weights, minlength=st.cells)
        # Nodes nobody reaches get 1 instead of 1/0: their entries have weight 0.
        inv = 1.0 / (node_w + (node_w <= 0.0))
        for p0, p1, e in parts:
            out[p0:p1] = _gather(e._replace(weights=e.weights * inv[e.nodes]), gp)
    else:
        node_w = np.zeros(st.cells)

    def diagnose():
        lost = np.zeros(len(pos), dtype=bool)
        for p0, p1, e in parts:
            lost[p0:p1] = ~e.weights.reshape(p1 - p0, -1).any(axis=1)
        # What nobody received (padding nodes hold 0, so they add nothing).
        unreached = (node_w <= 0.0).astype(np.float64)
        return lost, unreached @ gp, np.count_nonzero(unreached * np.abs(gp).sum(axis=1))

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
# Worlds -> grids
# --------------------------------------------------------------------------- #


def _grouped(names: Sequence[str]) -> list[tuple[str, list[int], list[str]]]:
    """Channels grouped by source: [(source, column indices, names)], in first-use order."""
    groups: dict[str, tuple[list[int], list[str]]] = {}
    for j, n in enumerate(names):
        if n not in CHANNELS:
            raise ValueError(f"unknown channel {n!r}; known channels: {sorted(CHANNELS)}")
        cols, ns = groups.setdefault(CHANNELS[n].source, ([], []))
        cols.append(j)
        ns.append(n)
    return [(s, cols, ns) for s, (cols, ns) in groups.items()]


def worlds_to_grids(
    worlds: Sequence[tuple[np.ndarray | None, np.ndarray | None]],
    spec: GridSpec,
    channels: Sequence[str] | None = None,
    *,
    walls: bool = True,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> tuple[np.ndarray, list[dict[str, TransferReport]]]:
    """Grids of several worlds, (B, ny, nx, len(channels)) float32, raw (not normalized).

    ``worlds`` lists ``(bodies, contacts)`` structured arrays as exported by
    the engine (see :mod:`deepcontact.gridspec` for the fields used; a source
    no channel needs may be None).  ``channels`` defaults to ``spec.inputs``.
    Each source is splatted once for all its channels, and all worlds and
    sources share one weight computation.  With ``walls`` (default) the
    static box's wall mass is added to ``walls=True`` channels (see
    :meth:`GridSpec.add_wall_mass`).  Returns the grids and, per world, a
    report per source (``{"bodies": ..., "contacts": ...}``).
    """
    channels = tuple(spec.inputs if channels is None else channels)
    if not channels:
        raise ValueError("worlds_to_grids needs at least one channel")
    if len(worlds) == 0:
        raise ValueError("worlds_to_grids needs at least one world")
    groups = _grouped(channels)
    _check_mode(outside, tolerance)
    sets = []
    for b, world in enumerate(worlds):  # loop over worlds
        for source, cols, names in groups:
            arr = world[0] if source == "bodies" else world[1]
            if arr is None:
                raise ValueError(f"world {b}: channels {names} need {source}, got None")
            src = SOURCES[source]
            records = src.records(arr)
            pos = _as_positions(records[src.position_field], f"{source} positions")
            label = source if len(worlds) == 1 else f"world {b} {source}"
            sets.append(_Set(b, cols, pos, channel_values(names, records, select=False), label, names))
    grids, reports = _p2g_sets(sets, spec, len(worlds), len(channels), outside, tolerance)
    if walls:
        spec.add_wall_mass(grids, channels)
    sources = [s for s, _, _ in groups]
    return grids, [dict(zip(sources, r)) for r in reports]


def world_to_grids(
    bodies: np.ndarray,
    contacts: np.ndarray,
    spec: GridSpec,
    *,
    walls: bool = True,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
    return_report: bool = False,
):
    """The CNN input grid of one world: (ny, nx, len(spec.inputs)) float32, raw.

    ``bodies`` and ``contacts`` are the engine's structured arrays (static
    bodies are skipped; contact points are splatted at ``point``).  Channels
    are computed from :data:`deepcontact.gridspec.CHANNELS` in
    ``spec.inputs`` order; the static box's edge nodes get
    ``spec.wall_mass`` in the mass channel unless ``walls=False``.  Apply
    ``spec.normalize(grid)`` before feeding the CNN.  With
    ``return_report`` returns ``(grid, {"bodies": report, "contacts": report})``.
    """
    grids, reports = worlds_to_grids(
        [(bodies, contacts)], spec, spec.inputs, walls=walls, outside=outside, tolerance=tolerance
    )
    return (grids[0], reports[0]) if return_report else grids[0]


def targets_to_grids(
    contacts: np.ndarray,
    spec: GridSpec,
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
    return_report: bool = False,
):
    """The training target grid of one world: (ny, nx, len(spec.targets)) float32, raw.

    Splats the contact points' ``spec.targets`` channels (normal and tangent
    final impulse, N s, by default).  With ``return_report`` returns
    ``(grid, report)``.
    """
    grids, reports = worlds_to_grids(
        [(None, contacts)], spec, spec.targets, walls=False, outside=outside, tolerance=tolerance
    )
    return (grids[0], reports[0]["contacts"]) if return_report else grids[0]
