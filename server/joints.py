"""Steps with joints: the learned models know contacts only.

Every model the server runs was trained on contacts between free bodies; a
joint's impulses are part of the same velocity problem, and a model that does
not see them answers for a problem that is not the step's. So the server
answers Box2D's own warm start (the request's builtin impulses) at every point
that touches a jointed body, and asks the model only about the rest: the
points between free bodies (and the static world), with the bodies'
velocities taken after the fixed impulses at the jointed points, so that the
rest is the contact problem left once those are given. A card that asks for it
(the face setting extrapolate_jointed) gets Box2D's start at the jointed points
extrapolated in time along the stream instead (deepcontact.temporal): on a
car's sprung wheels or a chain swinging onto a heap the impulses move steadily
from step to step, and the line through their last two values lands nearer.

    rows = wire.decode_joints(request)                 # (J, 2) body rows, 0 static
    answer = predict_around_joints(predictor, bodies, points, rows, world, step, ...)  # a Prediction
    answer = predict_around_joints(..., history=ImpulseHistory())  # extrapolated at the jointed points
"""

from __future__ import annotations

import numpy as np

from deepcontact.kinematics import after_impulses
from deepcontact.temporal import ImpulseHistory
from server.predictors import Prediction

#: served_by of a step whose every point touches a jointed body: nothing was left to ask a model
#: about; Box2D's start answered, or (with a history) Box2D's start extrapolated.
ALL_JOINTED = "builtin"
ALL_JOINTED_EXTRAPOLATED = "extrapolated"


def jointed_points(bodies: np.ndarray, points: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(P,) bool: the point touches a body on a joint. joints: (J, 2) rows of `bodies`; a static
    body (type 0: the wire's row 0, or any static body of the engine's own records) is the world,
    which a joint does not bind."""
    jointed = np.zeros(len(bodies), bool)
    jointed[joints.reshape(-1)] = True
    jointed[bodies["type"] == 0] = False
    return jointed[points["body_a"]] | jointed[points["body_b"]]


def predict_around_joints(predictor, bodies: np.ndarray, points: np.ndarray, joints: np.ndarray, world, step: int,
                          previous=None, friction: np.ndarray | None = None, history: ImpulseHistory | None = None,
                          **extra) -> Prediction:
    """The step's Prediction as predictor.predict gives it, with Box2D's own warm start at the
    points that touch a jointed body (joints: (J, 2) rows of `bodies`: the wire's rows, 0 static, or
    the engine's own body indices beside its own records; friction: (P,) when
    the predictor takes it; history: the stream's ImpulseHistory where that start is
    extrapolated in time, or None): impulses (P, 2) float32 N s at every point, the stages and
    served_by of the predictor's answer about the free ones. served_by is ALL_JOINTED (with a
    history ALL_JOINTED_EXTRAPOLATED) where no point is free of joints (no predictor was asked)."""
    fixed = jointed_points(bodies, points, joints)
    if history is not None:  # every step recorded, so that a point's last two starts are known when it needs them
        builtin = history.extrapolated(points, step, fixed)
    else:
        builtin = points["builtin"].astype(np.float32)
    if not fixed.any():
        return predictor.predict(bodies, points, world, step, previous, **_with(friction, None, extra))
    if fixed.all():
        return Prediction(builtin, served_by=ALL_JOINTED if history is None else ALL_JOINTED_EXTRAPOLATED)
    free = ~fixed
    moved = after_impulses(bodies, points[fixed], builtin[fixed].astype(np.float64))
    answer = predictor.predict(moved, points[free], world, step, previous, **_with(friction, free, extra))
    impulses = builtin.copy()
    impulses[free] = answer.impulses
    return Prediction(impulses, answer.stages, answer.served_by)


def _with(friction, keep, extra: dict) -> dict:
    """predict()'s keyword arguments: the friction at the kept points where the predictor takes it,
    and the restitution (extra's) at them where it is given."""
    if keep is not None and extra.get("restitution") is not None:
        extra = {**extra, "restitution": extra["restitution"][keep]}
    if friction is None:
        return extra
    return {**extra, "friction": friction if keep is None else friction[keep]}
