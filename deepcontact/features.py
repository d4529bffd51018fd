"""A step's records -> the CNN's input and target grids, channel by channel.

The channels a GridSpec lists (deepcontact.channels) are read from a step's
records and splatted with the shared transfer (deepcontact.transfer): each
particle source once for all its channels, all sources (and worlds) with one
weight computation.

    grid = world_to_grids(bodies, contacts, spec)                     # (ny, nx, Cin) raw
    grid, plan = world_to_grids(bodies, contacts, spec, outside="drop",
                                previous=last_points, physics=physics, return_plan=True)
    target = targets_to_grids(contacts, spec)                         # (ny, nx, Cout) raw

Grids are raw (not normalized: apply ``spec.normalize``); the static box's
edge nodes get ``spec.wall_mass`` in ``walls=True`` channels (thesis §8.1).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Sequence

import numpy as np

from deepcontact.channels import CHANNELS, SOURCES, Step
from deepcontact.gridspec import GridSpec
from deepcontact.kinematics import Physics
from deepcontact.transfer import (
    DOMAIN_TOLERANCE,
    ParticleSet,
    TransferPlan,
    TransferReport,
    channel_columns,
    p2g_sets,
    plan,
)

__all__ = ["step_to_grids", "targets_to_grids", "world_to_grids", "worlds_to_grids"]


def _grouped(names: tuple[str, ...]) -> tuple[tuple[str, tuple[int, ...], tuple[str, ...]], ...]:
    """Channels grouped by source: ((source, column indices, names), ...), in first-use order."""
    for n in names:
        if n not in CHANNELS:
            raise ValueError(f"unknown channel {n!r}; known channels: {sorted(CHANNELS)}")
    return _grouped_cached(names)


@lru_cache(maxsize=64)
def _grouped_cached(names: tuple[str, ...]):
    # Runs on every call with one of a handful of channel lists: cached.
    groups: dict[str, tuple[list[int], list[str]]] = {}
    for j, n in enumerate(names):
        cols, ns = groups.setdefault(CHANNELS[n].source, ([], []))
        cols.append(j)
        ns.append(n)
    return tuple((s, tuple(cols), tuple(ns)) for s, (cols, ns) in groups.items())


def _as_step(world) -> Step:
    return world if isinstance(world, Step) else Step(*world)


def _worlds_to_grids(worlds: Sequence[Step], spec: GridSpec, channels, walls: bool, outside: str, tolerance: float,
                     plan_source: str | None = None, reports: bool = True):
    """:func:`worlds_to_grids`, plus, for one world, the :class:`TransferPlan`
    of ``plan_source`` (a source name) if a channel splats it:
    ``(grids, reports (None unless reports), plan or None)``."""
    channels = tuple(spec.inputs if channels is None else channels)
    if not channels:
        raise ValueError("worlds_to_grids needs at least one channel")
    if len(worlds) == 0:
        raise ValueError("worlds_to_grids needs at least one world")
    groups = _grouped(channels)
    # Every set's records, then one (N, 2) position array and one (N, C)
    # value array for all of them, filled field by field.
    chosen = []
    for b, step in enumerate(worlds):  # loop over worlds
        for source, cols, names in groups:
            chosen.append((b, step, source, cols, names, SOURCES[source].particles(step)))
    n = sum([len(c[5]) for c in chosen])
    pos = np.empty((n, 2))
    values = np.zeros((n, len(channels)))
    sets = []
    plan_set = None
    start = 0
    for b, step, source, cols, names, records in chosen:  # loop over worlds and sources
        stop = start + len(records)
        p = records[SOURCES[source].position_field]
        if p.shape != (stop - start, 2):
            raise ValueError(f"{source} positions must have shape (N, 2), got {p.shape}")
        pos[start:stop] = p
        for j, name in zip(cols, names):  # loop over channels
            values[start:stop, j] = CHANNELS[name].extract(records, step)
        label = source if len(worlds) == 1 else f"world {b} {source}"
        if source == plan_source and len(worlds) == 1:
            plan_set = len(sets)
        sets.append(ParticleSet(b, channel_columns(cols), start, stop, label, names))
        start = stop
    grids, per_world, plan_ = p2g_sets(pos, values, sets, spec, len(worlds), outside, tolerance, plan_set, reports)
    if walls and spec.wall_mass != 0.0:
        _add_wall_mass(grids, spec, channels)
    if per_world is None:
        return grids, None, plan_
    sources = [s for s, _, _ in groups]
    return grids, [dict(zip(sources, r)) for r in per_world], plan_


def _add_wall_mass(grids: np.ndarray, spec: GridSpec, channels: tuple[str, ...]) -> None:
    """:meth:`GridSpec.add_wall_mass` of ``grids`` (B, ny, nx, C) float32, in place.

    The same nodes, channels and float32 sums, through one precomputed flat
    index instead of a (world, node, channel) one: about three times faster.
    """
    idx = _wall_index(spec, channels)
    flat = grids.reshape(-1)
    if len(grids) == 1:
        flat[idx] += spec.wall_mass
    else:
        flat[(idx + np.arange(0, flat.size, spec.n_nodes * len(channels))[:, None]).reshape(-1)] += spec.wall_mass


@lru_cache(maxsize=64)
def _wall_index(spec: GridSpec, channels: tuple[str, ...]) -> np.ndarray:
    """Flat indices into one (ny, nx, C) grid of the wall nodes' ``walls=True`` channels."""
    nodes = np.flatnonzero(spec.wall_mask())
    cols = [j for j, n in enumerate(channels) if CHANNELS[n].walls]
    idx = (nodes[:, None] * len(channels) + np.array(cols, dtype=np.intp)).reshape(-1)
    idx.flags.writeable = False
    return idx


def worlds_to_grids(
    worlds: Sequence,
    spec: GridSpec,
    channels: Sequence[str] | None = None,
    *,
    walls: bool = True,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
) -> tuple[np.ndarray, list[dict[str, TransferReport]]]:
    """Grids of several worlds, (B, ny, nx, len(channels)) float32, raw (not normalized).

    ``worlds`` lists :class:`~deepcontact.channels.Step` objects or
    ``(bodies, contacts)`` pairs of the engine's structured arrays (a source
    no channel needs may be None).  ``channels`` defaults to ``spec.inputs``.
    Each source is splatted once for all its channels, and all worlds and
    sources share one weight computation.  With ``walls`` (default) the
    static box's wall mass is added to ``walls=True`` channels (see
    :meth:`GridSpec.add_wall_mass`).  Returns the grids and, per world, a
    report per source (``{"bodies": ..., "contacts": ...}``).
    """
    steps = [_as_step(w) for w in worlds]
    grids, reports, _ = _worlds_to_grids(steps, spec, channels, walls, outside, tolerance)
    return grids, reports


def world_to_grids(
    bodies: np.ndarray | None,
    contacts: np.ndarray | None,
    spec: GridSpec,
    *,
    previous: np.ndarray | None = None,
    physics: Physics = Physics(),
    walls: bool = True,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
    return_report: bool = False,
    return_plan: bool = False,
):
    """The CNN input grid of one step: (ny, nx, len(spec.inputs)) float32, raw.

    ``bodies`` and ``contacts`` are the engine's structured arrays (static
    bodies are skipped; contact points are splatted at ``point``);
    ``previous`` the previous step's contact points, for temporal channels
    (None: those channels are 0); ``physics`` the step's gravity and time
    step, for the contact-velocity channels.  Channels are computed from
    :data:`deepcontact.channels.CHANNELS` in ``spec.inputs`` order; the static
    box's edge nodes get ``spec.wall_mass`` in the mass channel unless
    ``walls=False``.  Apply ``spec.normalize(grid)`` before feeding the CNN.

    With ``return_report`` also returns ``{source: report}``; with
    ``return_plan`` also the :class:`TransferPlan` of the contact points,
    reusing the weights of this splat, so that ``plan.g2p(output)`` equals
    ``g2p(output, contacts["point"], spec, outside=outside,
    tolerance=tolerance)`` at a fraction of the cost (the server's step).
    The result is ``grid``, ``(grid, reports)``, ``(grid, plan)`` or
    ``(grid, reports, plan)``.
    """
    step = Step(bodies, contacts, previous, physics)
    return step_to_grids(step, spec, walls=walls, outside=outside, tolerance=tolerance,
                         return_report=return_report, return_plan=return_plan)


def step_to_grids(step: Step, spec: GridSpec, channels: Sequence[str] | None = None, *, walls: bool = True,
                  outside: str = "raise", tolerance: float = DOMAIN_TOLERANCE, return_report: bool = False,
                  return_plan: bool = False):
    """:func:`world_to_grids` of a :class:`~deepcontact.channels.Step` (and
    optionally other ``channels`` than ``spec.inputs``)."""
    grids, reports, contact_plan = _worlds_to_grids(
        [step], spec, channels, walls, outside, tolerance, "contacts" if return_plan else None, return_report)
    out = [grids[0]]
    if return_report:
        out.append(reports[0])
    if return_plan:
        if contact_plan is None:  # no input channel reads the contact points
            contact_plan = plan(step.contacts["point"], spec, outside=outside, tolerance=tolerance)
        out.append(contact_plan)
    return out[0] if len(out) == 1 else tuple(out)


def targets_to_grids(
    contacts: np.ndarray | Step,
    spec: GridSpec,
    *,
    outside: str = "raise",
    tolerance: float = DOMAIN_TOLERANCE,
    return_report: bool = False,
):
    """The training target grid of one step: (ny, nx, len(spec.targets)) float32, raw.

    Splats the contact points' ``spec.targets`` channels (normal and tangent
    final impulse, N s, by default) of ``contacts`` (the engine's array, or a
    Step for targets that need more, such as the oracle's).  With
    ``return_report`` returns ``(grid, report)``.
    """
    step = contacts if isinstance(contacts, Step) else Step(None, contacts)
    grids, reports, _ = _worlds_to_grids([step], spec, spec.targets, False, outside, tolerance, None, return_report)
    return (grids[0], reports[0]["contacts"]) if return_report else grids[0]
