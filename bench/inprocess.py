"""A served model called in the simulation's own process: the server's work on a step
without gRPC, the request's encoding or the reply's decoding.

    provider = InProcess.load(Path("models"), "default", spec)   # a SceneSpec or a user's WorldSpec
    run_simulation(spec, seed, provider)                          # no server, no client

The simulation serves every step with the same predictor the server would load for
the model (`server.predictors.load_model`, one ONNX Runtime thread) and hands it what
a stream hands it: the step's bodies and points as the engine exports them (the
records the wire carries, float32 already), the world the stream declares, passed
through the wire once as the server decodes it (its time step and gravity are
float32 there), the last step's points for temporal channels, each point's
friction (float32, as the wire carries it) to a model that reads it, each point's restitution to a
route (Engine.point_restitution, none where no point has any), and to a model that
keeps state along a stream (a face card's carried admission, Predictor.takes_memory) the
state a stream keeps, one per simulation. On a world with joints the points that touch a
jointed body get Box2D's start (extrapolated along the stream for a card that asks), the
model the rest, as the server answers them (server.joints, on the engine's own body indices).
So the warm start is the served one to the bit, and a simulation takes the served
trajectory. What it measures is what a round trip costs beyond the model's own work:
`bench walltime` times a simulation this way beside the served one.

It lives in bench/, above both simclient and server, because it composes the two;
the simulation client itself never imports the server.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from deepcontact import wire
from deepcontact.modelcard import unknown_model
from deepcontact.temporal import ImpulseHistory
from server.joints import predict_around_joints
from server.revolute import all_held, joint_route, start_with_joints
from server.predictors import Predictor, World, load_model
from simclient import worlds
from simclient.provider import Provider, as_warm_start, point_friction
from simclient.scene import SceneSpec


class InProcess(Provider):
    """The predictor of one model card, asked in process at every step with points."""

    def __init__(self, predictor: Predictor, spec, revolute_joints: bool = True, budget_ms: float | None = None):
        self.predictor, self.spec = predictor, spec
        # Each step's answer due budget_ms after the call, as a server gives the route a request's
        # budget (less its margin); None: none, every step answered in full.
        self.budget_ms = budget_ms
        # As the server answers a world of revolute joints (server.revolute): the joints'
        # start too, set on the engine as the client sets a reply's. False: the contact points alone.
        self.revolute_joints = revolute_joints
        # As the simulation's stream would declare it: a project scene's now, a user's world's
        # when prepare reads it off the engine.
        self.world: World | None = declared_world(spec, None) if isinstance(spec, SceneSpec) else None
        self.name = f"in-process:{predictor.name}"
        self._points: np.ndarray | None = None  # the last step with points: temporal channels' previous
        self._memory: dict = {}  # what a stream keeps for the model between its steps (server.service._StreamSteps)
        self._history: ImpulseHistory | None = None  # Box2D's starts at jointed points, where extrapolated
        #: per step with points, the predictor's stage times (s), named as in the server's
        #: timings (server.predictors.STAGES)
        self.stages: list[dict[str, float]] = []
        #: per step with points, what answered in the predictor's place (Prediction.served_by;
        #: None: the predictor's own answer)
        self.served_by: list[str | None] = []

    @classmethod
    def load(cls, models: Path, model: str, spec, revolute_joints: bool = True) -> "InProcess":
        """The card `models/MODEL.json` (an alias card serves its target) for the worlds of `spec`
        (a simclient.scene.SceneSpec or a user's simclient.worlds.WorldSpec). FileNotFoundError
        names the models there when there is no such card. revolute_joints False: on a world of
        revolute joints, the answer at the contact points alone (the joints' own start)."""
        path = Path(models) / f"{model}.json"
        if not path.exists():
            raise FileNotFoundError(f"{models}: {unknown_model(model, [p.stem for p in Path(models).glob('*.json')])}")
        return cls(load_model(path), spec, revolute_joints)

    def prepare(self, engine) -> None:
        super().prepare(engine)
        self._points, self.stages, self.served_by, self._memory = None, [], [], {}
        self._history = ImpulseHistory() if self.predictor.extrapolates_jointed else None
        self.world = declared_world(self.spec, engine)
        self.predictor.warm_up(self.world.domain)  # as the server does when a stream declares its world

    def warm_start(self, engine, bodies: np.ndarray, points: np.ndarray, step: int):
        """(normal (P,), tangent (P,)) float32 N s, the model's warm start for this step; None without points."""
        if len(points) == 0:
            return None  # the simulation sends no such step, so it is no temporal channel's previous
        # Each point's friction as the wire carries it (float32), to a model that reads it.
        extra = {"friction": point_friction(engine.body_friction(), points).astype(np.float32)} \
            if "point_friction" in self.predictor.requires else {}
        if self.predictor.takes_memory:
            extra["memory"] = self._memory
        if self.budget_ms is not None and self.predictor.takes_deadline:
            extra["deadline"] = time.perf_counter() + self.budget_ms / 1e3
        # Each point's restitution as the wire carries it (float32; none where no point has any).
        restitution = engine.point_restitution(points)
        restitution = restitution if restitution.any() else None
        if self.predictor.takes_restitution:
            extra["restitution"] = restitution
        joints = engine.joints()
        if len(joints) and self.predictor.kind != "provider":  # as server.service answers a step with joints
            answer = predict_around_joints(self.predictor, bodies, points, joints, self.world, step, self._points,
                                           history=self._history, **extra)
            revolute = engine.revolute() if self.revolute_joints else None
            if all_held(revolute) and "friction" in extra:
                answer = start_with_joints(joint_route(self.predictor), bodies, points, joints, revolute, self.world,
                                           step, self._points, extra["friction"], answer,
                                           restitution=restitution)
                if answer.joint_impulses is not None:  # as the client sets a reply's joint_impulses
                    engine.set_revolute_impulses(answer.joint_impulses)
        else:
            answer = self.predictor.predict(bodies, points, self.world, step, self._points, **extra)
        self._points = points
        self.stages.append(answer.stages)
        self.served_by.append(answer.served_by)
        return as_warm_start(answer.impulses)


def declared_world(spec, engine) -> World:
    """The World a stream declares for (spec, engine) as the server decodes it: a project
    scene's from its spec, a user's world's read off its engine (simclient.worlds.world_message).
    The wire carries the step's time and gravity as float32, and the server's channels see them so."""
    declared = worlds.world_message(spec, engine)
    lower, upper, _edges = wire.decode_world(declared)
    return World((tuple(map(float, lower)), tuple(map(float, upper))), wire.decode_physics(declared),
                 wire.decode_tolerance(declared))
