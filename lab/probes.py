"""Probes of what a warm start could use: each builtin plus something a model might learn,
or a guess made without the solution (docs/research/2026-11-23-where-the-iterations-are.md,
2026-11-28-probes.md). Registered with simclient.warmstarts when `lab` is imported.

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
"""

from __future__ import annotations

import numpy as np

from deepcontact.kinematics import REST_SPEED
from simclient.provider import (CONE_SHARE, SWITCH_IMPULSE, Provider, ReadsFriction, as_warm_start, persisting_rows,
                                point_friction)
from simclient.warmstarts import register_name, register_prefix


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
        warm = points["builtin"].astype(np.float64)
        idx, persisting = persisting_rows(self._keys, points)
        warm[persisting] += self.alpha * self._change[idx[persisting]]
        warm[:, 0] = np.maximum(warm[:, 0], 0.0)
        return as_warm_start(warm)

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
        from deepcontact.kinematics import Physics, contact_velocities

        if len(points) == 0:
            return None
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
            return contact_velocities(still, points, warm=x * free) * free

        residual = -contact_velocities(bodies, points, warm=builtin, physics=physics) * free
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
        return as_warm_start(warm)


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
        return as_warm_start(warm)


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
        return as_warm_start(warm)


class RestAdmissible(ReadsFriction):
    """A settled pile's motion guessed from its velocities alone, then admitted (module docstring).

    A pile whose contacts all press and stick comes to rest: after a converged solve its
    bodies do not move. So a slow body's contacts must cancel its momentum after gravity,
    -m (v + g dt) and -I w, whatever the solution's self-stress; nearest_admissible then
    chooses the self-stress from the limits. Bodies that move keep Box2D's warm start's motion.
    """

    name = "rest-admissible"

    def warm_start(self, engine, bodies, points, step):
        from deepcontact.admission import nearest_admissible
        from deepcontact.kinematics import contact_frame, contact_jacobian

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
        return as_warm_start(warm)


def _parametrized(prefix: str, parse, make, what: str, positive: bool = True):
    """A factory for PREFIX<value>: the value parsed and checked (> 0 where `positive`; an
    integer >= 1), or ValueError saying what it needs."""

    def factory(name: str) -> Provider:
        try:
            value = parse(name[len(prefix):])
        except ValueError:
            raise ValueError(f"{prefix}... needs {what}, got {name!r}") from None
        if (parse is int and value < 1) or (parse is float and positive and not value > 0):
            raise ValueError(f"{prefix}... needs {what}, got {name!r}")
        return make(value)

    return factory


for _prefix, _parse, _make, _what, _usage, _help in (
        ("lastchange@", float, LastChange, "a factor, e.g. lastchange@-0.5", "lastchange@A",
         "builtin + A x the solver's change at the same point on the previous step"),
        ("solve@", int, LinearSolve, "a number of iterations, e.g. solve@10", "solve@K",
         "builtin + K conjugate-gradient steps on the step's contact problem without its limits"),
        ("solve-active@", int, lambda k: LinearSolve(k, active=True), "a number of iterations, e.g. solve-active@20",
         "solve-active@K", "the same on the contacts Box2D's warm start says are active"),
        ("jitter@", float, Jitter, "a noise level in N s, e.g. jitter@0.01", "jitter@S",
         "builtin + Gaussian noise of S N s at persisting points (seeded): a control"),
        ("prestress@", float, Prestress, "an impulse in N s, e.g. prestress@0.05", "prestress@M",
         "builtin + a self-stress lifting each pressing point toward at least M N s"),
        ("preload@", float, lambda m: Prestress(m, floor=False), "an impulse in N s, e.g. preload@0.05", "preload@M",
         "builtin + a self-stress lifting every pressing point by M N s")):
    register_prefix(_prefix, _parametrized(_prefix, _parse, _make, _what, positive=_prefix != "lastchange@"), _help,
                    usage=_usage)
register_name("rest-admissible", RestAdmissible,
              "a motion guessed without the solution (slow bodies at rest), then admitted into the cones")
