"""Worlds of rigid revolute joints: the joints' start served too, each step's start priced with
the joints swept as Box2D sweeps them.

Box2D starts each joint from its own last impulse and its sweeps carry a joint's correction one
link a sweep, so a chain's contacts wait on their joints (docs/research/2026-12-07-where-jointed-
worlds-lose.md). Where every joint of the request is a rigid revolute one (no limit, no motor;
the request's joint_revolute), the server here

- holds each joint as two contact points at its anchor, normals opposed, pressing and sticking in
  a cone too wide to bound them (a rigid revolute joint's two rows), and asks the face route
  (its classifier on the points and the joints' points, then its solve and admission) for the
  whole step: its answer at the contact points and the joints' impulses;
- prices five starts on its copy of the step with the joints in it, as b2RevoluteJoint sweeps
  them before the contacts in each sweep (deepcontact.faces.sweeps_to_stop with RevoluteRows),
  each to the client's stopping rule: Box2D's start, the served answer and the route's answer,
  each with the joints' own last impulses, and the served and the route's answers with the
  route's joint impulses;
- serves the one that stops soonest, with its joints' start on the reply (Impulses.joint_impulses)
  where it is the route's.

    best = start_with_joints(route, bodies, points, joints, revolute, world, step, previous, friction, served,
                             deadline, timing=PricingTime())    # the server keeps one PricingTime

Closed loop on the chain of `examples/` over the choosing seeds 850-899 this takes the default from
0.969x to 0.731x of Builtin's iterations (`deepcontact lab joint-start --runs best:replica`).
"""

from __future__ import annotations

import time

import numpy as np

from deepcontact.faces import RevoluteRows, route_compiled, sweeps_to_stop
from server.predictors import Prediction

#: A joint's two points' keys: far above any contact's (the engine's are 32-bit feature keys).
KEY_BASE = 2**63
#: The label (N s along the normal: pressing) and the cone (friction) of a joint's points in the
#: route: pressing and sticking, in a cone no impulse of a step reaches.
JOINT_LABEL = 1e3
JOINT_FRICTION = 1e3
#: The friction the classifier reads at a joint's points, as its research networks were trained.
JOINT_POINT_FRICTION = 1.0
#: served_by of a step whose best start is Box2D's own.
BUILTIN = "builtin"
#: The admission's rounds of the route with the joints as points: on the chain's choosing seeds
#: 850-899 closed loop 0.697x of Builtin's iterations at 30, 0.709x at the zoo card's 100, and
#: about 0.3 ms less a step (`deepcontact lab joint-start --runs served+revolute`).
ROUNDS = 30


def all_rigid(revolute: np.ndarray | None) -> bool:
    """Whether the request says every one of its joints (at least one) is a rigid revolute one."""
    return revolute is not None and len(revolute) > 0 and bool((revolute[:, 0] == 1).all())


def joint_points(points: np.ndarray, joints: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """The 2 J records (points' dtype) of the joints as contact points: each joint's two, at its
    anchor on body B between its two bodies (joints (J, 2) rows of the step's bodies), normals +x
    and -x; their builtin the joint's last impulse (revolute (J, 7), wire.decode_revolute's: along
    each normal where it points that way, half the rest along the tangent)."""
    J = len(joints)
    i = np.repeat(np.arange(J), 2)
    sign = np.tile(np.array([1.0, -1.0], np.float32), J)
    out = np.zeros(2 * J, points.dtype)
    out["key"] = np.uint64(KEY_BASE) + (2 * i + (sign < 0)).astype(np.uint64)
    out["body_a"], out["body_b"] = joints[i, 0], joints[i, 1]
    out["point"] = revolute[i, 3:5]
    out["normal"][:, 0] = sign
    impulse = revolute[i, 5:7]
    out["builtin"][:, 0] = np.maximum(sign * impulse[:, 0], 0.0)
    out["builtin"][:, 1] = 0.5 * (-sign * impulse[:, 1])
    out["warm_start"] = out["builtin"]
    out["impulse"] = (1.0, 0.0)
    out["friction"] = JOINT_POINT_FRICTION
    return out


def joints_on_b(answer: np.ndarray) -> np.ndarray:
    """(J, 2) N s, on each joint's body B: the joints' impulses an answer at their points
    (joint_points's 2 J, (2 J, 2) N s (normal, tangent)) holds."""
    a = np.asarray(answer, np.float64).reshape(-1, 2, 2)  # (J, its two points, normal and tangent)
    sign = np.array([1.0, -1.0])
    return np.stack([(sign * a[:, :, 0]).sum(1), (-sign * a[:, :, 1]).sum(1)], 1)


def rows(bodies: np.ndarray, joints: np.ndarray, revolute: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bodies (J, 2) int64, arms (J, 4) m, own (J, 2) N s): RevoluteRows's pieces, each joint's
    arms from its bodies' centres of mass (bodies' position) to its anchors, and its own last impulse."""
    centres = np.asarray(bodies["position"], np.float64)
    ab = np.asarray(joints, np.int64)
    arms = np.asarray(revolute[:, 1:5], np.float64) - np.concatenate([centres[ab[:, 0]], centres[ab[:, 1]]], 1)
    return ab, arms, np.asarray(revolute[:, 5:7], np.float64)


def joint_route(predictor):
    """The face route that answers worlds its card's own classifier was not trained on: the last
    face route along the predictor's fallbacks (the default's `zoo`), where its card sets
    revolute_joints; else None."""
    from server.face_route import FaceRoutePredictor

    found = None
    while isinstance(predictor, FaceRoutePredictor):
        found, predictor = predictor, predictor.fallback
    return found if found is not None and found.settings["revolute_joints"] else None


class PricingTime:
    """How long start_with_joints has taken (s, a moving average over the steps it priced): a
    step whose deadline it would miss keeps the served answer, which reaches the client in time,
    rather than a better one too late (and then Box2D's own start at the client)."""

    def __init__(self, weight: float = 0.2):
        self.seconds, self.weight = 0.0, weight

    def fits(self, now: float, deadline: float | None) -> bool:
        return deadline is None or now + self.seconds <= deadline

    def observe(self, seconds: float) -> None:
        self.seconds = seconds if self.seconds == 0.0 else self.seconds + self.weight * (seconds - self.seconds)


def joint_labels(route, bodies: np.ndarray, points: np.ndarray, joints: np.ndarray, revolute: np.ndarray, world,
                 step: int, previous, friction: np.ndarray) -> tuple[np.ndarray, np.ndarray, Prediction, float]:
    """(both, mu, labels, seconds): the step's points and the joints' (joint_points), the friction
    the route's classifier reads at them ((P + 2 J,) float32), its answer there and what it took.
    It depends on nothing served, so a server with a core to spare asks it while the served
    answer is made (start_with_joints's `labelled`)."""
    t0 = time.perf_counter()
    both = np.concatenate([points, joint_points(points, joints, revolute)])
    mu = np.concatenate([np.asarray(friction, np.float32), np.full(2 * len(joints), JOINT_POINT_FRICTION, np.float32)])
    labels = route.classifier.predict(bodies, both, world, step, previous, friction=mu)
    return both, mu, labels, time.perf_counter() - t0


def start_with_joints(route, bodies: np.ndarray, points: np.ndarray, joints: np.ndarray, revolute: np.ndarray, world,
                      step: int, previous, friction: np.ndarray, served: Prediction,
                      deadline: float | None = None, timing: PricingTime | None = None,
                      labelled=None) -> Prediction:
    """The served answer, or the start of five that the step's copy with its joints says stops
    soonest (module docstring). route: joint_route's; joints (J, 2) rows of bodies, every one a
    rigid revolute joint (revolute (J, 7), all_rigid); friction (P,); served: the step's answer
    as served without the joints; deadline: perf_counter() s, by which the answer must be ready
    (timing: what the pricing has taken, kept across steps; where it would end past the deadline
    the served answer is returned as it is); labelled: a future of joint_labels's for the same
    step, asked on another core while the served answer was made, or None (asked here). Its
    stages add the classifier's, the route's and the pricing's seconds (inference, admit)."""
    t0 = time.perf_counter()
    if route is None or world.tolerance <= 0 or len(points) == 0 or (deadline is not None and t0 >= deadline) or (
            timing is not None and not timing.fits(t0, deadline)):
        return served
    P = len(points)
    both, mu, labels, asked = (labelled.result() if labelled is not None else
                               joint_labels(route, bodies, points, joints, revolute, world, step, previous, friction))
    t1 = time.perf_counter()
    face = np.asarray(labels.impulses, np.float64).copy()
    face[P:] = (JOINT_LABEL, 0.0)
    mu[P:] = JOINT_FRICTION
    s = route.settings
    solved = route_compiled(bodies, both, face, np.asarray(mu, np.float64), world.physics, s["pressing"], s["share"],
                            s["label_friction"], min(ROUNDS, s["rounds"]), None, None, s["relax"], s["rho"], None)
    ab, arms, own = rows(bodies, joints, revolute)
    starts = [np.asarray(points["builtin"], np.float64), np.asarray(served.impulses, np.float64)]
    joint_starts = [own, own]
    if solved is not None:
        answer = np.asarray(solved.impulses, np.float64)
        theirs = joints_on_b(answer[P:])
        starts += [answer[:P], starts[1], answer[:P]]
        joint_starts += [own, theirs, theirs]
    mu, most = np.asarray(friction, np.float64), route.settings["check_sweeps"] or 200
    # Box2D's start first: a start that has not stopped by the sweep where it stopped has lost,
    # so none is played further (on a step where the others lose that spares most of the sweeps).
    counts, changes = sweeps_to_stop(bodies, points, np.stack(starts[:1]), mu, world.physics, world.tolerance, most,
                                     None, RevoluteRows(ab, arms, np.stack(joint_starts[:1])))
    rest = sweeps_to_stop(bodies, points, np.stack(starts[1:]), mu, world.physics, world.tolerance,
                          max(1, min(most, int(counts[0]))), None, RevoluteRows(ab, arms, np.stack(joint_starts[1:])))
    counts, changes = np.concatenate([counts, rest[0]]), np.concatenate([changes, rest[1]])
    best = int(np.lexsort((changes, counts))[0])
    if timing is not None:
        timing.observe(time.perf_counter() - t0)
    stages = dict(served.stages)
    stages["inference"] = stages.get("inference", 0.0) + asked
    stages["admit"] = stages.get("admit", 0.0) + (time.perf_counter() - t1)
    if best == 1:
        return Prediction(served.impulses, stages, served.served_by, served.unfamiliar)
    impulses = np.asarray(starts[best], np.float32)
    served_by = BUILTIN if best == 0 else route.name
    return Prediction(impulses, stages, served_by, served.unfamiliar,
                      joint_impulses=np.asarray(joint_starts[best], np.float32) if best >= 3 else None)
