"""Worlds of revolute, weld and prismatic joints: each step's start priced with the joints swept
as Box2D sweeps them, the revolute joints' start served too.

Box2D starts each joint from its own last impulse and its sweeps carry a joint's correction one
link a sweep, so a chain's contacts wait on their joints (docs/research/2026-12-07-where-jointed-
worlds-lose.md). Where every joint of the request is a revolute, rigid weld or prismatic one (the
request's joint_revolute, their limits and motors in joint_limits), the server here

- holds each revolute or weld joint as two contact points at its anchor, normals opposed,
  pressing and sticking in a cone too wide to bound them (its two point rows), and asks the face route
  (its classifier on the points and the joints' points, then its solve and admission) for the
  whole step: its answer at the contact points and the joints' impulses, each active angle limit
  (and a weld's angle) held there as a point on a lever from the anchor (lever_points; a motor's
  torque and a prismatic joint are not in that solve);
- with the card's repairs, repairs that answer up to so many times (the contacts' labels read
  off its motion, deepcontact.faces.repair_face, the joints' points and levers held as they were)
  and solves the step again on each, each repair another start with its joints' start;
- prices five starts and the repairs on its copy of the step with the joints in it, as Box2D's
  joints sweep them (b2RevoluteJoint with its angle limit and motor, b2WeldJoint,
  b2PrismaticJoint) before the contacts in each sweep (deepcontact.faces.sweeps_to_stop with
  RevoluteRows), each to the client's stopping rule: Box2D's start, the served answer and the
  route's answer, each with the joints' own last impulses, and the served and the route's answers
  with the route's impulses at the revolute joints (the client sets no other kind's);
- serves the one that stops soonest, with its joints' start on the reply (Impulses.joint_impulses)
  where it is the route's.

    best = start_with_joints(route, bodies, points, joints, revolute, world, step, previous, friction, served,
                             deadline, timing=PricingTime())    # the server keeps one PricingTime

Closed loop on the chain of `examples/` over the choosing seeds 850-899 this takes the default from
0.969x to 0.731x of Builtin's iterations (`deepcontact lab joint-start --runs served+revolute`); on
Box2D's own states of 850-859 the zoo's ragdolls from 1.004x to 0.838x (0.897x before the levers)
and its jointed worlds from 0.931x to 0.766x (0.774x) (`deepcontact lab joint-start --world
simclient.zoo:ragdolls --seeds 850-859 --on-builtin`).
"""

from __future__ import annotations

import time

import numpy as np

from deepcontact.faces import (LABELS_FRICTION, RevoluteRows, face_labels, island_sweeps_to_stop, repair_face,
                               route_compiled, sweeps_to_stop)
from server.predictors import Prediction

#: A joint's two points' keys: far above any contact's (the engine's are 32-bit feature keys).
KEY_BASE = 2**63
#: An angle limit's lever point's keys (lever_points), above the joints' points'.
LEVER_KEY_BASE = 2**63 + 2**62
#: The shortest lever (m) an angle limit is held on, where the joint's arms are shorter.
LEVER_ARM = 0.05
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


#: A joint's kind in a request's joint_revolute (wire.JOINT_KINDS).
REVOLUTE, WELD, PRISMATIC = 1, 2, 3


def all_held(revolute: np.ndarray | None) -> bool:
    """Whether the request says every one of its joints (at least one) is of a kind the server's
    copy of a step holds: revolute, rigid weld or prismatic (wire.decode_revolute's (J, 15))."""
    return revolute is not None and len(revolute) > 0 and bool(np.isin(revolute[:, 0], (REVOLUTE, WELD, PRISMATIC)).all())


def limits(bodies: np.ndarray, joints: np.ndarray, revolute: np.ndarray, dt: float) -> np.ndarray | None:
    """RevoluteRows.limits, (J, 13) float64 (deepcontact/_route.c's struct joint_rows), from the
    joints as the request holds them (revolute (J, 15), wire.decode_revolute's; joints (J, 2)
    rows of `bodies`): each one's kind for the copy (0 revolute or weld, which it holds as a
    revolute joint at equal limits; 1 prismatic), its limit's state and impulse, its motor (on,
    impulse, the largest torque or force made the largest impulse in a step of dt s, speed), and
    a prismatic joint's axis and the cross products of its arms with the axis and across it
    (b2PrismaticJoint's a1, a2, s1, s2, m). None where every joint is a revolute one with no limit
    and no motor (or revolute is (J, 7): none sent)."""
    if revolute.shape[1] < 15:
        return None
    kind = revolute[:, 0]
    held = np.asarray(revolute[:, 7:15], np.float64)
    if not ((kind != REVOLUTE).any() or held[:, 0].any() or held[:, 1].any() or held[:, 2].any()):
        return None
    out = np.zeros((len(revolute), 13))
    out[:, 0] = kind == PRISMATIC
    out[:, 1:9] = held
    out[:, 5] *= dt
    centres = np.asarray(bodies["position"], np.float64)
    ab = np.asarray(joints, np.int64)
    anchor_b = np.asarray(revolute[:, 3:5], np.float64)
    from_a, r_b = anchor_b - centres[ab[:, 0]], anchor_b - centres[ab[:, 1]]  # Box2D's d + rA, and rB
    axis = held[:, 6:8]
    perp = np.stack([-axis[:, 1], axis[:, 0]], 1)
    cross = lambda u, v: u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]  # noqa: E731
    prismatic = kind == PRISMATIC
    out[prismatic, 9] = cross(from_a, axis)[prismatic]
    out[prismatic, 10] = cross(r_b, axis)[prismatic]
    out[prismatic, 11] = cross(from_a, perp)[prismatic]
    out[prismatic, 12] = cross(r_b, perp)[prismatic]
    return out


def pointed(revolute: np.ndarray) -> np.ndarray:
    """(J,) bool: the joints the route holds as two points at their anchor (revolute and weld
    joints; a prismatic one slides, and is left to the copy's pricing)."""
    return revolute[:, 0] != PRISMATIC


def joint_points(points: np.ndarray, joints: np.ndarray, revolute: np.ndarray) -> np.ndarray:
    """The 2 Jp records (points' dtype) of the pointed joints (`pointed`) as contact points: each
    one's two, at its anchor on body B between its two bodies (joints (J, 2) rows of the step's
    bodies), normals +x and -x; their builtin the joint's last point impulse (revolute (J, 7 or
    15), wire.decode_revolute's: along each normal where it points that way, half the rest along
    the tangent)."""
    keep = np.flatnonzero(pointed(revolute))
    i = np.repeat(keep, 2)
    sign = np.tile(np.array([1.0, -1.0], np.float32), len(keep))
    out = np.zeros(2 * len(keep), points.dtype)
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


def lever_points(points: np.ndarray, bodies: np.ndarray, joints: np.ndarray,
                 revolute: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each active angle limit as the route can hold it: (records (K,) of the points' dtype,
    owner (K,) int, the joint each belongs to). A revolute joint at its lower or upper limit, or
    at equal limits, and a rigid weld (revolute (J, 15), wire.decode_revolute's; joints (J, 2) rows
    of `bodies`) turn their two bodies about the anchor only one way or not at all. A contact
    point on a lever from the anchor (along +x, as long as the longer of the joint's arms, at
    least LEVER_ARM) between the same two bodies, its normal across the lever (+y where the
    limit's impulse may only be positive, -y where only negative, both at equal limits), holds
    that: its normal impulse times the lever is the limit's torque, and the joint's point rows,
    at the anchor, carry its push. Pressing and sticking, as a joint's points are; their builtin
    the limit's last impulse over the lever."""
    state = revolute[:, 7] if revolute.shape[1] >= 15 else np.zeros(len(revolute))  # (J, 7): no limits sent
    held = (revolute[:, 0] != PRISMATIC) & (state > 0)
    one_way = np.flatnonzero(held)
    both_ways = np.flatnonzero(held & (state == 3))
    owner = np.concatenate([one_way, both_ways])
    sign = np.concatenate([np.where(state[one_way] == 2, -1.0, 1.0), -np.ones(len(both_ways))])
    out = np.zeros(len(owner), points.dtype)
    if not len(owner):
        return out, owner
    centres = np.asarray(bodies["position"], np.float64)
    anchor = np.asarray(revolute[owner, 3:5], np.float64)
    a, b = joints[owner, 0], joints[owner, 1]
    arm = np.maximum(np.maximum(np.hypot(*(anchor - centres[a]).T), np.hypot(*(anchor - centres[b]).T)), LEVER_ARM)
    out["key"] = np.uint64(LEVER_KEY_BASE) + np.arange(len(owner), dtype=np.uint64)
    out["body_a"], out["body_b"] = a, b
    out["point"][:, 0], out["point"][:, 1] = anchor[:, 0] + arm, anchor[:, 1]
    out["normal"][:, 1] = sign
    out["builtin"][:, 0] = np.maximum(sign * revolute[owner, 8] / arm, 0.0)
    out["warm_start"] = out["builtin"]
    out["impulse"] = (1.0, 0.0)
    out["friction"] = JOINT_POINT_FRICTION
    return out, owner


def joints_on_b(answer: np.ndarray) -> np.ndarray:
    """(Jp, 2) N s, on each joint's body B: the joints' impulses an answer at their points
    (joint_points's 2 Jp, (2 Jp, 2) N s (normal, tangent)) holds."""
    a = np.asarray(answer, np.float64).reshape(-1, 2, 2)  # (Jp, its two points, normal and tangent)
    sign = np.array([1.0, -1.0])
    return np.stack([(sign * a[:, :, 0]).sum(1), (-sign * a[:, :, 1]).sum(1)], 1)


def rows(bodies: np.ndarray, joints: np.ndarray, revolute: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bodies (J, 2) int64, arms (J, 4) m, own (J, 2)): RevoluteRows's pieces, each joint's
    arms from its bodies' centres of mass (bodies' position) to its anchors, and its own last
    impulse (revolute's columns 5 and 6)."""
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


def _joints_start(answer: np.ndarray, n_points: int, levers: np.ndarray, owner: np.ndarray, revolute: np.ndarray,
                  own: np.ndarray) -> np.ndarray:
    """The joints' start from the route's answer with the joints in it: `own` (the joints' own
    last impulses, as rows(...) gives them) with each revolute joint's replaced by the route's
    push on its body B (the client sets no other kind's). answer: (P + 2 J' + L, 2) N s, the
    contact points', the jointed points' and the levers' (lever_points, `owner` their joints)."""
    theirs = own.copy()
    # Each joint's push on B: its two points' and its levers' (a lever's push, which the
    # joint's point rows carry in Box2D, as the limit's impulse is a pure torque there).
    push = np.zeros((len(revolute), 2))
    with_points = pointed(revolute)
    push[with_points] = joints_on_b(answer[n_points:len(answer) - len(levers)])
    lever = answer[len(answer) - len(levers):]
    n = np.asarray(levers["normal"], np.float64)
    np.add.at(push, owner, lever[:, :1] * n + lever[:, 1:] * np.stack([n[:, 1], -n[:, 0]], 1))
    on_b = push[with_points]
    theirs[revolute[:, 0] == REVOLUTE] = on_b[revolute[pointed(revolute), 0] == REVOLUTE]
    return theirs


def joint_labels(route, bodies: np.ndarray, points: np.ndarray, joints: np.ndarray, revolute: np.ndarray, world,
                 step: int, previous, friction: np.ndarray) -> tuple[np.ndarray, np.ndarray, Prediction, float]:
    """(both, mu, labels, seconds): the step's points and the joints' (joint_points), the friction
    the route's classifier reads at them ((P + 2 J,) float32), its answer there and what it took.
    It depends on nothing served, so a server with a core to spare asks it while the served
    answer is made (start_with_joints's `labelled`)."""
    t0 = time.perf_counter()
    both = np.concatenate([points, joint_points(points, joints, revolute)])
    mu = np.concatenate([np.asarray(friction, np.float32), np.full(len(both) - len(points), JOINT_POINT_FRICTION,
                                                                   np.float32)])
    labels = route.classifier.predict(bodies, both, world, step, previous, friction=mu)
    return both, mu, labels, time.perf_counter() - t0


def start_with_joints(route, bodies: np.ndarray, points: np.ndarray, joints: np.ndarray, revolute: np.ndarray, world,
                      step: int, previous, friction: np.ndarray, served: Prediction,
                      deadline: float | None = None, timing: PricingTime | None = None,
                      labelled=None, restitution: np.ndarray | None = None) -> Prediction:
    """The served answer, or the start of five that the step's copy with its joints says stops
    soonest (module docstring). route: joint_route's; joints (J, 2) rows of bodies, every one a
    joint of a kind the copy holds (revolute (J, 15), all_held); friction (P,); served: the step's answer
    as served without the joints; deadline: perf_counter() s, by which the answer must be ready
    (timing: what the pricing has taken, kept across steps; where it would end past the deadline
    the served answer is returned as it is); labelled: a future of joint_labels's for the same
    step, asked on another core while the served answer was made, or None (asked here);
    restitution: (P,) each point's, or None (deepcontact.faces.prepare_route; the joints' points
    and levers bounce at nothing). Its stages add the classifier's, the route's and the pricing's
    seconds (inference, admit)."""
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
    levers, owner = lever_points(points, bodies, joints, revolute)
    both = np.concatenate([both, levers])
    face = np.concatenate([face, np.tile([JOINT_LABEL, 0.0], (len(levers), 1))])
    mu = np.concatenate([mu, np.full(len(levers), JOINT_FRICTION, mu.dtype)])
    s = route.settings
    if not s["restitution"]:
        restitution = None
    bounce = None if restitution is None else np.concatenate([restitution, np.zeros(len(both) - P)])
    t_solve = time.perf_counter()
    solved = route_compiled(bodies, both, face, np.asarray(mu, np.float64), world.physics, s["pressing"], s["share"],
                            s["label_friction"], min(ROUNDS, s["rounds"]), None, None, s["relax"], s["rho"], None,
                            restitution=bounce)
    solve_seconds, repairs_seconds = time.perf_counter() - t_solve, 0.0
    ab, arms, own = rows(bodies, joints, revolute)
    held = limits(bodies, joints, revolute, world.physics.dt)
    starts = [np.asarray(points["builtin"], np.float64), np.asarray(served.impulses, np.float64)]
    joint_starts = [own, own]
    if solved is not None:
        answer = np.asarray(solved.impulses, np.float64)
        theirs = _joints_start(answer, P, levers, owner, revolute, own)
        starts += [answer[:P], starts[1], answer[:P]]
        joint_starts += [own, theirs, theirs]
        # The route's answer repaired (the card's repairs), each with its joints' start: the
        # contacts' labels read off its motion, the joints' points and levers held as they were.
        cone = np.asarray(mu, np.float64)
        for k in range(1, s["repairs"] + 1):
            # Begun only where it, and the pricing with k more starts (at most twice the pricing
            # as it has taken without repairs), would still end by the deadline.
            r0 = time.perf_counter()
            if deadline is not None and r0 + solve_seconds + 2 * (timing.seconds if timing is not None else 0.0) \
                    >= deadline:
                break
            relabelled = face_labels(repair_face(bodies, both, answer, cone, world.physics, restitution=bounce))
            relabelled[P:] = face[P:]
            again = route_compiled(bodies, both, relabelled, cone, world.physics, s["pressing"], s["share"],
                                   LABELS_FRICTION, min(ROUNDS, s["repair_rounds"] or s["rounds"]), None, None,
                                   s["relax"], s["rho"], None,
                                   restitution=bounce)
            if again is None:
                break
            answer = np.asarray(again.impulses, np.float64)
            starts.append(answer[:P])
            joint_starts.append(_joints_start(answer, P, levers, owner, revolute, own))
            repairs_seconds += time.perf_counter() - r0
    mu, most = np.asarray(friction, np.float64), route.settings["check_sweeps"] or 200
    # Box2D's start first: a start that has not stopped by the sweep where it stopped has lost,
    # so none is played further (on a step where the others lose that spares most of the sweeps).
    price = island_sweeps_to_stop if route.settings["by_island"] else sweeps_to_stop
    first = price(bodies, points, np.stack(starts[:1]), mu, world.physics, world.tolerance, most,
                  None, RevoluteRows(ab, arms, np.stack(joint_starts[:1]), held), restitution=restitution)
    t_rest = time.perf_counter()
    rest = price(bodies, points, np.stack(starts[1:]), mu, world.physics, world.tolerance,
                 max(1, min(most, int(first[0][0]))), None, RevoluteRows(ab, arms, np.stack(joint_starts[1:]), held),
                 restitution=restitution)
    if timing is not None:
        # The pricing as it would take without the repairs and their starts' share of the sweeps:
        # they are begun only where they fit, so they do not turn a step's pricing away.
        repaired = len(starts) - 5 if solved is not None else 0
        rest_seconds = time.perf_counter() - t_rest
        timing.observe(time.perf_counter() - t0 - repairs_seconds - rest_seconds * repaired / (len(starts) - 1))
    stages = dict(served.stages)
    stages["inference"] = stages.get("inference", 0.0) + asked
    stages["admit"] = stages.get("admit", 0.0) + (time.perf_counter() - t1)
    if route.settings["by_island"]:
        # Each island from the start that stops it soonest (Box2D stops each at its own sweep).
        islands = first[2]._replace(counts=np.concatenate([first[2].counts, rest[2].counts]),
                                    changes=np.concatenate([first[2].changes, rest[2].changes]))
        start, joint_start, chosen = islands.compose(np.stack(starts), np.stack(joint_starts))
        if (chosen == 1).all():
            return Prediction(served.impulses, stages, served.served_by, served.unfamiliar)
        served_by = BUILTIN if (chosen == 0).all() else route.name
        return Prediction(np.asarray(start, np.float32), stages, served_by, served.unfamiliar,
                          joint_impulses=np.asarray(joint_start, np.float32) if (chosen >= 3).any() else None)
    counts, changes = np.concatenate([first[0], rest[0]]), np.concatenate([first[1], rest[1]])
    best = int(np.lexsort((changes, counts))[0])
    if best == 1:
        return Prediction(served.impulses, stages, served.served_by, served.unfamiliar)
    impulses = np.asarray(starts[best], np.float32)
    served_by = BUILTIN if best == 0 else route.name
    return Prediction(impulses, stages, served_by, served.unfamiliar,
                      joint_impulses=np.asarray(joint_starts[best], np.float32) if best >= 3 else None)
