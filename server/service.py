"""The WarmStart gRPC service: validate, P2G -> model -> G2P, reply.

Per step: decode and validate the request (deepcontact.wire), look up the
model, check its grid fits the world, predict, encode the impulses with the
stage timings. Bad input never reaches the model: it is answered with
INVALID_ARGUMENT naming the field and the limit, NOT_FOUND for an unknown
model, RESOURCE_EXHAUSTED when the inference queue is full. A stream that
receives a bad message is ended with that status; other streams are not
affected. Bytes that do not parse as a request never get here: they are
refused by server.malformed.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import logging
import os
import threading
import time

import grpc
import numpy as np

from deepcontact import wire
from deepcontact.temporal import ImpulseHistory
from deepcontact.v1 import warmstart_pb2 as pb
from deepcontact.v1 import warmstart_pb2_grpc as pb_grpc
from server import metrics
from server.batching import QueueFull
from server.idle import IdleStreams
from server.joints import predict_around_joints
from server.revolute import PricingTime, all_held, joint_labels, joint_route, start_with_joints
from deepcontact.channels import NEEDS
from server.predictors import MAX_GRID_NODES, NOT_JUDGED, GridMismatch, Prediction, Predictor, World
from server.rejects import reject

log = logging.getLogger("deepcontact.server")
SERVICE_NAME = pb.DESCRIPTOR.services_by_name["WarmStart"].full_name
_PREDICT, _STREAM = f"/{SERVICE_NAME}/Predict", f"/{SERVICE_NAME}/Stream"
#: Of a request's budget_us, what the service leaves for the transport and the reply (s;
#: `deepcontact serve --deadline-margin-ms`): a loopback round trip's share outside the
#: handler is about 0.5 ms on an idle host, and several times that beside a simulation.
DEADLINE_MARGIN_S = 3e-3
#: Of a request's budget, what each other request the server is answering at the same time
#: takes of it outside this one's handler (s): their parsing, hand-offs and replies share the
#: cores with it. Measured on one core: 16 lockstep streams of thesis steps cost about 0.2 ms a
#: step of the server's time beyond the handlers (docs/performance.md, "Under load").
LOAD_SHARE_S = 2e-4
#: The weight of each step in the moving averages of the wait before a handler begins and of
#: the handler's CPU time (server.service.WarmStartService.queue).
QUEUE_WEIGHT = 0.05


@dataclasses.dataclass(frozen=True)
class Limits:
    max_bodies: int = 10_000
    max_points: int = 100_000
    max_grid_nodes: int = MAX_GRID_NODES  # enforced by the predictors, which build the grids


@dataclasses.dataclass(frozen=True)
class FaultDelay:
    """Fault injection for testing clients: hold the reply of every step whose
    index is a multiple of `every` for `seconds` (a slow or stalled server)."""

    seconds: float
    every: int = 1

    def applies(self, step: int) -> bool:
        return self.seconds > 0 and step % self.every == 0


class _Reject(Exception):
    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


# When the current thread began parsing its request (see _parse_step).
_parse_started = threading.local()


def _parse_step(data: bytes) -> pb.StepRequest:
    """StepRequest.FromString, noting when it started.

    gRPC's Python server parses a request in the thread that then runs the
    handler (the pool thread of the RPC), so a step's `decode` time is taken
    from here: it includes protobuf parsing and gRPC's hand-off to the handler,
    not just our checks.
    """
    _parse_started.t = time.perf_counter()
    return pb.StepRequest.FromString(data)


def add_to_server(service: "WarmStartService", server: grpc.Server) -> None:
    """Register the service like the generated add_WarmStartServicer_to_server,
    with :func:`_parse_step` as the step requests' deserializer."""
    handlers = {
        "Stream": grpc.stream_stream_rpc_method_handler(
            service.Stream, request_deserializer=_parse_step,
            response_serializer=pb.Impulses.SerializeToString),
        "Predict": grpc.unary_unary_rpc_method_handler(
            service.Predict, request_deserializer=_parse_step,
            response_serializer=pb.Impulses.SerializeToString),
        "ListModels": grpc.unary_unary_rpc_method_handler(
            service.ListModels, request_deserializer=pb.ListModelsRequest.FromString,
            response_serializer=pb.ListModelsReply.SerializeToString),
    }
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(SERVICE_NAME, handlers)


class WarmStartService(pb_grpc.WarmStartServicer):
    def __init__(self, predictors: list[Predictor], limits: Limits = Limits(), fault: FaultDelay | None = None,
                 idle: IdleStreams | None = None, deadline_margin_s: float = DEADLINE_MARGIN_S):
        self.predictors = {p.name: p for p in predictors}
        # A request's budget counts from the client's sending; this much of it is left for what
        # happens outside the handler (the transport both ways, parsing before t0, the reply).
        self.deadline_margin_s = deadline_margin_s
        # The requests inside a handler now, and the cores they share: a face card's route is
        # taken only where it is expected to end inside its request's budget at that share.
        self._in_flight = 0
        self._flight = threading.Lock()
        # Moving averages of how long recent steps from this host waited before their handler
        # began, and of their handlers' CPU time (s): their ratio is about how many steps were
        # ahead of each, the queue that a step's work is shared with.
        self._wait, self._work = 0.0, 1e-3
        self.cores = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
        self.limits = limits
        self.fault = fault
        self.idle = idle  # None: streams may stay open without sending for as long as they like
        # What pricing a world of revolute joints has taken (server.revolute), kept across steps,
        # and a thread that asks its classifier about the step with the joints' points while the
        # served answer is made, where a core is spare.
        self._pricing = PricingTime()
        self._joint_labels = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="joint-labels") \
            if self.cores > 1 else None

    # -- RPCs -----------------------------------------------------------------
    def ListModels(self, request, context):
        reply = pb.ListModelsReply()
        for p in self.predictors.values():
            reply.models.add(name=p.name, kind=p.kind, fixed_grid=p.fixed_grid, description=p.description,
                             gridspec_json=p.gridspec.to_json(indent=None) if p.gridspec is not None else "")
        return reply

    def Predict(self, request, context):
        try:
            if not request.HasField("world"):
                raise _Reject(grpc.StatusCode.INVALID_ARGUMENT, "world: required on every Predict request")
            return self._step(request, self._world(request.world), local=_same_host(context))[0]
        except _Reject as r:
            reject(context, r.code, r.message, rpc=_PREDICT)

    def Stream(self, request_iterator, context):
        # A stream is one simulation: its world, and its last step's points for temporal channels.
        world, steps = None, _StreamSteps()
        local = _same_host(context)  # a client on this host: its steps' sending times are on this clock
        idle = self.idle
        token = idle.open(context) if idle is not None else None
        try:
            for request in request_iterator:
                if token is not None:
                    idle.touch(token)
                try:
                    if request.HasField("world"):
                        world, steps = self._world(request.world), _StreamSteps()
                        self._warm_up(request.model, world)
                    elif world is None:
                        raise _Reject(grpc.StatusCode.INVALID_ARGUMENT,
                                      "world: required on the first message of a stream")
                    reply, points = self._step(request, world, steps.before(request.step), streamed=True, local=local,
                                               memory=steps.memory, histories=steps.histories)
                    steps.record(request.step, points)
                    yield reply
                except _Reject as r:
                    reject(context, r.code, r.message, rpc=_STREAM)
        except grpc.RpcError:
            return  # cancelled (by the client, a shutdown, or IdleStreams): nobody is left to answer
        finally:
            if token is not None:
                idle.close(token)

    # -- one step -------------------------------------------------------------
    def _world(self, world: pb.World) -> World:
        try:
            lower, upper, _edges = wire.decode_world(world)
            physics, tolerance = wire.decode_physics(world), wire.decode_tolerance(world)
        except wire.WireError as exc:
            raise _Reject(grpc.StatusCode.INVALID_ARGUMENT, str(exc)) from None
        return World(((float(lower[0]), float(lower[1])), (float(upper[0]), float(upper[1]))), physics, tolerance)

    def _warm_up(self, model: str, world: World) -> None:
        """Ready the stream's model for its world's grid before the first step
        (a client can declare the world in a message without points, see
        simclient.client.WarmStartClient.declare). Errors are left to the step."""
        predictor = self.predictors.get(model)
        if predictor is None:
            return
        try:
            seconds = predictor.warm_up(world.domain)
        except GridMismatch:
            return
        if seconds:
            log.info("warmed up %s for a new grid in %.1f ms", model, 1e3 * seconds,
                     extra={"model": model, "domain": world.domain})

    @staticmethod
    def _missing(predictor: Predictor, request: pb.StepRequest, world: World) -> list[str]:
        """What the predictor needs that this request does not carry (keys of channels.NEEDS)."""
        sent = {"point_bodies": request.point_bodies, "body_inertia": request.body_inertia,
                "point_separation": request.point_separation, "builtin": request.builtin,
                "point_keys": request.point_keys, "point_friction": request.point_friction,
                "physics": world.physics.dt > 0}
        return [need for need in predictor.requires if not sent[need]]

    def _step(self, request: pb.StepRequest, world: World, previous=None, streamed: bool = False,
              local: bool = False, memory: dict | None = None, histories: dict | None = None):
        """(reply, the step's decoded points). streamed: the request is a stream's step (a shed
        step is answered, not refused: a refusal would end the stream); local: its client is on
        this host, so its sending time (sent_unix_us) is on this host's clock; memory: the
        stream's dict of predictors' state by model name (_StreamSteps.memory), or None;
        histories: the stream's ImpulseHistory by model name (_StreamSteps.histories), or None."""
        # From the start of parsing when gRPC parsed this request in this thread.
        t0 = _parse_started.__dict__.pop("t", None) or time.perf_counter()
        with self._flight:
            self._in_flight += 1
            in_flight = self._in_flight
        waited = 1e-6 * _waited_us(request, t0) if local else None
        cpu = time.thread_time()
        try:
            return self._answer(request, world, previous, t0, in_flight, streamed, local, memory, histories)
        finally:
            cpu = time.thread_time() - cpu
            with self._flight:
                self._in_flight -= 1
                if waited is not None:
                    self._wait += QUEUE_WEIGHT * (waited - self._wait)
                    self._work += QUEUE_WEIGHT * (cpu - self._work)

    def queue(self) -> float:
        """About how many steps share the cores with one now: 1 plus the recent steps' wait over
        their handlers' CPU time (a step waited for about that many others ahead of it)."""
        return 1.0 + self._wait / max(self._work, 1e-5)

    def _answer(self, request: pb.StepRequest, world: World, previous, t0: float, in_flight: int, streamed: bool,
                local: bool, memory: dict | None = None, histories: dict | None = None):
        """_step's work, t0 when its parsing began, in_flight the requests in a handler now, this
        one among them."""
        predictor = self.predictors.get(request.model)
        if predictor is None:
            raise _Reject(grpc.StatusCode.NOT_FOUND,
                          f"model {request.model!r} is not served here; ListModels names {sorted(self.predictors)}")
        # A step without points needs nothing beyond the world (e.g. a message declaring it).
        missing = self._missing(predictor, request, world) if predictor.requires and request.point_count else ()
        if missing:
            raise _Reject(grpc.StatusCode.INVALID_ARGUMENT,
                          f"model {predictor.name!r} needs {'; '.join(NEEDS[m] for m in missing)}, "
                          "which this request lacks (a client older than the model's inputs?)")
        try:
            bodies, points = wire.decode_step(request, max_bodies=self.limits.max_bodies,
                                              max_points=self.limits.max_points)
            friction, joints = wire.decode_friction(request), wire.decode_joints(request)
            restitution = wire.decode_restitution(request)
            revolute = wire.decode_revolute(request)
            # Only a predictor that asks for the friction gets it: the others' predict() takes none.
            extra = {"friction": friction} if "point_friction" in predictor.requires else {}
            deadline = None
            if request.budget_us:
                # The steps in a handler share the cores now; with clients on this host, also the
                # steps waiting to begin (queue()): a route's wall time is its CPU time that many
                # over, and the reply's way back is that much longer.
                load = max(in_flight, self.queue())
                waited = _waited_us(request, t0) if local else 0
                deadline = (t0 + 1e-6 * (request.budget_us - waited) - self.deadline_margin_s
                            - (load - 1) * LOAD_SHARE_S)
            if predictor.takes_restitution:
                extra["restitution"] = restitution
            if predictor.takes_memory and memory is not None:
                extra["memory"] = memory.setdefault(request.model, {})
            if predictor.takes_deadline and deadline is not None:
                extra["deadline"], extra["slowdown"] = deadline, max(1.0, load / self.cores)
            predictor.check_domain(world.domain)
        except (wire.WireError, GridMismatch) as exc:
            raise _Reject(grpc.StatusCode.INVALID_ARGUMENT, str(exc)) from None
        t1 = time.perf_counter()
        if deadline is not None and t1 >= deadline and len(points):
            # Its budget spent before any work (it waited in the server's sockets and for its
            # cores): the work would reach the client too late and delay the steps behind it.
            # Shed: a stream's step is answered at once with Box2D's own warm start (the stream
            # goes on; the client starts there as it would after a miss), a single request refused.
            metrics.SHED.labels(model=predictor.name).inc()
            if not streamed:
                raise _Reject(grpc.StatusCode.RESOURCE_EXHAUSTED,
                              f"the server is answering {in_flight} requests on {self.cores} cores and this "
                              f"one's budget of {request.budget_us} us was spent before it began")
            if len(request.builtin):
                answer = Prediction(points["builtin"].astype(np.float32), served_by=SHED)
                return self._reply(request, predictor, answer, t0, t1, bodies, points, friction, joints, world)
        try:
            if len(points) == 0:  # nothing to warm-start (e.g. a message that only declares the world)
                answer = Prediction(np.zeros((0, 2), np.float32))
            elif joints is not None and predictor.kind != "provider":  # a provider (zero, ...) answers as it is
                history = None
                if predictor.extrapolates_jointed and histories is not None and request.point_keys:
                    history = histories.setdefault(request.model, ImpulseHistory())
                route = joint_route(predictor) if all_held(revolute) and friction is not None else None
                labelled = None
                if route is not None and self._joint_labels is not None and self._pricing.fits(t1, deadline):
                    labelled = self._joint_labels.submit(joint_labels, route, bodies, points, joints, revolute, world,
                                                         request.step, previous, friction)
                answer = predict_around_joints(predictor, bodies, points, joints, world, request.step, previous,
                                               history=history, **extra)
                if route is not None:
                    answer = start_with_joints(route, bodies, points, joints, revolute, world, request.step, previous,
                                               friction, answer, deadline, self._pricing, labelled,
                                               restitution=restitution)
            else:
                answer = predictor.predict(bodies, points, world, request.step, previous, **extra)
        except QueueFull as exc:
            raise _Reject(grpc.StatusCode.RESOURCE_EXHAUSTED, str(exc)) from None
        except Exception as exc:  # a bug, not the client's fault: say so, keep serving
            log.exception("predict failed", extra={"model": predictor.name, "step": request.step})
            raise _Reject(grpc.StatusCode.INTERNAL, f"{predictor.name} failed: {exc}") from None
        if self.fault is not None and self.fault.applies(request.step):
            time.sleep(self.fault.seconds)
        return self._reply(request, predictor, answer, t0, t1, bodies, points, friction, joints, world)

    def _reply(self, request, predictor: Predictor, answer: Prediction, t0: float, t1: float, bodies, points, friction,
               joints, world: World):
        """(the reply to `request`, its points): answer's impulses, who answered, whether the
        world is familiar, the stage timings from t0 (parsing began) and t1 (decoded)."""
        reply = wire.encode_impulses(request.step, predictor.name, answer.impulses)
        if len(points):
            unfamiliar = _unfamiliar(predictor, bodies, points, friction, joints, world, answer.unfamiliar)
            reply.familiar = unfamiliar is None
            reply.unfamiliar = unfamiliar or ""
        if answer.served_by:
            reply.served_by = answer.served_by
        if answer.joint_impulses is not None:
            reply.joint_impulses = np.ascontiguousarray(answer.joint_impulses, np.float32).tobytes()
            metrics.SERVED_BY.labels(model=predictor.name, served_by=answer.served_by).inc()
        # Filled in place: building a Timings and copying it in costs more. Each stage a
        # predictor did not run stays 0 (a grid model has no solve, the face route no p2g).
        stages, timings = answer.stages, reply.timings
        timings.decode_us = _us(t1 - t0)
        timings.p2g_us = _us(stages.get("p2g", 0.0))
        timings.features_us = _us(stages.get("features", 0.0))
        timings.inference_us = _us(stages.get("inference", 0.0))
        timings.g2p_us = _us(stages.get("g2p", 0.0))
        timings.solve_us = _us(stages.get("solve", 0.0))
        timings.admit_us = _us(stages.get("admit", 0.0))
        total = time.perf_counter() - t0
        timings.total_us = _us(total)
        metrics.observe_step(predictor.name, t1 - t0, stages, total)
        return reply, points


#: served_by of a step shed: its budget was spent before any work began, and Box2D's own warm
#: start (the request's builtin impulses) answered it at once.
SHED = "builtin"


def _waited_us(request: pb.StepRequest, t0: float) -> int:
    """How long a request from this host waited between its client's sending and t0
    (perf_counter s), in us: 0 where it does not say when it was sent (sent_unix_us; an older
    client) or says a time after t0."""
    if not request.sent_unix_us:
        return 0
    return max(0, int((time.time() - (time.perf_counter() - t0)) * 1e6) - request.sent_unix_us)


def _same_host(context) -> bool:
    """Whether the RPC's peer is on this host (a Unix socket or loopback), whose clock is ours."""
    peer = context.peer() or ""
    return peer.startswith(("unix:", "ipv4:127.", "ipv6:[::1]"))


#: Why a predictor's steps are all unfamiliar: its card records no training envelope, or no
#: measured gain over Box2D's start on the worlds it holds (deepcontact.modelcard, measured).
NO_ENVELOPE = "the card records no trained_on"
NO_GAIN = "the card records no measured gain over Box2D's start where it was trained"


def _unfamiliar(predictor: Predictor, bodies, points, friction, joints, world: World,
                judged=NOT_JUDGED) -> str | None:
    """Why the step is not one the predictor's card vouches for, or None where it is: inside what
    the model was trained on (deepcontact.envelope) and measured to win there. judged: the
    predictor's own verdict on the step against its envelope (Prediction.unfamiliar), taken as
    it is where the step has no joints (which the predictor does not judge)."""
    if predictor.envelope is None:
        return NO_ENVELOPE
    if not predictor.wins_where_trained:
        return NO_GAIN
    if judged is not NOT_JUDGED and joints is None:
        return judged
    return predictor.envelope.unfamiliar(bodies, points, friction, world.physics, joints)


class _StreamSteps:
    """A stream's last step's points, the `previous` of temporal channels.

    A step's previous step is the last one sent with another index: a client that asks
    several models about one state (bench iterations' price:, shadow:, pick:) sends one
    request per model with the same step, and each must see the step before, not the
    request before. A step without points is not sent, so the step before a gap is the
    last one that had points."""

    __slots__ = ("step", "points", "_before", "memory", "histories")

    def __init__(self):
        self.step, self.points, self._before = None, None, None
        # What predictors keep along the stream (takes_memory), a dict per model name: a model
        # asked about the same states as others (price:) keeps its own.
        self.memory: dict[str, dict] = {}
        # Box2D's starts of the last two steps by model name, for a card that extrapolates them
        # at jointed points (Predictor.extrapolates_jointed).
        self.histories: dict[str, ImpulseHistory] = {}

    def before(self, step: int):
        """(P,) CONTACT_DTYPE of the step before `step`, or None."""
        return self._before if step == self.step else self.points

    def record(self, step: int, points) -> None:
        if step != self.step:
            self._before, self.step = self.points, step
        self.points = points


def _us(seconds: float) -> int:
    return max(0, int(round(seconds * 1e6)))
