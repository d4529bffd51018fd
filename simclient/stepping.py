"""One step of a simulation with a warm start, measured: the loop every client runs.

    stepper = Stepper(engine, provider, client=client, deadline_ms=10.0, guard=Guard())
    record = stepper.step(k)        # collide, export, ask, inject (or not), solve: a StepRecord
    summary = summarize(records)    # iteration statistics over the steps with contacts

`simulate`, `bench iterations` and `WarmStartSession` all step through here.
Faults never stop a simulation: a reply that misses its deadline, a broken or
absent server, a reply that cannot be injected (wrong length, not finite) make
the step run with Box2D's own warm start, counted as a fallback by reason. A
refusal of the step (the server's limits, a model that cannot serve this world)
is logged once, and steps at least as large are not sent again (fallback
REFUSED). With a guard (simclient.guard), the learned start is served only
while it beats Box2D's on this simulation's own steps.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time

import numpy as np

from deepcontact import wire
from simclient.guard import BUILTIN, LEARNED, Guard
from simclient.provider import Provider

log = logging.getLogger("deepcontact.simclient")


@dataclasses.dataclass
class StepRecord:
    contact_points: int
    velocity_iterations: int
    position_iterations: int
    residual_trace: list[float]
    mse_normal: float | None
    mse_tangent: float | None
    latency_ms: float | None  # round trip to the server; None for local warm starts
    server_us: dict | None  # the server's stage timings
    client_us: float  # export + encode + decode + inject, microseconds
    provider_ms: float  # time to obtain the warm start (round trip or local computation)
    solve_ms: float
    collide_ms: float  # the engine's collision step, before the warm start
    export_ms: float  # reading bodies and contact points out of the engine
    inject_ms: float  # handing the warm start to the engine (0 without one)
    fallback: bool
    fallback_reason: str | None  # StepFailed.reason, NO_SERVER, BAD_REPLY or REFUSED; None when not a fallback
    reconnect: bool  # this step's request went on a stream reopened after the first
    served_by: str | None = None  # the reply's served_by: another card's answer than the model's route
    guard: str | None = None  # a guarded step with contacts: the start the guard chose ("learned" or "builtin")
    probe: bool = False  # the guard priced both starts on this step
    guard_switch: bool = False  # the guard changed its start after this step
    trial_iterations: int = 0  # the guard's trial sweeps on this step
    trial_ms: float = 0.0  # their time
    learned: bool = False  # the server's model's own answer (not a fallback's, nor Box2D's) started the solve
    familiar: bool | None = None  # the server's word: the step lies inside what its model was trained on (None: not asked)
    unfamiliar: str | None = None  # where not, why (the reply's unfamiliar)
    joints_started: bool = False  # the reply's joint_impulses started the revolute joints too


@dataclasses.dataclass
class _Served:
    """What one step got from the server: the warm start (None: Box2D's own) and what it cost."""

    warm: tuple[np.ndarray, np.ndarray] | None = None
    latency_ms: float | None = None  # the round trip, or until the step failed
    server_us: dict | None = None  # the server's stage timings
    codec_s: float = 0.0  # encoding the request and decoding the reply, seconds
    fallback_reason: str | None = None  # set: the step fell back to builtin
    reconnect: bool = False
    served_by: str | None = None  # the reply's served_by, where set
    detail: str = ""  # a failure's message
    familiar: bool | None = None  # the reply's familiar (None: no reply)
    unfamiliar: str | None = None  # the reply's unfamiliar, where not familiar
    joints: np.ndarray | None = None  # (J, 2) N s, the revolute joints' start with `warm`; None: their own


class _Laps:
    """Seconds between successive calls of lap(): one step's parts, timed in order."""

    def __init__(self):
        self._t = time.perf_counter()

    def lap(self) -> float:
        now = time.perf_counter()
        seconds, self._t = now - self._t, now
        return seconds


def _usable(warm: tuple[np.ndarray, np.ndarray], n_points: int) -> bool:
    """A reply the engine can start from: one finite normal and tangent per point."""
    normal, tangent = warm
    return len(normal) == n_points and len(tangent) == n_points and bool(
        np.isfinite(normal).all() and np.isfinite(tangent).all())


class Stepper:
    """Drives one Engine with one provider, a step at a time.

    client: a simclient.client.WarmStartClient whose world is set (server: providers);
    None makes every server step a fallback (NO_SERVER). guard: a Guard for a server
    provider, or None to serve its answer every step.
    """

    def __init__(self, engine, provider: Provider, *, client=None, deadline_ms: float = 10.0,
                 guard: Guard | None = None):
        self.engine, self.provider, self.client = engine, provider, client
        self.timeout = deadline_ms / 1e3
        self.guard = guard if provider.uses_server and not provider.picks else None
        self.refused_at: int | None = None  # the smallest step (points) the server refused
        self.refusal: str | None = None  # its reason, logged once

    def step(self, k: int) -> StepRecord:
        """Step k, whole: collide, export, the warm start, solve; its record."""
        engine, provider = self.engine, self.provider
        laps = _Laps()
        engine.collide()
        collide_s = laps.lap()
        bodies, points = engine.bodies(), engine.contacts()
        export_s = laps.lap()
        # A world asleep (Box2D's sleeping is on in most users' worlds) has nothing to warm-start.
        live = len(points) > 0 and ((not provider.uses_server and not provider.picks) or self._touches_awake(points))
        if self.guard is not None and live:
            return self._guarded(k, bodies, points, laps, collide_s, export_s)
        if provider.picks:
            served = self._pick(k, bodies, points) if live else _Served()
        elif provider.uses_server:
            served = self._ask(k, bodies, points) if live else _Served()
        else:
            served = _Served(warm=provider.warm_start(engine, bodies, points, k))
        provider_s = laps.lap()
        inject_s = 0.0
        if served.warm is not None:
            engine.set_warm_start(*served.warm)
            if served.joints is not None:
                engine.set_revolute_impulses(served.joints)
            inject_s = laps.lap()
        stats = engine.solve()
        record = self._record(stats, served, collide_s=collide_s, export_s=export_s, provider_s=provider_s,
                              inject_s=inject_s)
        record.joints_started = served.warm is not None and served.joints is not None
        record.learned = provider.uses_server and not provider.picks and served.warm is not None and not served.served_by
        return record

    # -- the guarded step ----------------------------------------------------
    def _guarded(self, k, bodies, points, laps: _Laps, collide_s: float, export_s: float) -> StepRecord:
        """A step with contacts under the guard: maybe ask, maybe price both starts, serve one."""
        engine, guard = self.engine, self.guard
        plan = guard.plan()
        served = self._ask(k, bodies, points) if plan.ask else _Served()
        if served.warm is not None:
            guard.heard(served.familiar, served.unfamiliar or "")
        provider_s = laps.lap()
        learned, mode, trial, trial_s, inject_s, capped = served.warm, guard.mode, None, 0.0, 0.0, False
        if plan.probe and learned is not None:
            builtin = engine.builtin_start()
            t0 = time.perf_counter()
            if mode == LEARNED:  # Box2D's start priced beside the learned one, which is served
                trial = engine.trial_trace(*builtin)
                engine.set_warm_start(*learned)
                if served.joints is not None:
                    engine.set_revolute_impulses(served.joints)
            else:  # the learned start priced, Box2D's served; past the cap it has lost (with a tolerance)
                cap = guard.trial_cap() if engine.config.velocity_threshold >= 0 else None
                own = None
                if served.joints is not None:  # priced with the joints' start it comes with, then put back
                    own = engine.joint_state()
                    engine.set_revolute_impulses(served.joints)
                trial = engine.trial_trace(*learned, cap=cap)
                if own is not None:
                    engine.set_joint_state(own)
                capped = cap is not None and len(trial) >= cap
                engine.set_warm_start(*builtin)
            trial_s = time.perf_counter() - t0
            laps.lap()
        elif mode == LEARNED and learned is not None:
            engine.set_warm_start(*learned)
            if served.joints is not None:
                engine.set_revolute_impulses(served.joints)
            inject_s = laps.lap()
        stats = engine.solve()
        served_start = LEARNED if (mode == LEARNED and learned is not None) else BUILTIN
        record = self._record(stats, served, collide_s=collide_s, export_s=export_s, provider_s=provider_s,
                              inject_s=inject_s)
        record.joints_started = served_start == LEARNED and served.joints is not None
        record.learned = served_start == LEARNED and not served.served_by
        if stats.contact_points == 0:  # every point slept after all: nothing for the guard to learn
            return record
        if trial is not None:
            solved = self._cost(stats.residual_trace, stats.velocity_iterations)
            priced = self._cost(trial, len(trial))
            pair = (solved, priced) if mode == LEARNED else (priced, solved)
            guard.probed(learned=pair[0], builtin=pair[1], trial_sweeps=len(trial),
                         builtin_sweeps=len(trial) if mode == LEARNED else stats.velocity_iterations, capped=capped)
            record.probe, record.trial_iterations, record.trial_ms = True, len(trial), 1e3 * trial_s
        else:
            guard.served(served_start, self._cost(stats.residual_trace, stats.velocity_iterations),
                         stats.velocity_iterations)
        record.guard, record.guard_switch = mode, guard.mode != mode
        return record

    def _touches_awake(self, points) -> bool:
        """Whether some point touches an awake body (else the solver solves none of them)."""
        awake = self.engine.awake()
        return bool(awake[points["body_a"]].any() or awake[points["body_b"]].any())

    def _cost(self, trace: np.ndarray, sweeps: int) -> float:
        """What a start cost the step: its sweeps to the tolerance; with none (every step runs
        the same sweeps), how far from converged it left the step (the last sweep's change)."""
        if self.engine.config.velocity_threshold >= 0:
            return float(sweeps)
        return float(trace[-1]) if len(trace) else 0.0

    # -- the server ------------------------------------------------------------
    def _ask(self, k: int, bodies, points) -> _Served:
        """Step k's warm start from the server, or a counted fallback."""
        from simclient.client import REFUSALS, StepFailed

        if len(points) == 0:
            return _Served()  # nothing to warm-start; no round trip
        if self.client is None:
            return _Served(fallback_reason="NO_SERVER")
        if self.refused_at is not None and len(points) >= self.refused_at:
            return _Served(fallback_reason="REFUSED")
        engine, provider, client = self.engine, self.provider, self.client
        oracle = engine.oracle() if provider.sends_oracle else None
        t0 = time.perf_counter()
        joints = engine.joints()
        request = wire.encode_step(k, provider.model, bodies, points, builtin=points["builtin"], impulses=oracle,
                                   friction=points["friction"], joints=joints,
                                   revolute=engine.revolute() if len(joints) else None,
                                   restitution=engine.point_restitution(points))
        t1 = time.perf_counter()
        streams = client.reconnects
        try:
            reply = client.step(request, self.timeout)
        except StepFailed as exc:
            if exc.code in REFUSALS:
                self._refused(len(points), str(exc))
            return _Served(latency_ms=1e3 * (time.perf_counter() - t1), fallback_reason=exc.reason,
                           reconnect=client.reconnects > streams, detail=str(exc))
        t2 = time.perf_counter()
        try:
            warm = wire.decode_impulses(reply)
            started = wire.decode_joint_impulses(reply, len(joints))
        except wire.WireError as exc:
            warm = started = None
            detail = str(exc)
        else:
            detail = "" if _usable(warm, len(points)) else f"{reply.point_count} values for {len(points)} points, or not finite"
        t3 = time.perf_counter()
        if detail:
            log.warning("step %d: the server's reply cannot be injected (%s); Box2D's own warm start instead", k, detail)
            return _Served(latency_ms=1e3 * (t2 - t1), fallback_reason="BAD_REPLY", detail=detail,
                           reconnect=client.reconnects > streams)
        tm = reply.timings
        return _Served(warm=warm, latency_ms=1e3 * (t2 - t1), codec_s=(t1 - t0) + (t3 - t2),
                       server_us={"decode": tm.decode_us, "p2g": tm.p2g_us, "features": tm.features_us,
                                  "inference": tm.inference_us, "g2p": tm.g2p_us, "solve": tm.solve_us,
                                  "admit": tm.admit_us, "total": tm.total_us},
                       reconnect=client.reconnects > streams, served_by=reply.served_by or None,
                       familiar=reply.familiar, unfamiliar=reply.unfamiliar or None, joints=started)

    def _refused(self, n_points: int, reason: str) -> None:
        """The server refused a step of n_points: log it the first time, and send no step that large again."""
        if self.refusal is None:
            log.warning("the server refuses this simulation's steps (%s); steps of %d points or more get Box2D's "
                        "own warm start from now on", reason, n_points)
        self.refusal = reason
        self.refused_at = n_points if self.refused_at is None else min(self.refused_at, n_points)

    def _pick(self, k: int, bodies, points) -> _Served:
        """A composite's warm start for step k (simclient.provider.Composite): every candidate asked and
        priced by trial solves, the cheapest (or the first, their mean, builtin) served. A server
        candidate that fell back is priced as builtin, and the step counts as a fallback."""
        if len(points) == 0:
            return _Served()
        warms, reasons = [], []
        for c in self.provider.candidates:
            if c.uses_server:
                asked = Stepper(self.engine, c, client=self.client, deadline_ms=1e3 * self.timeout)._ask(k, bodies, points)
                warms.append(asked.warm)
                reasons.append(asked.fallback_reason)
            else:
                warms.append(c.warm_start(self.engine, bodies, points, k))
        return _Served(warm=self.provider.pick(self.engine, points, warms),
                       fallback_reason=next((r for r in reasons if r), None))

    # -- the record --------------------------------------------------------------
    def _record(self, stats, served: _Served, *, collide_s: float, export_s: float, provider_s: float,
                inject_s: float) -> StepRecord:
        """One step's record from the solve's statistics and the contact points after it (seconds in)."""
        after = self.engine.contacts()
        self.provider.observe(after)
        mse_n = mse_t = None
        if len(after):
            err = after["warm_start"] - after["impulse"]
            mse_n, mse_t = float(np.mean(err[:, 0] ** 2)), float(np.mean(err[:, 1] ** 2))
        return StepRecord(
            contact_points=stats.contact_points, velocity_iterations=stats.velocity_iterations,
            position_iterations=stats.position_iterations,
            residual_trace=[float(x) for x in stats.residual_trace],
            mse_normal=mse_n, mse_tangent=mse_t, latency_ms=served.latency_ms, server_us=served.server_us,
            client_us=1e6 * (export_s + served.codec_s + inject_s), provider_ms=1e3 * provider_s,
            solve_ms=stats.solve_ms, collide_ms=1e3 * collide_s, export_ms=1e3 * export_s, inject_ms=1e3 * inject_s,
            fallback=served.fallback_reason is not None, fallback_reason=served.fallback_reason,
            reconnect=served.reconnect, served_by=served.served_by, familiar=served.familiar,
            unfamiliar=served.unfamiliar)


def columns(records: list[StepRecord]) -> dict[str, list]:
    """The records as one list per field: a results file's "per_step"."""
    return {f.name: [getattr(r, f.name) for r in records] for f in dataclasses.fields(StepRecord)}


def summarize(records: list[StepRecord]) -> dict:
    """Iteration statistics over steps with at least one contact point, and the guard's counts."""
    solved = [r for r in records if r.contact_points > 0]
    its = np.array([r.velocity_iterations for r in solved], float)
    lat = np.array([r.latency_ms for r in records if r.latency_ms is not None and not r.fallback], float)
    mse_n = [r.mse_normal for r in solved if r.mse_normal is not None]
    mse_t = [r.mse_tangent for r in solved if r.mse_tangent is not None]
    client = np.array([r.client_us for r in solved], float)
    guarded = [r for r in records if r.guard is not None]

    def stat(fn, a):
        return float(fn(a)) if len(a) else None

    return {
        "steps": len(records),
        "steps_with_contacts": len(solved),
        "mean_velocity_iterations": stat(np.mean, its),
        "median_velocity_iterations": stat(np.median, its),
        "p90_velocity_iterations": stat(lambda a: np.percentile(a, 90), its),
        "mse_normal": stat(np.mean, mse_n),
        "mse_tangent": stat(np.mean, mse_t),
        "p50_latency_ms": stat(np.median, lat),
        "p99_latency_ms": stat(lambda a: np.percentile(a, 99), lat),
        "fallback_steps": sum(r.fallback for r in records),
        "fallbacks_by_reason": dict(collections.Counter(r.fallback_reason for r in records if r.fallback)),
        "reconnects": sum(r.reconnect for r in records),
        # Steps a server answered with another card's (a face card's fallback; docs/server.md, Deadlines).
        "served_by": dict(collections.Counter(r.served_by for r in records if r.served_by)),
        "median_client_us": stat(np.median, client),
        "total_solve_ms": float(sum(r.solve_ms for r in records)),
        # The guard (simclient.guard): steps it served Box2D's own start, the learned one, its probes and switches.
        "guarded_steps": sum(r.guard == BUILTIN for r in guarded),
        "learned_steps": sum(r.guard == LEARNED for r in guarded),
        "guard_probes": sum(r.probe for r in guarded),
        "guard_switches": sum(r.guard_switch for r in guarded),
        "guard_trial_iterations": int(sum(r.trial_iterations for r in guarded)),
        "guard_trial_ms": float(sum(r.trial_ms for r in guarded)),
        # Steps with contacts the server's model's own answer started (no fallback, no other card, not the guard's Box2D).
        "learned_route_steps": sum(r.learned for r in solved),
        # Steps whose revolute joints the server's answer started too (server.revolute).
        "joints_started_steps": sum(r.joints_started for r in records),
        # The server's word on the world (deepcontact.envelope): steps it called familiar, and why it did not.
        "familiar_steps": sum(r.familiar is True for r in records),
        "unfamiliar_steps": sum(r.familiar is False for r in records),
        "unfamiliar": next((r.unfamiliar for r in records if r.familiar is False), None),
    }
