"""The patched Box2D engine, seen from NumPy.

One `Engine` wraps one `Box2D.b2World` built from the deepcontact patch
(`box2d/deepcontact.patch`). A step is two phases:

    n = engine.collide()            # narrow phase: this step's contact points
    bodies = engine.bodies()        # (B,) BODY_DTYPE, creation order
    points = engine.contacts()      # (n,) CONTACT_DTYPE, export order
    engine.set_warm_start(jn, jt)   # optional: (n,) float32 each, N s
    stats = engine.solve()          # island solver; StepStats

`engine.step()` is `collide()` + `solve()` with Box2D's own warm start.
Every array crosses the SWIG boundary in one call; nothing here loops over
bodies or contacts in Python.

Importing this module with a stock pybox2d fails at once: the project needs
the patched build (`make box2d`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

PATCH_REVISION = 3
"""Layout revision of the patch this module speaks (B2_DEEPCONTACT_REVISION)."""

_BUILD_HINT = (
    "deepcontact needs the patched Box2D (box2d-py 2.3.8+deepcontact.{rev}). "
    "Build and install it with `make box2d` from the repository root "
    "(or `make test`, which does it on first use)."
)

try:
    import Box2D
except ImportError as exc:  # pragma: no cover - depends on the environment
    raise ImportError("Box2D is not installed. " + _BUILD_HINT.format(rev=PATCH_REVISION)) from exc

if not hasattr(Box2D, "DeepContactLayout"):
    raise ImportError(
        f"Box2D {getattr(Box2D, '__version__', '?')} is the stock build. "
        + _BUILD_HINT.format(rev=PATCH_REVISION)
    )

from deepcontact.records import BODY_DTYPE, CONTACT_DTYPE  # noqa: E402  (after the Box2D check)

_revision, _body_bytes, _contact_bytes = Box2D.DeepContactLayout()
if (_revision, _body_bytes, _contact_bytes) != (PATCH_REVISION, BODY_DTYPE.itemsize, CONTACT_DTYPE.itemsize):
    raise ImportError(
        f"patched Box2D layout {(_revision, _body_bytes, _contact_bytes)} does not match this "
        f"checkout's {(PATCH_REVISION, BODY_DTYPE.itemsize, CONTACT_DTYPE.itemsize)}. "
        + _BUILD_HINT.format(rev=PATCH_REVISION)
    )


@dataclasses.dataclass(frozen=True)
class SolverConfig:
    """How each step is solved.

    velocity_threshold: stop the velocity iterations after the first sweep
        whose largest impulse change (N s, infinity norm over normal and
        tangent components of all points) is <= this; < 0 disables.
    position_threshold: likewise for the position iterations (largest
        positional impulse), besides Box2D's own separation test; < 0 disables.
    statistics: record the residual trace even when no threshold is set.
    """

    dt: float = 0.01
    velocity_iterations: int = 1000
    position_iterations: int = 1000
    velocity_threshold: float = 1e-4
    position_threshold: float = -1.0
    statistics: bool = True

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be a positive number of seconds, got {self.dt}")
        if self.velocity_iterations < 1 or self.position_iterations < 0:
            raise ValueError(
                "velocity_iterations must be >= 1 and position_iterations >= 0, got "
                f"{self.velocity_iterations} and {self.position_iterations}"
            )

    @property
    def stopping_tolerance(self) -> float:
        """The velocity iterations' stopping rule as a stream declares it (World.solver_tolerance,
        N s): velocity_threshold, or 0 where it is disabled (the solver then runs to its cap)."""
        return max(float(self.velocity_threshold), 0.0)


@dataclasses.dataclass(frozen=True)
class StepStats:
    """What the solver did in one step.

    Islands are solved independently: `velocity_iterations` is the max over
    islands, `velocity_iterations_sum` the sum, and `residual_trace[k]` the
    largest impulse change (N s) at iteration k over the islands still
    iterating (empty when the step ran untracked).
    """

    contact_points: int
    islands: int
    velocity_iterations: int
    velocity_iterations_sum: int
    position_iterations: int
    residual_trace: np.ndarray  # (velocity_iterations,) float32, N s
    collide_ms: float
    solve_ms: float

    @classmethod
    def _from_world(cls, world: "Box2D.b2World") -> "StepStats":
        raw = world.GetSolverStats()
        profile = world.GetProfile()
        return cls(
            contact_points=raw["points"],
            islands=raw["islands"],
            velocity_iterations=raw["velocity_iterations"],
            velocity_iterations_sum=raw["velocity_iterations_sum"],
            position_iterations=raw["position_iterations"],
            residual_trace=np.frombuffer(raw["residual_trace"], dtype=np.float32),
            collide_ms=float(profile.collide),
            solve_ms=float(profile.solve),
        )


class Engine:
    """One simulation: a patched `b2World` plus the solver settings.

    The world is owned by the caller's scene builder; the engine only drives
    it. `dt` and iteration limits come from `config`.
    """

    def __init__(self, world: "Box2D.b2World", config: SolverConfig = SolverConfig()):
        self.world = world
        self.step_index = 0
        self._friction: np.ndarray | None = None  # body_friction(), read once
        self._restitution: np.ndarray | None = None  # point_restitution()'s bodies', read once
        self._inv_dt0 = np.float32(0.0)  # 1 / the last solved step's dt, as Box2D keeps it (0 before the first)
        self.configure(config)

    def configure(self, config: SolverConfig) -> None:
        """Solve the next steps with these settings (a session may change dt or the
        iteration limits between steps, as world.Step's arguments allow)."""
        self.config = config
        self.world.velocityThreshold = config.velocity_threshold
        self.world.positionThreshold = config.position_threshold
        self.world.solverStatistics = config.statistics

    # -- phase 1 ---------------------------------------------------------
    def collide(self) -> int:
        """Run this step's narrow phase; returns the number of contact points."""
        return self.world.Collide()

    def bodies(self) -> np.ndarray:
        """All bodies, creation order: (B,) BODY_DTYPE."""
        out = np.empty(self.world.bodyCount, dtype=BODY_DTYPE)
        self.world.ExportBodies(out)
        return out

    def awake(self) -> np.ndarray:
        """(B,) bool, creation order: the body is awake (static bodies never are). A step's points
        that touch no awake body are not solved: nothing to warm-start there."""
        out = np.empty(self.world.bodyCount, np.uint8)
        if len(out):
            self.world.ExportAwake(out)
        return out.view(bool)

    def joints(self) -> np.ndarray:
        """Each joint's body A and body B, creation-order indices: (J, 2) int32, the world's joint order."""
        out = np.empty((self.world.jointCount, 2), np.int32)
        if len(out):
            self.world.ExportJoints(out)
        return out

    def revolute(self) -> np.ndarray:
        """Each joint as its next solve will hold it, where the server's copy of a step holds its
        kind: (J, 15) float32, the world's joint order (`joints()`): its kind (1 revolute, 2 rigid
        weld, 3 prismatic; else 0 and the row's rest 0), its anchor on body A and on body B
        (world, m), the first two components of its impulse (the joint's warm start: a revolute
        or weld joint's point impulse on body B, world, N s; a prismatic joint's across its axis,
        N s, and its angular one, N m s); then its limit's state (0 off or inactive, 1 at its
        lower angle or translation, 2 at its upper, 3 equal limits; a rigid weld's angle 3), the
        limit's impulse (N m s, a prismatic joint's N s), 1 where its motor is on, the motor's
        impulse, its largest torque (N m) or force (N), its speed (rad/s or m/s) and a prismatic
        joint's axis (world). What a request's joint_revolute (the first 7) and joint_limits (the
        last 8) carry."""
        point = np.empty((self.world.jointCount, 7), np.float32)
        limit = np.empty((self.world.jointCount, 8), np.float32)
        if len(point):
            self.world.ExportRevolute(point)
            self.world.ExportRevoluteLimits(limit)
        return np.concatenate([point, limit], 1)

    def joint_state(self) -> bytes:
        """Every joint object as it is now (their impulses, the joints' warm start for the next
        solve or trial, among their other fields), for `set_joint_state` on this same world."""
        return self.world.GetJointState()

    def set_joint_state(self, state: bytes) -> None:
        """The joints as `joint_state` gave them: a trial started with other joints is put back."""
        self.world.SetJointState(state)

    def set_revolute_impulses(self, xy: np.ndarray) -> None:
        """Start the revolute joints from these impulses: (J, 2) float32, each one's point impulse
        (N s, world frame, on body B), or (J, 3), its limit's impulse (N m s) beside it, the
        world's joint order (`joints()`). A limit's impulse is set only where the limit will be
        active at the next solve (`revolute()`'s limit state 1-3; Box2D zeroes it elsewhere); with
        (J, 2) the limits keep their own. Other kinds of joint keep their own, and so do the
        motors' impulses. Box2D's solver applies a joint's start before its sweeps as it applies
        the contacts' (the next `solve()` or trial)."""
        xy = np.ascontiguousarray(xy, np.float32)
        if xy.ndim != 2 or xy.shape[1] not in (2, 3):
            raise ValueError(f"revolute impulses are (J, 2) or (J, 3), got {xy.shape}")
        self.world.SetRevoluteImpulses(np.ascontiguousarray(xy[:, :2]).reshape(-1))
        if xy.shape[1] == 3:
            self.world.SetRevoluteLimitImpulses(np.ascontiguousarray(xy[:, 2]))

    def body_friction(self) -> np.ndarray:
        """(B,) each body's friction coefficient (its first fixture's; 0 without one), creation
        order, the records' body index. Read from pybox2d once while the body count holds: a
        loop over bodies in Python, not something to repeat every step. The project's scenes
        give each body one fixture; a live step's points carry their own friction
        (`contacts()["friction"]`, any world)."""
        if self._friction is None or len(self._friction) != self.world.bodyCount:
            self._friction = np.array([b.fixtures[0].friction if b.fixtures else 0.0 for b in self.world.bodies])
        return self._friction

    def point_restitution(self, points: np.ndarray) -> np.ndarray:
        """(P,) float32 each point's restitution, as Box2D mixes its two fixtures' (the larger),
        each body's taken from its first fixture (0 without one). The bodies' are read from
        pybox2d once while the body count holds, as body_friction's are: a body whose fixtures
        differ in restitution is read at its first one's."""
        if self._restitution is None or len(self._restitution) != self.world.bodyCount:
            self._restitution = np.array([b.fixtures[0].restitution if b.fixtures else 0.0 for b in self.world.bodies],
                                         np.float32)
        return np.maximum(self._restitution[points["body_a"]], self._restitution[points["body_b"]])

    def contacts(self) -> np.ndarray:
        """This step's contact points in export order: (n,) CONTACT_DTYPE.

        Geometry and `builtin` are from collide time; `warm_start` and
        `impulse` are filled once `solve()` has run (NaN before).
        """
        out = np.empty(self.world.contactPointCount, dtype=CONTACT_DTYPE)
        self.world.ExportContacts(out)
        return out

    def builtin_start(self) -> tuple[np.ndarray, np.ndarray]:
        """Box2D's own warm start for this step as (normal, tangent) (n,) float32 (N s): the
        points' `builtin` impulses scaled by the step's time ratio, as the solver scales them
        (float32, as Box2D computes it), so that `set_warm_start(*engine.builtin_start())`
        solves exactly as Box2D's own warm start would."""
        builtin = self.contacts()["builtin"]
        ratio = self._inv_dt0 * np.float32(self.config.dt)
        return (np.ascontiguousarray(builtin[:, 0] * ratio, np.float32),
                np.ascontiguousarray(builtin[:, 1] * ratio, np.float32))

    def set_warm_start(self, normal: np.ndarray, tangent: np.ndarray) -> None:
        """Start this step's solver from these impulses (N s), export order.

        normal, tangent: (n,) float32, C-contiguous. Wrong length, dtype or
        non-finite values raise and leave the step as it was. Negative normal
        impulses are clamped to 0 (the solver's normal impulse is >= 0).
        """
        self.world.SetWarmStart(normal, tangent)

    def oracle(self, max_iterations: int = 20000, threshold: float = 1e-6, start=None,
               keep_joints: bool = False) -> np.ndarray:
        """This step's velocity problem solved to convergence; the world is unchanged.

        start: None solves from zero (the thesis's Copy); a (normal, tangent)
        pair of (n,) float32 impulses (N s, export order) solves from there
        instead and sets it as the step's warm start, as `trial` does. A pile
        held at more points than its bodies have freedoms has many solutions:
        each start converges to its own.
        keep_joints: leave the joints as the solve left them (their impulses its converged
        ones, the next solve's or trial's joint start; `joint_state` first to put them back),
        where they are otherwise put back as they were.
        Returns (n, 2) float32: (normal, tangent) impulse per contact point
        (N s), NaN for points outside every awake island.
        """
        out = np.empty((self.world.contactPointCount, 2), dtype=np.float32)
        if start is not None:
            self.world.SetWarmStart(*start)
        self.world.SetKeepJoints(bool(keep_joints))
        try:
            self.world.SolveOracle(out, self.config.dt, int(max_iterations), float(threshold), start is not None)
        finally:
            self.world.SetKeepJoints(False)
        return out

    def trial(self, normal: np.ndarray, tangent: np.ndarray, cap: int | None = None) -> int:
        """Velocity iterations this step's solve would take from these impulses
        (N s, (n,) float32 each, export order), under this engine's limit and
        stopping rule (or at most `cap`); the world is unchanged, its joints
        included. Sets the step's warm start to them: call `set_warm_start` again
        before `solve()` to start elsewhere. Each trial costs a velocity solve.
        """
        return len(self.trial_trace(normal, tangent, cap))

    def trial_trace(self, normal: np.ndarray, tangent: np.ndarray, cap: int | None = None) -> np.ndarray:
        """As `trial`, but the trial's residual trace: (iterations,) float32, N s,
        the largest impulse change of each sweep over the islands still iterating
        (as `StepStats.residual_trace` is for a solve). Its length is the
        iteration count; at the cap, its last value is how far from converged
        that start left the step.
        """
        self.world.SetWarmStart(normal, tangent)
        limit = self.config.velocity_iterations if cap is None else max(1, min(int(cap), self.config.velocity_iterations))
        stats = self.world.SolveTrial(self.config.dt, limit, self.config.velocity_threshold)
        return np.frombuffer(stats["residual_trace"], dtype=np.float32)

    # -- phase 2 ---------------------------------------------------------
    def solve(self) -> StepStats:
        """Finish the step begun by `collide()`."""
        c = self.config
        self.world.Solve(c.dt, c.velocity_iterations, c.position_iterations)
        return self._solved()

    def step(self) -> StepStats:
        """A whole step with Box2D's own warm start (upstream `Step`)."""
        c = self.config
        self.world.Step(c.dt, c.velocity_iterations, c.position_iterations)
        return self._solved()

    def _solved(self) -> StepStats:
        self.step_index += 1
        self._inv_dt0 = np.float32(1.0) / np.float32(self.config.dt)  # Box2D's m_inv_dt0 after a step
        return StepStats._from_world(self.world)
