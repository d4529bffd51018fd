"""A per-step gate: serve a model's warm start, or Box2D's, at this step?

A model's warm start loses to Box2D's own at about a quarter of the steps. The gate is a
logistic regression on features of the step that a server holds once its model has run (the
request and the model's answer, nothing the solve tells), fitted on simulated steps each
weighted by what the choice is worth there (`lab.step_gate`, `deepcontact lab step-gate`).
Where it predicts a loss, the server serves Box2D's warm start instead: the request's builtin
impulses, unchanged.

    gate = StepGate.fit(x, model_won, weight)               # x: (S, F) step_features rows
    gate.serves_model(step_features(bodies, points, answer))   # True: serve the answer

A card carries it as `step_gate` (deepcontact.modelcard), so one trained model can be served
gated and plain under two names.
"""

from __future__ import annotations

import dataclasses

import numpy as np

#: the names of step_features' entries, in order
FEATURES = (
    "log points", "share of new points", "log |builtin| rms (N s)", "log |correction| rms (N s)",
    "|correction| / |builtin|", "share of points corrected > 0.1 N s", "share corrected > 1 N s",
    "log max |correction| (N s)", "share of normal answers at 0", "share of tangent signs flipped",
    "log mean body speed (m/s)", "log max body speed (m/s)", "share of bodies moving > 0.1 m/s",
    "log mean angular speed (rad/s)", "mean penetration (m)",
)
_BODY_DYNAMIC = 2
_TINY = 1e-6  # keeps the logs and the ratio finite at a step with nothing moving or no warm start


def step_features(bodies: np.ndarray, points: np.ndarray, answer: np.ndarray) -> np.ndarray:
    """One step's features (len(FEATURES),) float64.

    bodies: (B,) BODY_DTYPE records (static bodies, if there, are left out);
    points: (P,) CONTACT_DTYPE records, P >= 1, whose builtin is Box2D's warm start;
    answer: (P, 2) the model's (normal, tangent) impulses, N s.
    """
    # Sums and counts in place of np.linalg.norm and np.mean over masks: this runs on every
    # served step, and a handful of fused reductions cost less than the plain form's many passes
    # (tests/deepcontact/test_step_gate.py holds the plain form).
    b = points["builtin"].astype(np.float64)
    a = np.asarray(answer, np.float64)
    d = a - b
    nd = np.sqrt(np.einsum("ij,ij->i", d, d))  # (P,) |correction|, N s
    nb2 = np.einsum("ij,ij->i", b, b)  # (P,) |builtin|^2
    dynamic = bodies["type"] == _BODY_DYNAMIC
    v = bodies["velocity"][dynamic].astype(np.float64)
    speed = np.sqrt(np.einsum("ij,ij->i", v, v)) if len(v) else np.zeros(1)  # m/s
    spin = np.abs(bodies["angular_velocity"][dynamic].astype(np.float64)) if len(v) else np.zeros(1)  # rad/s
    p = len(points)
    sd2, sb2 = float(nd @ nd), float(nb2.sum())
    sep = points["separation"]
    return np.array([
        np.log(p), np.count_nonzero(nb2 == 0) / p, np.log(np.sqrt(sb2 / p) + _TINY),
        np.log(np.sqrt(sd2 / p) + _TINY), np.sqrt(sd2 / (sb2 + _TINY)),
        np.count_nonzero(nd > 0.1) / p, np.count_nonzero(nd > 1.0) / p, np.log(nd.max() + _TINY),
        np.count_nonzero(a[:, 0] <= 0) / p, np.count_nonzero(a[:, 1] * b[:, 1] < 0) / p,
        np.log(speed.mean() + _TINY), np.log(speed.max() + _TINY), np.count_nonzero(speed > 0.1) / len(speed),
        np.log(spin.mean() + _TINY), float(-sep[sep < 0].astype(np.float64).sum()) / p,
    ])


@dataclasses.dataclass(frozen=True)
class StepGate:
    """P(the model's warm start takes fewer iterations) = sigmoid(c0 + c . (x - mean) / scale).

    mean, scale: (F,) the fit steps' feature means and spreads; coefficients: (F + 1,), the
    intercept first. names: the F features' names, FEATURES for a gate a server can compute;
    a screen may fit one on more (lab.step_gate's --hidden), which no card can carry.
    """

    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coefficients: tuple[float, ...]
    names: tuple[str, ...] = FEATURES

    def __post_init__(self):
        f = len(self.names)
        if (len(self.mean), len(self.scale), len(self.coefficients)) != (f, f, f + 1):
            raise ValueError(f"a step gate holds {f} means, {f} scales and {f + 1} coefficients "
                             f"(one per feature it names, and the intercept); got "
                             f"{len(self.mean)}, {len(self.scale)} and {len(self.coefficients)}")
        values = np.array(self.mean + self.scale + self.coefficients, float)
        if not np.all(np.isfinite(values)) or min(self.scale) <= 0:
            raise ValueError("a step gate's numbers are finite and its scales above 0")

    def serves_model(self, x: np.ndarray) -> np.ndarray | bool:
        """x: (F,) one step's features, or (S, F): True (each) where the gate serves the model."""
        z = (np.asarray(x, np.float64) - self.mean) / self.scale
        return self.coefficients[0] + z @ np.asarray(self.coefficients[1:]) > 0

    @classmethod
    def fit(cls, x: np.ndarray, model_won: np.ndarray, weight: np.ndarray, *, l2: float = 1e-2,
            iterations: int = 50, names: tuple[str, ...] = FEATURES) -> "StepGate":
        """A weighted logistic regression by Newton steps.

        x: (S, F) features, named by names; model_won: (S,) 1 where the model's warm start took fewer iterations
        than Box2D's, else 0; weight: (S,) each step's worth (e.g. the iterations between them),
        at least one above 0. l2 keeps the fit finite where the steps separate.
        """
        mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-9
        z = np.hstack([np.ones((len(x), 1)), (x - mean) / scale])
        w = weight / weight.mean()
        c = np.zeros(z.shape[1])
        for _ in range(iterations):
            p = 1 / (1 + np.exp(-np.clip(z @ c, -30, 30)))
            grad = z.T @ (w * (p - model_won)) + l2 * c
            hess = (z * (w * p * (1 - p))[:, None]).T @ z + l2 * np.eye(len(c))
            c -= np.linalg.solve(hess, grad)
        return cls(tuple(mean.tolist()), tuple(scale.tolist()), tuple(c.tolist()), tuple(names))

    def to_dict(self) -> dict:
        return {"features": list(self.names), "mean": list(self.mean), "scale": list(self.scale),
                "coefficients": list(self.coefficients)}

    @classmethod
    def from_dict(cls, d: dict) -> "StepGate":
        """ValueError for a gate fitted on other features than FEATURES, or malformed."""
        if not isinstance(d, dict) or set(d) != {"features", "mean", "scale", "coefficients"}:
            raise ValueError("a step gate is an object of features, mean, scale and coefficients")
        if tuple(d["features"]) != FEATURES:
            raise ValueError("this step gate was fitted on other features than deepcontact.step_gate.FEATURES")
        try:
            return cls(*(tuple(float(v) for v in d[k]) for k in ("mean", "scale", "coefficients")))
        except TypeError:
            raise ValueError("a step gate's mean, scale and coefficients are lists of numbers") from None
