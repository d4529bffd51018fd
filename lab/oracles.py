"""Oracle experiments: warm starts built from the step's own solution, to find where a warm
start's value lies (docs/results.md). Not servable: each solves the step first. Registered
with simclient.warmstarts as oracle:VARIANT when `lab` is imported.

    provider = make_provider("oracle:near-admissible")   # simclient.warmstarts.make_provider

    oracle:persisting   the oracle at points that persist, zero at new ones
    oracle:new          the oracle at new points, builtin where the point persists
    oracle:normal       the oracle's normal impulse, builtin's tangent
    oracle:tangent      builtin's normal impulse, the oracle's tangent
    oracle:heavy        the oracle at the more heavily loaded half of the points, builtin elsewhere
    oracle:half         builtin + half the oracle's correction (oracle - builtin)
    oracle:grid@RES     builtin + the oracle's correction through a grid of RES m
                        (h = 2 RES, poly6): what smoothing at that scale keeps
    oracle:small@T      the oracle at points whose correction (oracle - builtin, normal)
                        is at most T N s, builtin elsewhere
    oracle:big@T        the oracle where that correction exceeds T N s, builtin elsewhere
    oracle:noisy@S      oracle:small@1 with Gaussian noise of S N s added to each served
                        correction (seeded): how exact a model must be
    oracle:relnoisy@R   the same with noise of R times each correction's size
    oracle:previous     the previous step's oracle at points that persist, builtin at new
                        ones: Box2D's warm start as if the last solve had converged
    oracle:some@F       the oracle at a random share F of the points (seeded), builtin
                        elsewhere: what a warm start exact where it is served, and served
                        only at some points, is worth
    oracle:settled      the oracle at points whose bodies both move slower than 0.01 m/s
                        (a pile at rest, deepcontact.kinematics.points_at_rest), builtin elsewhere
    oracle:moving       the oracle at the other points, builtin at those
    oracle:body-space   builtin + the part of the oracle's correction that moves the bodies
                        (the least-norm impulses with the same net impulse and torque on
                        every body, deepcontact.kinematics.body_space_part); normal >= 0
    oracle:self-stress  builtin + the rest of the correction: a self-stress, impulses
                        that move no body (a pile held at more points than it has freedoms)
    oracle:near         the step solved to convergence from Box2D's warm start instead of
                        from zero: of the pile's many solutions, the one builtin leads to
    oracle:near-body-space, oracle:near-self-stress  the two parts of that correction
    oracle:near-previous  oracle:previous with the previous step's solve itself run to
                        convergence, from where it started, instead of the step solved from zero
    oracle:near-release Box2D's warm start with no impulse at the points that solution lets go
                        (normal 0 there, more than 1e-6 N s in Box2D's): the contacts that open
    oracle:near-switch  that solution at the points whose normal impulse switches on or off
                        between Box2D's warm start and it, Box2D's elsewhere
    oracle:near-cone    that solution at the points whose friction is at its cone (at least
                        0.99 of its limit) in Box2D's warm start or in the solution, Box2D's elsewhere
    oracle:near-inside  that solution at the other points (friction inside the cone at both ends)
    oracle:near-admissible  builtin + that solution's body-space part, then the smallest self-stress
                        that brings every point inside its friction cone (normal >= 0, |tangent| <=
                        mu normal; deepcontact.kinematics.nearest_admissible): the bodies' motion
                        exact, the self-stress chosen by the limits alone, without the solution's
    oracle:near-admissible-open  the same with the points that solution lets go held at 0 as well
    oracle:near-admissible-separating  the same with the points the motion itself pulls apart held at 0:
                        those whose normal velocity after it is above SEPARATING_SPEED (the motion
                        alone, no more of the solution, names the contacts that let go)
    oracle:near-admissible-moving  the same with the solution's motion at the moving bodies only
                        (recorded speed REST_SPEED or more, deepcontact.kinematics.bodies_moving) and
                        Box2D's warm start's at the others (body_space_part_of): whose motion pays?
    oracle:near-admissible-settled  the solution's motion at the other bodies, Box2D's at the moving
    oracle:near-admissible@R  oracle:near-admissible from a motion known to within noise: Gaussian
                        noise of R times the body-space correction's root-mean-square size added at
                        each point and taken to body space (seeded), then admitted as above
    oracle:near-admissible-abs@S  the same with noise of S N s at each point, whatever the step's
                        correction: a model's error, which is not scaled to each step's own
    oracle:near-admissible-scaled@S  oracle:near-admissible from the motion's correction times S (no
                        noise): a motion right in direction and wrong in size, as a regression's
                        shrunk answer is (S < 1)
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from deepcontact.admission import nearest_admissible
from deepcontact.gridspec import GridSpec
from deepcontact.kinematics import (Physics, bodies_moving, body_space_part, body_space_part_of, contact_velocities,
                                    points_at_rest)
from deepcontact.transfer import plan
from simclient.provider import (SWITCH_IMPULSE, Provider, ReadsFriction, as_warm_start, at_friction_cone,
                                persisting_rows, point_friction)
from simclient.warmstarts import register_prefix

ORACLES = ("persisting", "new", "normal", "tangent", "heavy", "half", "grid@RES", "small@T", "big@T", "noisy@S",
           "relnoisy@R", "previous", "some@F", "settled", "moving", "body-space", "self-stress", "near",
           "near-body-space", "near-self-stress", "near-previous", "near-release", "near-switch", "near-cone",
           "near-inside", "near-admissible", "near-admissible-open", "near-admissible-separating", "near-admissible-moving",
           "near-admissible-settled", "near-admissible@R",
           "near-admissible-abs@S", "near-admissible-scaled@S")
#: Oracle variants that take a parameter after "@", and what it is.
_ORACLE_PARAMETERS = {"grid": "a grid spacing in m, e.g. oracle:grid@0.5",
                      "small": "a correction size in N s, e.g. oracle:small@1",
                      "big": "a correction size in N s, e.g. oracle:big@1",
                      "noisy": "a noise level in N s, e.g. oracle:noisy@0.05",
                      "relnoisy": "a noise level relative to the correction, e.g. oracle:relnoisy@0.5",
                      "some": "a share of the points, 0 < F <= 1, e.g. oracle:some@0.5",
                      "near-admissible": "a noise level relative to the motion, e.g. oracle:near-admissible@0.5",
                      "near-admissible-abs": "a noise level in N s, e.g. oracle:near-admissible-abs@0.2",
                      "near-admissible-scaled": "a scale of the motion, e.g. oracle:near-admissible-scaled@0.8"}
#: oracle:near-admissible-separating: a point whose normal velocity after the motion is above this (m/s) lets go;
#: a thousandth of a metre a second, ten times what the stopping rule's 1e-4 N s leaves at a point of about 1 kg.
SEPARATING_SPEED = 1e-3
#: oracle:noisy and oracle:relnoisy perturb the corrections of oracle:small at this size (N s).
NOISY_SMALL = 1.0


class OracleMix(ReadsFriction):
    """The oracle's impulses where they say most, builtin elsewhere (see the module docstring).

    A step is served in two stages: the step's solution (`_solution`: from zero, or from
    Box2D's warm start for the near- variants), then the variant's mix of it with Box2D's
    warm start (`_MIXES`, one small function each)."""

    def __init__(self, variant: str):
        self.variant = variant
        self.name = f"oracle:{variant}"
        kind, at, value = variant.partition("@")
        self.kind, self.value = kind, 0.0
        if kind in _ORACLE_PARAMETERS and at:
            try:
                self.value = float(value)
            except ValueError:
                self.value = -1.0
            if not self.value > 0 or (kind == "some" and self.value > 1):
                raise ValueError(f"oracle:{kind}@... needs {_ORACLE_PARAMETERS[kind]}, got {variant!r}")
        elif variant not in ORACLES:
            raise ValueError(f"unknown oracle variant {variant!r}: use one of {', '.join(ORACLES)}")
        self.mix = self.kind.removeprefix("near-")
        if self.mix not in _MIXES:
            raise ValueError(f"oracle:{variant} is not a mix of this step's solution (make_oracle serves it "
                             "with PreviousOracle)")
        self._rng = np.random.default_rng(0)  # a fresh provider per world: the same noise every run

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            return None  # nothing to warm-start
        builtin = points["builtin"].astype(np.float64)
        solved = _Solved(engine, bodies, points, builtin, self._solution(engine, builtin))
        return as_warm_start(_MIXES[self.mix](self, solved))

    def _solution(self, engine, builtin: np.ndarray) -> np.ndarray:
        """(P, 2) float64 N s: the step solved to convergence, from Box2D's warm start
        `builtin` (P, 2) for the near- variants, else from zero."""
        if self.kind.startswith("near"):
            start = tuple(np.ascontiguousarray(builtin[:, k], np.float32) for k in (0, 1))
            exact = engine.oracle(start=start).astype(np.float64)
            return np.where(np.isnan(exact), builtin, exact)  # NaN: outside every awake island
        return np.nan_to_num(engine.oracle()).astype(np.float64)


class _Solved(NamedTuple):
    """A step and its solution, as a mix reads them."""

    engine: object
    bodies: np.ndarray  # (B,) BODY_DTYPE
    points: np.ndarray  # (P,) CONTACT_DTYPE
    builtin: np.ndarray  # (P, 2) float64 N s, Box2D's warm start
    exact: np.ndarray  # (P, 2) float64 N s, OracleMix._solution

    @property
    def new(self) -> np.ndarray:
        """(P,) bool: points Box2D carries nothing into (new this step)."""
        return ~self.builtin.any(axis=1)

    @property
    def correction(self) -> np.ndarray:
        """(P,) N s: the size of the solution's change to Box2D's normal impulse."""
        return np.abs(self.exact[:, 0] - self.builtin[:, 0])


Mix = Callable[[OracleMix, _Solved], np.ndarray]  # -> (P, 2) float64 N s, the served impulses


def _exact_where(where: Callable[[OracleMix, _Solved], np.ndarray]) -> Mix:
    """The solution at the points `where` picks ((P,) bool), Box2D's warm start at the others."""
    return lambda o, s: np.where(where(o, s)[:, None], s.exact, s.builtin)


def _column(col: int) -> Mix:
    def mix(o: OracleMix, s: _Solved) -> np.ndarray:
        warm = s.builtin.copy()
        warm[:, col] = s.exact[:, col]
        return warm
    return mix


def _noisy(relative: bool) -> Mix:
    def mix(o: OracleMix, s: _Solved) -> np.ndarray:
        noise = o._rng.normal(0.0, o.value, s.exact.shape)
        if relative:
            noise *= np.abs(s.exact - s.builtin)
        return np.where((s.correction <= NOISY_SMALL)[:, None], s.exact + noise, s.builtin)
    return mix


def _pressing(impulses: np.ndarray) -> np.ndarray:
    return impulses[:, 0] > SWITCH_IMPULSE


def _release(o: OracleMix, s: _Solved) -> np.ndarray:
    let_go = _pressing(s.builtin) & ~_pressing(s.exact)
    return np.where(let_go[:, None], 0.0, s.builtin)


def _at_cone(o: OracleMix, s: _Solved) -> np.ndarray:
    mu = point_friction(o._friction, s.points)
    return at_friction_cone(s.builtin, mu) | at_friction_cone(s.exact, mu)


def _admissible(o: OracleMix, s: _Solved) -> np.ndarray:
    """Box2D's warm start moved by (part of) the solution's motion, then admitted inside the cones."""
    b, p = s.bodies, s.points
    if o.mix in ("admissible-moving", "admissible-settled"):
        moving = bodies_moving(b)
        moves = body_space_part_of(b, p, s.exact - s.builtin, moving if o.mix == "admissible-moving" else ~moving)
    else:
        moves = body_space_part(b, p, s.exact - s.builtin)
    released = None
    if o.mix == "admissible-open":
        released = ~_pressing(s.exact)
    elif o.mix == "admissible-separating":
        physics = Physics(s.engine.config.dt, tuple(s.engine.world.gravity))
        released = contact_velocities(b, p, s.builtin + moves, physics)[:, 0] > SEPARATING_SPEED
    if o.mix == "admissible-scaled":
        moves = o.value * moves
    elif o.value:  # oracle:near-admissible@R, oracle:near-admissible-abs@S
        size = 1.0 if o.mix == "admissible-abs" else np.sqrt(np.mean(moves ** 2))
        moves = body_space_part(b, p, moves + o._rng.normal(0.0, o.value * size, moves.shape))
    return nearest_admissible(b, p, s.builtin + moves, point_friction(o._friction, p), released)


def _part(body_space: bool) -> Mix:
    """Box2D's warm start plus the body-space part of the correction, or the rest (a self-stress)."""
    def mix(o: OracleMix, s: _Solved) -> np.ndarray:
        moves = body_space_part(s.bodies, s.points, s.exact - s.builtin)
        warm = s.builtin + (moves if body_space else s.exact - s.builtin - moves)
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        return warm
    return mix


def _through_grid(o: OracleMix, s: _Solved) -> np.ndarray:
    # A grid from the scenes' origin (their box's lower-left corner) over every point.
    res = o.value
    reach = np.ceil(s.points["point"].max(axis=0) / res) * res + res
    spec = GridSpec.for_domain((0.0, 0.0), tuple(np.maximum(reach, res)), res, 2 * res)
    pl = plan(s.points["point"], spec, outside="drop")
    return s.builtin + pl.g2p(pl.p2g(s.exact - s.builtin)[0])[0]


#: Each variant's mix, by its name without "near-" (the solution it starts from is _solution's).
_MIXES: dict[str, Mix] = {
    "near": lambda o, s: s.exact,
    "persisting": lambda o, s: np.where(s.new[:, None], 0.0, s.exact),
    "new": _exact_where(lambda o, s: s.new),
    "normal": _column(0),
    "tangent": _column(1),
    "heavy": _exact_where(lambda o, s: s.exact[:, 0] >= np.median(s.exact[:, 0])),
    "half": lambda o, s: s.builtin + 0.5 * (s.exact - s.builtin),
    "grid": _through_grid,
    "small": _exact_where(lambda o, s: s.correction <= o.value),
    "big": _exact_where(lambda o, s: s.correction > o.value),
    "noisy": _noisy(relative=False),
    "relnoisy": _noisy(relative=True),
    "some": _exact_where(lambda o, s: o._rng.random(len(s.points)) < o.value),
    "settled": _exact_where(lambda o, s: points_at_rest(s.bodies, s.points)),
    "moving": _exact_where(lambda o, s: ~points_at_rest(s.bodies, s.points)),
    "body-space": _part(body_space=True),
    "self-stress": _part(body_space=False),
    "release": _release,
    "switch": _exact_where(lambda o, s: _pressing(s.builtin) != _pressing(s.exact)),
    "cone": _exact_where(_at_cone),
    "inside": _exact_where(lambda o, s: ~_at_cone(o, s)),
    **{v: _admissible for v in ("admissible", "admissible-open", "admissible-separating", "admissible-abs",
                                "admissible-scaled", "admissible-moving", "admissible-settled")},
}


class PreviousOracle(Provider):
    """The previous step's oracle at persisting points (matched by key), builtin at
    new ones: does Box2D's warm start lose by carrying a solve that stopped at the
    threshold rather than the converged one? With `near`, the previous step's solve
    itself run to convergence (from the warm start this provider served there) rather
    than the step solved from zero, which converges to another of the pile's solutions."""

    def __init__(self, near: bool = False):
        self.near = near
        self.name = "oracle:near-previous" if near else "oracle:previous"
        self._keys = np.zeros(0, np.uint64)  # sorted keys of the previous step's points ...
        self._exact = np.zeros((0, 2))  # ... and their oracle impulses, N s
        self._now = None  # this step's (keys, oracle), kept until observe()

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            self._now = None
            return None
        warm = points["builtin"].astype(np.float64)
        idx, persisting = persisting_rows(self._keys, points)
        warm[persisting] = self._exact[idx[persisting]]
        served = as_warm_start(warm)
        if self.near:
            converged = engine.oracle(start=served).astype(np.float64)
            converged = np.where(np.isnan(converged), warm, converged)  # NaN: outside every awake island
        else:
            converged = np.nan_to_num(engine.oracle()).astype(np.float64)
        self._now = (points["key"], converged)
        return served

    def observe(self, points_after_solve):
        keys, exact = self._now if self._now is not None else (np.zeros(0, np.uint64), np.zeros((0, 2)))
        order = np.argsort(keys)
        self._keys, self._exact = keys[order], exact[order]


def make_oracle(name: str) -> Provider:
    """oracle:VARIANT (the module docstring); ValueError for an unknown variant or a bad parameter."""
    if name in ("oracle:previous", "oracle:near-previous"):
        return PreviousOracle(near=name == "oracle:near-previous")
    return OracleMix(name.split(":", 1)[1])


register_prefix("oracle:", make_oracle, "the step's own solution mixed with Box2D's warm start: "
                f"{', '.join(ORACLES)} (lab/oracles.py)", usage="oracle:VARIANT")
