"""Attach a warm-start server to a world you built: `WarmStartSession`.

    from simclient import WarmStartSession

    with WarmStartSession(world, "127.0.0.1:50051", model="default") as session:
        for _ in range(steps):
            result = session.step(1 / 60, 1000, 3)    # in place of world.Step(1 / 60, 1000, 3)
        print(session.summary())

`world` is any `Box2D.b2World` of the patched build (`make box2d`). Each
`step` collides, exports the step's bodies, contact points and joints, asks
the server, injects its answer as the solver's starting impulses (Box2D's own
warm start on any failure, counted), solves, and returns the step's
`StepResult`. With `guard=True` (the default) the learned start is served only
while it beats Box2D's own on this world's steps (simclient.guard). What is
sent and what the server assumes: docs/worlds.md.
"""

from __future__ import annotations

import dataclasses
import logging
import math

from simclient.client import Refused, WarmStartClient
from simclient.engine import Box2D, Engine, SolverConfig
from simclient.guard import Guard, GuardSettings
from simclient.simulate import DECLARE_TIMEOUT_S, DEFAULT_DEADLINE_MS
from simclient.stepping import StepRecord, Stepper, summarize
from simclient.warmstarts import Remote
from simclient.worlds import describe

log = logging.getLogger("deepcontact.session")


@dataclasses.dataclass(frozen=True)
class StepResult:
    """What one step did. velocity_iterations: the solver's sweeps (max over islands);
    points: contact points solved; served_by: the card that answered where it was not
    the model's own route; latency_ms: the round trip (None: not asked); fallback: why
    Box2D's own start ran instead of the server's answer (a gRPC status name, NO_SERVER,
    BAD_REPLY or REFUSED), None otherwise; start: the start the guard chose ("learned"
    or "builtin"; None without a guard or without contacts); probe: the guard priced
    both starts on this step; joints_started: the server's answer started the world's revolute
    joints too (a world of revolute joints, server.revolute)."""

    velocity_iterations: int
    position_iterations: int
    points: int
    served_by: str | None
    latency_ms: float | None
    fallback: str | None
    start: str | None
    probe: bool
    joints_started: bool = False

    @classmethod
    def of(cls, record: StepRecord) -> "StepResult":
        return cls(record.velocity_iterations, record.position_iterations, record.contact_points,
                   record.served_by, record.latency_ms, record.fallback_reason, record.guard, record.probe,
                   record.joints_started)


class WarmStartSession:
    """One simulation of your world with its warm starts from a server; owns its client.

    world: a patched Box2D.b2World (built by you; the session steps it). target: the
    server ("127.0.0.1:50051", "unix:PATH", any gRPC target). model: a name the server
    lists. deadline_ms: how long a step waits for its answer. tolerance: the solver stops
    after the first sweep whose largest impulse change is at most this (N s); None runs
    the velocity iterations given to step(), Box2D's fixed count. guard: serve the
    learned start only while it beats Box2D's (True, or GuardSettings). Raises
    ConnectionError when no server answers within connect_timeout s (unless
    allow_fallback: then every step runs Box2D's own start, counted), ValueError
    when the server does not serve `model` or the world is not of the patched build.
    tls_ca, tls_cert, tls_key: PEM files for a server with TLS (deepcontact.tls).
    """

    def __init__(self, world, target: str = "127.0.0.1:50051", model: str = "default", *,
                 deadline_ms: float = DEFAULT_DEADLINE_MS, tolerance: float | None = 1e-4,
                 guard: bool | GuardSettings = True, connect_timeout: float = 5.0, allow_fallback: bool = False,
                 tls_ca=None, tls_cert=None, tls_key=None):
        if not isinstance(world, Box2D.b2World) or not hasattr(world, "ExportContacts"):
            raise ValueError(f"WarmStartSession needs a patched Box2D.b2World (make box2d), got {type(world).__name__}")
        if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
            raise ValueError(f"tolerance must be a positive impulse in N s or None, got {tolerance}")
        if not deadline_ms > 0:
            raise ValueError(f"deadline_ms must be > 0, got {deadline_ms}")
        self.model = model
        self.tolerance = tolerance
        self.client = self._connect(target, model, connect_timeout, allow_fallback, (tls_ca, tls_cert, tls_key))
        self.engine = Engine(world, self._config(1 / 60, 8, 3))
        settings = guard if isinstance(guard, GuardSettings) else GuardSettings()
        self.guard = Guard(settings) if guard else None
        provider = Remote(model)
        provider.prepare(self.engine)  # Box2D's own warm starting on: the start the guard and every fallback serve
        self._stepper = Stepper(self.engine, provider, client=self.client, deadline_ms=deadline_ms, guard=self.guard)
        self._physics: tuple | None = None  # (dt, gravity) the server was last told
        self.records: list[StepRecord] = []
        self.refusal: str | None = None  # the server's reason, where it refused this world or its steps

    # -- lifecycle ---------------------------------------------------------------
    @staticmethod
    def _connect(target: str, model: str, timeout: float, allow_fallback: bool, tls) -> WarmStartClient | None:
        from deepcontact.tls import client_credentials

        client = WarmStartClient(target, credentials=client_credentials(*tls))
        if not client.wait_ready(timeout):
            client.close()
            if allow_fallback:
                log.warning("no warm-start server at %s; every step runs Box2D's own warm start", target)
                return None
            raise ConnectionError(f"no warm-start server at {target} (waited {timeout:g} s); start one with "
                                  "`deepcontact serve`, or pass allow_fallback=True")
        names = [m.name for m in client.list_models()]
        if model not in names:
            client.close()
            raise ValueError(f"the server at {target} does not serve {model!r}; it serves {', '.join(sorted(names))}")
        return client

    def close(self) -> None:
        """Close the channel; the world stays yours, as it is."""
        if self.client is not None:
            self.client.close()
            self.client = None
            self._stepper.client = None

    def __enter__(self) -> "WarmStartSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- one step ------------------------------------------------------------------
    def step(self, time_step: float, velocity_iterations: int, position_iterations: int) -> StepResult:
        """Advance the world one step, as world.Step(time_step, velocity_iterations,
        position_iterations) would, from the server's warm start. velocity_iterations is
        the cap with a tolerance, the fixed count without one. Never raises for the
        server's sake: whatever goes wrong there, the step runs from Box2D's own start."""
        config = self._config(time_step, velocity_iterations, position_iterations)
        if config != self.engine.config:
            self.engine.configure(config)
        self._declare(config.dt)
        record = self._stepper.step(len(self.records))
        self.records.append(record)
        self.refusal = self.refusal or self._stepper.refusal
        return StepResult.of(record)

    def summary(self) -> dict:
        """The same keys as `deepcontact simulate`'s summary (mean_velocity_iterations,
        fallback_steps, ...), the guard's counts (learned_steps, guarded_steps,
        guard_probes, guard_switches, guard_trial_iterations) and the server's refusal."""
        return {**summarize(self.records), "refusal": self.refusal}

    def _config(self, dt: float, velocity_iterations: int, position_iterations: int) -> SolverConfig:
        return SolverConfig(dt=float(dt), velocity_iterations=int(velocity_iterations),
                            position_iterations=int(position_iterations),
                            velocity_threshold=-1.0 if self.tolerance is None else float(self.tolerance))

    def _declare(self, dt: float) -> None:
        """Tell the server this world (its domain, static edges, dt and gravity) before the first
        step, and again on a new stream whenever dt or gravity change."""
        if self.client is None:
            return
        gravity = tuple(self.engine.world.gravity)
        if self._physics == (dt, gravity):
            return
        first = self._physics is None
        self._physics = (dt, gravity)
        self.client.set_world(describe(self.engine.world, dt, self.tolerance or 0.0))
        if first:
            try:
                self.client.declare(self.model, DECLARE_TIMEOUT_S)
            except Refused as exc:
                self.refusal = str(exc)
                log.warning("the server refuses %s for this world (%s); every step runs Box2D's own warm start",
                            self.model, exc)
                self._stepper.refused_at, self._stepper.refusal = 0, str(exc)  # no step is sent: REFUSED
