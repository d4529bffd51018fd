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
Probes of what a model could use (docs/results.md, "Where the iterations are"):
    lastchange@A builtin + A x the change the solver made to the same point's warm
                 start on the previous step (temporal information, e.g. A = -0.5)
    solve@K      builtin + K conjugate-gradient steps on this step's contact problem
                 without its limits (no friction cone, normal impulses may go
                 negative until clamped): a global linear solve, as a model with
                 unlimited reach could at best learn it
    solve-active@K  the same on the contacts Box2D's warm start says are active:
                 normal impulses only where it is > 0 (or the point is new), tangent
                 ones only where last step's friction was inside the cone
    jitter@S     builtin + Gaussian noise of S N s at persisting points (seeded): a
                 control for pick:, candidates that know nothing
    prestress@M  builtin + a self-stress (impulses that move no body) that lifts every
                 pressing point's normal impulse toward at least M N s where it is below:
                 the part of that lift that moves no body (deepcontact.kinematics.body_space_part).
                 Does any self-stress that keeps contacts off their limits pay, or only the
                 solution's own?
    preload@M    the same with a lift of M N s at every pressing point, whatever its load
    rest-admissible  a motion guessed without the solution, then admitted: every touching body
                 slower than REST_SPEED (m/s) brought to rest by its contacts (their net impulse and
                 torque cancel its velocity after gravity), every other body moved as Box2D's warm
                 start moves it; the least-norm change to Box2D's warm start with that motion, then
                 the smallest self-stress that brings every point inside its cone (as
                 oracle:near-admissible does with the solution's motion)
Oracle experiments (where a warm start's value lies; docs/results.md):
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
Remote:
    server:NAME  the warm-start server's model or provider NAME (see `ListModels`);
                 `server:grid-identity` is sent the oracle's impulses (thesis's Grid)
Oracle over warm starts:
    pick:W1+W2+...  each step, the engine solves the step from Box2D's warm start and
                 from each of W1, W2, ... (any warm starts above, e.g. server:default;
                 trial solves, the world unchanged) and keeps the one that takes the
                 fewest iterations (builtin on a tie): what a perfect per-step choice
                 among them is worth. A solve per candidate; not one a server could serve
    shadow:W1+W2+...  serves W1 every step, as W1 alone would, and trial-solves builtin
                 and the others beside it: each against builtin on W1's own trajectory
    mean:W1+W2+...  serves the mean of W1, W2, ... and trial-solves builtin, each of them
                 and the mean on the same states: does averaging two kinds of guess pay?
    price:W1+W2+...  serves builtin, so its steps are Builtin's own, and trial-solves
                 W1, W2, ... beside it: every model priced on one set of states, the same
                 in every run, so two models (or two checkpoints) measured apart are
                 compared step by step, with no trajectory between them
    split:W      serves W, as W alone would, and trial-solves builtin, W, and the two
                 parts of W's correction (W - builtin) each alone on Box2D's warm start:
                 the part that moves the bodies and the self-stress that moves none
                 (oracle:body-space, oracle:self-stress): which part of a model's
                 correction pays
    boost:W      serves W, as W alone would, and trial-solves builtin, W, and W's
                 correction with its self-stress part scaled by 0.5, 1.5, 2 and 3 (the part
                 that moves the bodies kept): is a model's self-stress right in direction
                 and short in size?
    admit:W      serves W, as W alone would, and trial-solves builtin, W, and three
                 admissible forms of it (deepcontact.kinematics.nearest_admissible): W
                 moved by the smallest self-stress that brings every point inside its
                 friction cone; builtin plus W's body-space part moved the same way
                 (W's motion, the self-stress chosen by the limits alone); and that with
                 the points W's motion pulls apart held at 0 (oracle:near-admissible-separating's rule);
                 and builtin plus W's motion at the moving bodies only, Box2D's at the others,
                 admitted (oracle:near-admissible-moving's split), and the same not admitted
                 (normal impulses clamped at 0 only): does the admission pay, or the split?
    graft:W1+W2  serves W1, as W1 alone would, and trial-solves builtin, W1, W2, and W1 with W2's
                 motion at the moving bodies (W1 plus the least-norm change that moves them as W2
                 does and no other body), admitted and not: one model's self-stress and resting
                 bodies with another's moving bodies
"""

from __future__ import annotations

import numpy as np

from deepcontact.kinematics import REST_SPEED, points_at_rest

LOCAL = ("none", "builtin", "copy", "copy2", "copy0", "extrapolate", "lastchange@A", "solve@K", "solve-active@K",
         "jitter@S", "prestress@M", "preload@M", "rest-admissible")
ORACLES = ("persisting", "new", "normal", "tangent", "heavy", "half", "grid@RES", "small@T", "big@T", "noisy@S",
           "relnoisy@R", "previous", "some@F", "settled", "moving", "body-space", "self-stress", "near",
           "near-body-space", "near-self-stress", "near-previous", "near-release", "near-switch", "near-cone",
           "near-inside", "near-admissible", "near-admissible-open", "near-admissible-separating", "near-admissible-moving",
           "near-admissible-settled", "near-admissible@R",
           "near-admissible-abs@S")
#: Oracle variants that take a parameter after "@", and what it is.
_ORACLE_PARAMETERS = {"grid": "a grid spacing in m, e.g. oracle:grid@0.5",
                      "small": "a correction size in N s, e.g. oracle:small@1",
                      "big": "a correction size in N s, e.g. oracle:big@1",
                      "noisy": "a noise level in N s, e.g. oracle:noisy@0.05",
                      "relnoisy": "a noise level relative to the correction, e.g. oracle:relnoisy@0.5",
                      "some": "a share of the points, 0 < F <= 1, e.g. oracle:some@0.5",
                      "near-admissible": "a noise level relative to the motion, e.g. oracle:near-admissible@0.5",
                      "near-admissible-abs": "a noise level in N s, e.g. oracle:near-admissible-abs@0.2"}
#: oracle:near-release and -switch: a normal impulse above this (N s) presses; at or below, the contact is open.
SWITCH_IMPULSE = 1e-6
#: oracle:near-admissible-separating: a point whose normal velocity after the motion is above this (m/s) lets go;
#: a thousandth of a metre a second, ten times what the stopping rule's 1e-4 N s leaves at a point of about 1 kg.
SEPARATING_SPEED = 1e-3
#: oracle:near-cone and -inside, solve-active@K: friction at this share of its limit or more slides.
CONE_SHARE = 0.99
#: oracle:noisy and oracle:relnoisy perturb the corrections of oracle:small at this size (N s).
NOISY_SMALL = 1.0


class Provider:
    name: str
    uses_server = False
    picks = False  # pick:...: the engine's trial solves choose among builtin and candidates

    def prepare(self, engine) -> None:
        """Before the first step (e.g. switch Box2D's own warm starting)."""
        engine.world.warmStarting = True

    def warm_start(self, engine, bodies, points, step):
        return None

    def observe(self, points_after_solve: np.ndarray) -> None:
        """After each solve, with the step's points and their final impulses."""


class ReadsFriction(Provider):
    """A provider that needs each point's friction coefficient (point_friction): it reads
    the bodies' from the world before the first step."""

    _friction = np.zeros(0)  # (B,) per body, creation order; set by prepare()

    def prepare(self, engine) -> None:
        super().prepare(engine)
        # pybox2d lists the bodies in creation order, the records' body index.
        self._friction = body_friction(engine)


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


class OracleMix(ReadsFriction):
    """The oracle's impulses where they say most, builtin elsewhere (see the module docstring)."""

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
        self._rng = np.random.default_rng(0)  # a fresh provider per world: the same noise every run

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            return None  # nothing to warm-start
        builtin = points["builtin"].astype(np.float64)
        if self.kind.startswith("near"):
            start = tuple(np.ascontiguousarray(builtin[:, k], np.float32) for k in (0, 1))
            exact = engine.oracle(start=start).astype(np.float64)
            exact = np.where(np.isnan(exact), builtin, exact)  # NaN: outside every awake island
        else:
            exact = np.nan_to_num(engine.oracle()).astype(np.float64)
        new = ~builtin.any(axis=1)
        correction = np.abs(exact[:, 0] - builtin[:, 0])
        v = self.kind.removeprefix("near-")
        if v in ("near", "copy"):
            warm = exact
        elif v == "persisting":
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
        elif v == "small":
            warm = np.where((correction <= self.value)[:, None], exact, builtin)
        elif v == "big":
            warm = np.where((correction > self.value)[:, None], exact, builtin)
        elif v in ("noisy", "relnoisy"):
            noise = self._rng.normal(0.0, self.value, exact.shape)
            if v == "relnoisy":
                noise *= np.abs(exact - builtin)
            warm = np.where((correction <= NOISY_SMALL)[:, None], exact + noise, builtin)
        elif v in ("settled", "moving"):
            at_rest = points_at_rest(bodies, points)
            warm = np.where((at_rest if v == "settled" else ~at_rest)[:, None], exact, builtin)
        elif v in ("release", "switch"):
            pressing, will_press = builtin[:, 0] > SWITCH_IMPULSE, exact[:, 0] > SWITCH_IMPULSE
            if v == "release":
                warm = np.where((pressing & ~will_press)[:, None], 0.0, builtin)
            else:
                warm = np.where((pressing != will_press)[:, None], exact, builtin)
        elif v in ("cone", "inside"):
            mu = point_friction(self._friction, points)
            cone = at_friction_cone(builtin, mu) | at_friction_cone(exact, mu)
            warm = np.where((cone if v == "cone" else ~cone)[:, None], exact, builtin)
        elif v in ("admissible", "admissible-open", "admissible-separating", "admissible-abs", "admissible-moving",
                   "admissible-settled"):
            from deepcontact.kinematics import (Physics, bodies_moving, body_space_part, body_space_part_of,
                                                contact_velocities, nearest_admissible)

            if v in ("admissible-moving", "admissible-settled"):
                moving = bodies_moving(bodies)
                moves = body_space_part_of(bodies, points, exact - builtin, moving if v == "admissible-moving" else ~moving)
            else:
                moves = body_space_part(bodies, points, exact - builtin)
            released = None
            if v == "admissible-open":
                released = exact[:, 0] <= SWITCH_IMPULSE
            elif v == "admissible-separating":
                physics = Physics(engine.config.dt, tuple(engine.world.gravity))
                released = contact_velocities(bodies, points, builtin + moves, physics)[:, 0] > SEPARATING_SPEED
            if self.value:  # oracle:near-admissible@R, oracle:near-admissible-abs@S
                size = 1.0 if v == "admissible-abs" else np.sqrt(np.mean(moves ** 2))
                moves = body_space_part(bodies, points, moves + self._rng.normal(0.0, self.value * size, moves.shape))
            warm = nearest_admissible(bodies, points, builtin + moves, point_friction(self._friction, points), released)
        elif v in ("body-space", "self-stress"):
            from deepcontact.kinematics import body_space_part

            moves = body_space_part(bodies, points, exact - builtin)
            warm = builtin + (moves if v == "body-space" else exact - builtin - moves)
            warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        elif v == "some":
            served = self._rng.random(len(points)) < self.value
            warm = np.where(served[:, None], exact, builtin)
        else:
            from deepcontact.gridspec import GridSpec
            from deepcontact.transfer import plan

            # A grid from the scenes' origin (their box's lower-left corner) over every point.
            res = self.value
            reach = np.ceil(points["point"].max(axis=0) / res) * res + res
            spec = GridSpec.for_domain((0.0, 0.0), tuple(np.maximum(reach, res)), res, 2 * res)
            pl = plan(points["point"], spec, outside="drop")
            warm = builtin + pl.g2p(pl.p2g(exact - builtin)[0])[0]
        return _as_warm_start(warm)


def body_friction(engine) -> np.ndarray:
    """(B,) each body's friction coefficient; pybox2d lists the bodies in creation order, the records' body index."""
    return np.array([b.fixtures[0].friction if b.fixtures else 0.0 for b in engine.world.bodies])


def point_friction(friction: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) the friction coefficient at each point: Box2D mixes two fixtures' as sqrt(f_A f_B)."""
    return np.sqrt(friction[points["body_a"]] * friction[points["body_b"]])


def at_friction_cone(impulses: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(P,) bool: the point presses (normal > SWITCH_IMPULSE) and its tangent impulse is at
    CONE_SHARE of mu times the normal one or more. impulses: (P, 2) N s."""
    return (impulses[:, 0] > SWITCH_IMPULSE) & (np.abs(impulses[:, 1]) >= CONE_SHARE * mu * impulses[:, 0])


def _as_warm_start(warm: np.ndarray):
    """(P, 2) impulses (N s) as the (normal, tangent) float32 pair the engine takes."""
    warm = warm.astype(np.float32)
    return np.ascontiguousarray(warm[:, 0]), np.ascontiguousarray(warm[:, 1])


class LastChange(Provider):
    """Builtin plus `alpha` times what the solver changed at the same point on the
    previous step (its final impulse minus where it started), matched by key.

    A large correction is often partly undone one step later, hence a negative
    alpha (docs/results.md, "Where the iterations are").
    """

    def __init__(self, alpha: float):
        self.alpha = alpha
        self.name = f"lastchange@{alpha:g}"
        self._keys = np.zeros(0, np.uint64)  # sorted keys of the previous step's points ...
        self._change = np.zeros((0, 2))  # ... and the solver's change at each, N s

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            return None
        builtin = points["builtin"].astype(np.float64)
        warm = builtin.copy()
        if len(self._keys):
            idx = np.searchsorted(self._keys, points["key"]).clip(max=len(self._keys) - 1)
            persisting = (self._keys[idx] == points["key"]) & builtin.any(axis=1)
            warm[persisting] += self.alpha * self._change[idx[persisting]]
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        return _as_warm_start(warm)

    def observe(self, points_after_solve):
        order = np.argsort(points_after_solve["key"])
        after = points_after_solve[order]
        self._keys = after["key"]
        self._change = np.nan_to_num(after["impulse"].astype(np.float64) - after["warm_start"])


class LinearSolve(ReadsFriction):
    """Builtin plus `iterations` conjugate-gradient steps on this step's contact
    problem without its limits: find the correction c (P, 2) that leaves no
    relative velocity at any point, A c = -v, with A = J M^-1 J^T (both
    directions of every point) and v the points' relative velocity after
    gravity and Box2D's warm start. Normal impulses are clamped at 0 and
    tangent ones to the friction cone afterwards (friction from the scene).
    It is the global solve a model with unlimited reach could at best
    learn, minus the contact problem's limits. With `active`, only the
    unknowns Box2D's warm start says are free take part: the normal impulse
    where it is > 0 or the point is new, the tangent one where it was also
    inside the friction cone (below 0.99 of its limit) or the point is new;
    the others keep Box2D's values (last step's active set).
    """

    def __init__(self, iterations: int, active: bool = False):
        self.iterations, self.active = iterations, active
        self.name = f"solve{'-active' if active else ''}@{iterations}"

    def warm_start(self, engine, bodies, points, step):
        from deepcontact.kinematics import Physics, contact_frame, contact_velocities

        if len(points) == 0:
            return None
        frame = contact_frame(bodies, points)
        gravity = engine.world.gravity
        physics = Physics(engine.config.dt, (float(gravity[0]), float(gravity[1])))
        builtin = points["builtin"].astype(np.float64)
        still = bodies.copy()
        still["velocity"], still["angular_velocity"] = 0.0, 0.0

        free = np.ones_like(builtin)  # (P, 2): 1 where the unknown takes part
        if self.active:
            new = ~builtin.any(axis=1)
            limit = point_friction(self._friction, points) * builtin[:, 0]
            free[:, 0] = (builtin[:, 0] > 0) | new
            free[:, 1] = (free[:, 0] > 0) & ((np.abs(builtin[:, 1]) < CONE_SHARE * limit) | new)

        def delassus(x):  # A x on the free unknowns: the relative velocities impulses x alone cause, (P, 2) m/s
            return contact_velocities(still, points, warm=x * free, frame=frame) * free

        residual = -contact_velocities(bodies, points, warm=builtin, physics=physics, frame=frame) * free
        correction = np.zeros_like(builtin)
        direction = residual.copy()
        rr = float((residual * residual).sum())
        for _ in range(self.iterations):  # conjugate-gradient steps, not points
            ad = delassus(direction)
            dad = float((direction * ad).sum())
            if rr <= 1e-30 or dad <= 1e-30:
                break
            step_size = rr / dad
            correction += step_size * direction
            residual -= step_size * ad
            rr_next = float((residual * residual).sum())
            direction = residual + (rr_next / rr) * direction
            rr = rr_next
        warm = builtin + correction
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        limit = point_friction(self._friction, points) * warm[:, 0]
        warm[:, 1] = np.clip(warm[:, 1], -limit, limit)
        return _as_warm_start(warm)


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
        builtin = points["builtin"].astype(np.float64)
        warm = builtin.copy()
        if len(self._keys):
            idx = np.searchsorted(self._keys, points["key"]).clip(max=len(self._keys) - 1)
            persisting = (self._keys[idx] == points["key"]) & builtin.any(axis=1)
            warm[persisting] = self._exact[idx[persisting]]
        served = _as_warm_start(warm)
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


class Jitter(Provider):
    """Builtin plus Gaussian noise of `sigma` N s on both impulses at persisting
    points (normal clamped at 0): a control for pick:, whose candidates differ
    from Box2D's warm start by nothing a model knows."""

    def __init__(self, sigma: float, seed: int = 0):
        self.sigma = sigma
        self.name = f"jitter@{sigma:g}"
        self.reseed(seed)

    def reseed(self, seed: int) -> None:
        self._rng = np.random.default_rng(seed)  # a fresh provider per world: the same noise every run

    def warm_start(self, engine, bodies, points, step):
        if len(points) == 0:
            return None
        builtin = points["builtin"].astype(np.float64)
        persisting = builtin.any(axis=1)[:, None]
        warm = builtin + np.where(persisting, self._rng.normal(0.0, self.sigma, builtin.shape), 0.0)
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        return _as_warm_start(warm)


class Prestress(Provider):
    """Builtin plus a self-stress chosen without the solution: the part of a lift of the
    pressing points' normal impulses that moves no body. `floor`: lift each to at least
    `impulse` N s; else lift every one by `impulse` N s. Normal clamped at 0 after."""

    def __init__(self, impulse: float, floor: bool = True):
        self.impulse, self.floor = impulse, floor
        self.name = f"{'prestress' if floor else 'preload'}@{impulse:g}"

    def warm_start(self, engine, bodies, points, step):
        from deepcontact.kinematics import body_space_part

        if len(points) == 0:
            return None
        builtin = points["builtin"].astype(np.float64)
        pressing = builtin[:, 0] > SWITCH_IMPULSE
        lift = np.zeros_like(builtin)
        lift[:, 0] = np.where(pressing, np.maximum(self.impulse - builtin[:, 0], 0.0) if self.floor else self.impulse, 0.0)
        warm = builtin + lift - body_space_part(bodies, points, lift)
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        return _as_warm_start(warm)


class RestAdmissible(ReadsFriction):
    """A settled pile's motion guessed from its velocities alone, then admitted (module docstring).

    A pile whose contacts all press and stick comes to rest: after a converged solve its
    bodies do not move. So a slow body's contacts must cancel its momentum after gravity,
    -m (v + g dt) and -I w, whatever the solution's self-stress; nearest_admissible then
    chooses the self-stress from the limits. Bodies that move keep Box2D's warm start's motion.
    """

    name = "rest-admissible"

    def warm_start(self, engine, bodies, points, step):
        from deepcontact.kinematics import contact_frame, contact_jacobian, nearest_admissible

        if len(points) == 0:
            return None
        builtin = points["builtin"].astype(np.float64)
        frame = contact_frame(bodies, points)
        jt = contact_jacobian(bodies, points, frame)  # (3 D, 2 P)
        dynamic = np.flatnonzero(frame.dynamic)
        target = (jt @ builtin.ravel()).reshape(-1, 3)  # (D, 3) N s, N s, N m s: Box2D's warm start's motion
        gravity = np.asarray(engine.world.gravity, np.float64) * engine.config.dt
        velocity = bodies["velocity"][dynamic].astype(np.float64)
        touching = np.abs(jt).reshape(len(dynamic), -1).any(axis=1)
        slow = touching & (np.hypot(*velocity.T) < REST_SPEED)
        mass, inertia = bodies["mass"][dynamic].astype(np.float64), bodies["inertia"][dynamic].astype(np.float64)
        target[slow, :2] = -mass[slow, None] * (velocity[slow] + gravity)
        target[slow, 2] = -inertia[slow] * bodies["angular_velocity"][dynamic][slow]
        # The least-norm change with that motion (least squares where a body's points cannot give it).
        change, *_ = np.linalg.lstsq(jt, target.ravel() - jt @ builtin.ravel(), rcond=None)
        warm = nearest_admissible(bodies, points, builtin + change.reshape(-1, 2), point_friction(self._friction, points),
                                  frame=frame)
        return _as_warm_start(warm)


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


class Pick(Provider):
    """An oracle over warm starts: each step, the engine solves the step from
    Box2D's warm start and from each candidate's (trial solves, the world
    unchanged) and keeps the one that takes the fewest iterations (builtin on
    a tie). simclient.simulate asks every candidate, then calls pick()."""

    picks = True

    MODES = ("pick", "shadow", "mean", "price", "split", "boost", "admit", "graft")
    #: boost:W: the factors its self-stress part is priced at.
    BOOSTS = (0.5, 1.5, 2.0, 3.0)
    PREFIXES = tuple(f"{m}:" for m in MODES)

    def __init__(self, candidates: list[Provider], mode: str = "pick"):
        if mode not in self.MODES:
            raise ValueError(f"mode must be one of {self.MODES}, got {mode!r}")
        self.candidates = candidates
        # pick: serve the cheapest; shadow: serve the first, price the others beside it;
        # mean: serve the candidates' mean, price it and each of them on the same state;
        # price: serve builtin, price the candidates on its states (the same states for every
        # model and every run: a paired, trajectory-free comparison of any two models);
        # split: serve the one candidate, price it and the two parts of its correction;
        # boost: serve the one candidate, price it with its self-stress part scaled;
        # admit: serve the one candidate, price it and its admissible forms;
        # graft: serve the first, price it with the second's moving bodies' motion
        if mode in ("split", "boost", "admit") and len(candidates) != 1:
            raise ValueError(f"{mode}: takes one warm start, e.g. {mode}:server:default, got {len(candidates)}")
        if mode == "graft" and len(candidates) != 2:
            raise ValueError(f"graft: takes two warm starts, e.g. graft:server:default+server:graph-mse-1-799-moving-rel, "
                             f"got {len(candidates)}")
        self.mode = mode
        for i, c in enumerate(candidates):
            if isinstance(c, Jitter):
                c.reseed(i)  # two jitters in one pick draw different noise
        self.name = f"{mode}:" + "+".join(c.name for c in candidates)
        self.uses_server = any(c.uses_server for c in candidates)
        self.sends_oracle = False
        self.trials: list[list[int]] = []  # per step with contacts: builtin's, then each candidate's iterations

    @property
    def models(self) -> tuple[str, ...]:
        return tuple(m for c in self.candidates if c.uses_server for m in c.models)

    @property
    def labels(self) -> list[str]:
        """What each entry of a trials row priced: builtin, the candidates (and their mean)."""
        first = self.candidates[0].name
        extra = {"mean": ["mean"], "split": [f"{first} body-space", f"{first} self-stress"],
                 "boost": [f"{first} self-stress x{k:g}" for k in self.BOOSTS],
                 "admit": [f"{first} admissible", f"{first} body-space admissible",
                           f"{first} body-space admissible, separating open",
                           f"{first} moving bodies' motion admissible", f"{first} moving bodies' motion"],
                 "graft": [f"{first} with {self.candidates[-1].name}'s moving bodies' motion admissible",
                           f"{first} with {self.candidates[-1].name}'s moving bodies' motion"]}.get(self.mode, [])
        return ["builtin", *(c.name for c in self.candidates)] + extra

    @property
    def model(self) -> str:
        return self.models[0] if self.models else ""

    def prepare(self, engine) -> None:
        self._friction = body_friction(engine)
        for c in self.candidates:
            c.prepare(engine)

    def observe(self, points_after_solve):
        for c in self.candidates:
            c.observe(points_after_solve)

    def pick(self, engine, points, served: list) -> tuple[np.ndarray, np.ndarray]:
        """The best for this step, by trial solves, of Box2D's warm start and the
        candidates' (`served`: (normal, tangent) each, or None for Box2D's own)."""
        builtin = (np.ascontiguousarray(points["builtin"][:, 0]), np.ascontiguousarray(points["builtin"][:, 1]))
        candidates = [builtin] + [builtin if w is None else w for w in served]
        if self.mode == "mean":
            normal = np.mean([w[0] for w in candidates[1:]], axis=0, dtype=np.float64)
            tangent = np.mean([w[1] for w in candidates[1:]], axis=0, dtype=np.float64)
            candidates.append(_as_warm_start(np.stack([normal, tangent], axis=1)))
        if self.mode == "admit":
            from deepcontact.kinematics import (Physics, bodies_moving, body_space_part, body_space_part_of,
                                                contact_velocities, nearest_admissible)

            bodies, mu = engine.bodies(), point_friction(self._friction, points)
            start = np.stack(candidates[0], axis=1).astype(np.float64)
            served = np.stack(candidates[1], axis=1).astype(np.float64)
            motion = start + body_space_part(bodies, points, served - start)
            moving = start + body_space_part_of(bodies, points, served - start, bodies_moving(bodies))
            physics = Physics(engine.config.dt, tuple(engine.world.gravity))
            separating = contact_velocities(bodies, points, motion, physics)[:, 0] > SEPARATING_SPEED
            candidates += [_as_warm_start(nearest_admissible(bodies, points, w, mu, o))
                           for w, o in ((served, None), (motion, None), (motion, separating), (moving, None))]
            candidates.append(_as_warm_start(np.column_stack([np.maximum(moving[:, 0], 0.0), moving[:, 1]])))
        if self.mode == "graft":
            from deepcontact.kinematics import bodies_moving, body_space_part_of, nearest_admissible

            bodies = engine.bodies()
            base, donor = (np.stack(w, axis=1).astype(np.float64) for w in candidates[1:3])
            grafted = base + body_space_part_of(bodies, points, donor - base, bodies_moving(bodies))
            candidates += [_as_warm_start(nearest_admissible(bodies, points, grafted, point_friction(self._friction, points))),
                           _as_warm_start(np.column_stack([np.maximum(grafted[:, 0], 0.0), grafted[:, 1]]))]
        if self.mode in ("split", "boost"):
            from deepcontact.kinematics import body_space_part

            start = np.stack(candidates[0], axis=1).astype(np.float64)
            correction = np.stack(candidates[1], axis=1).astype(np.float64) - start
            moves = body_space_part(engine.bodies(), points, correction)
            stress = correction - moves
            parts = (moves, stress) if self.mode == "split" else [moves + k * stress for k in self.BOOSTS]
            for part in parts:
                warm = start + part
                warm[:, 0] = np.maximum(warm[:, 0], 0.0)
                candidates.append(_as_warm_start(warm))
        iterations = [engine.trial(*w) for w in candidates]
        self.trials.append(iterations)
        if self.mode in ("shadow", "split", "boost", "admit", "graft"):
            return candidates[1]
        if self.mode == "price":
            return builtin  # the trials left the last candidate's as the step's warm start
        if self.mode == "mean":
            return candidates[-1]
        return candidates[int(np.argmin(iterations))]  # argmin: the first, builtin, on a tie


def make_provider(name: str) -> Provider:
    """ValueError for an unknown name."""
    for prefix in Pick.PREFIXES:
        if name.startswith(prefix):
            names = [n for n in name[len(prefix):].split("+") if n]
            if not names or any(n.startswith(Pick.PREFIXES) for n in names):
                raise ValueError(f"{prefix} takes warm starts joined by +, e.g. {prefix}server:default+server:pressure, "
                                 f"got {name!r}")
            if any(n in ("none", "builtin") for n in names):
                raise ValueError(f"{prefix} always tries builtin; for zeros use server:zero, got {name!r}")
            return Pick([make_provider(n) for n in names], mode=prefix[:-1])
    if name.startswith("server:"):
        model = name.split(":", 1)[1]
        if not model:
            raise ValueError("server: needs a model name, e.g. server:pressure")
        return Remote(model)
    if name in ("oracle:previous", "oracle:near-previous"):
        return PreviousOracle(near=name == "oracle:near-previous")
    if name.startswith("oracle:"):
        return OracleMix(name.split(":", 1)[1])
    for prefix, parse, make, what in (
            ("lastchange@", float, LastChange, "a factor, e.g. lastchange@-0.5"),
            ("jitter@", float, Jitter, "a noise level in N s, e.g. jitter@0.01"),
            ("prestress@", float, Prestress, "an impulse in N s, e.g. prestress@0.05"),
            ("preload@", float, lambda m: Prestress(m, floor=False), "an impulse in N s, e.g. preload@0.05"),
            ("solve@", int, LinearSolve, "a number of iterations, e.g. solve@10"),
            ("solve-active@", int, lambda k: LinearSolve(k, active=True), "a number of iterations, e.g. solve-active@20")):
        if name.startswith(prefix):
            try:
                value = parse(name[len(prefix):])
            except ValueError:
                raise ValueError(f"{prefix}... needs {what}, got {name!r}") from None
            if (parse is int and value < 1) or (parse is float and prefix != "lastchange@" and not value > 0):
                raise ValueError(f"{prefix}... needs {what}, got {name!r}")
            return make(value)
    factories = {
        "none": NoWarmStart,
        "builtin": Builtin,
        "copy": lambda: Copy("copy", None),
        "copy2": lambda: Copy("copy2", 2),
        "copy0": lambda: Copy("copy0", 0),
        "extrapolate": Extrapolate,
        "rest-admissible": RestAdmissible,
    }
    if name not in factories:
        raise ValueError(f"unknown warm start {name!r}: use one of {', '.join(LOCAL)}, oracle:VARIANT "
                         f"({', '.join(ORACLES)}) or server:MODEL")
    return factories[name]()
