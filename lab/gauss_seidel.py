"""A NumPy replica of the contact solver's iteration: projected Gauss-Seidel on recorded steps.

    p = Steps(graph_set, mu=0.5)                        # every step of a GraphSet as one problem
    lam, sweeps = gauss_seidel(p, colour_points(p.ends, p.inverse, seed=0), threshold=1e-4, max_sweeps=1000)
    # lam (P, 2) N s where each step stopped; sweeps (S,) the sweeps each took

Per point the normal and tangent impulse are updated together (as training.graph_loss's
sweeps do), the normal kept >= 0 and the tangent inside mu times it; the points are visited
colour by colour (training.graph_loss.colour_points: no two points of a colour share a moving
body, so a colour at once is exactly its points one after another), and each step stops as
the solver does, when a sweep changes no impulse by more than the threshold. It is not
Box2D's solver (Box2D updates friction before the normal impulse, in its islands' order):
on 512 validation steps it stops within 3 % of the recorded answers' size of them and prices
the default's warm start as the engine's trial solves do (docs/results.md, "Is the answer the
solver's choice?"). Used by `deepcontact lab order` and lab.probe_screen.
"""

from __future__ import annotations

import numpy as np


class Steps:
    """Recorded steps as one problem (their disjoint union): what the replica's sweeps read.

    builtin, solution (P, 2) N s: Box2D's warm start and the recorded solve's final impulses;
    v_free (P, 2) m/s: each point's relative (normal, tangent) velocity before any impulse;
    mu (P,); ends (P, 2) int32 rows of inverse (B, 2) (1/kg, 1/(kg m^2)); geometry (P, 8):
    normal, tangent, the point from body A's and B's centre (m); masses (P, 2) kg: effective
    masses; step_of (P,) int32, each point's step (0 .. S-1, in `steps` order)."""

    def __init__(self, gs, mu: float, steps=None):
        """gs: a training.contact_graph.GraphSet; steps: which of its steps (default all), in
        the order GraphSet.batch puts them; mu > 0 at every point, or 0 for each step's own
        bound from its recorded solution (training.graph_loss.friction_bounds)."""
        from training.graph_loss import friction_bounds

        steps = np.arange(len(gs)) if steps is None else np.asarray(steps)
        features, targets, self.ends, _ = gs.batch(steps)
        self.geometry, self.masses, self.inverse = (x.astype(np.float64) for x in gs.solver_batch(steps))
        column = {n: j for j, n in enumerate(gs.inputs)}
        self.builtin = features[:, [column["builtin_normal"], column["builtin_tangent"]]].astype(np.float64)
        self.solution = self.builtin + targets.astype(np.float64)
        self.v_free = features[:, [column["vn"], column["vt"]]].astype(np.float64)
        self.step_of = np.repeat(np.arange(len(steps), dtype=np.int32), np.diff(gs.point_offsets)[steps])
        self.n_steps = len(steps)
        if mu > 0:
            self.mu = np.full(len(self.builtin), mu)
        else:
            self.mu = np.asarray(friction_bounds(self.solution, self.step_of), np.float64)

    def body_velocities(self, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dv (B, 2) m/s, dw (B,) rad/s): what impulses lam (P, 2) N s do to the bodies."""
        dv, dw = np.zeros((len(self.inverse), 2)), np.zeros(len(self.inverse))
        self._push(dv, dw, np.arange(len(lam)), lam)
        return dv, dw

    def _push(self, dv, dw, idx, lam):
        """Add to dv, dw what impulses lam (len(idx), 2) at points idx do to their bodies."""
        g = self.geometry[idx]
        impulse = lam[:, 0:1] * g[:, 0:2] + lam[:, 1:2] * g[:, 2:4]  # on body B; its opposite on A
        for k, sign, r in ((1, 1.0, g[:, 6:8]), (0, -1.0, g[:, 4:6])):  # the point's two bodies
            body = self.ends[idx, k]
            np.add.at(dv, body, sign * impulse * self.inverse[body, 0:1])
            np.add.at(dw, body, sign * (r[:, 0] * impulse[:, 1] - r[:, 1] * impulse[:, 0]) * self.inverse[body, 1])

    def relative(self, dv, dw, idx) -> np.ndarray:
        """(len(idx), 2) m/s: the (normal, tangent) relative velocity at points idx."""
        g = self.geometry[idx]

        def at(k, r):
            body = self.ends[idx, k]
            return dv[body] + dw[body][:, None] * np.stack([-r[:, 1], r[:, 0]], axis=1)

        rel = at(1, g[:, 6:8]) - at(0, g[:, 4:6])
        return self.v_free[idx] + np.stack([np.sum(rel * g[:, 0:2], axis=1), np.sum(rel * g[:, 2:4], axis=1)], axis=1)


def gauss_seidel(p: Steps, colour: np.ndarray, *, threshold: float, max_sweeps: int,
                 start: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Projected Gauss-Seidel from `start` (P, 2) N s (default Box2D's warm start), colour by
    colour (colour (P,) int32). Returns (lam (P, 2) N s, sweeps (S,)): where each step stopped
    and the sweeps it took (as the solver counts: the sweep whose largest change fell below
    `threshold`)."""
    lam = (p.builtin if start is None else start).copy()
    dv, dw = p.body_velocities(lam)
    groups = [np.flatnonzero(colour == c) for c in range(int(colour.max()) + 1)]
    active = np.ones(p.n_steps, bool)
    sweeps = np.full(p.n_steps, max_sweeps)
    for k in range(max_sweeps):  # loop over sweeps, not points
        change = np.zeros(p.n_steps)
        for idx in groups:  # loop over colours: their points share no moving body
            idx = idx[active[p.step_of[idx]]]
            if len(idx) == 0:
                continue
            step = lam[idx] - p.masses[idx] * p.relative(dv, dw, idx)
            normal = np.maximum(step[:, 0], 0.0)
            bound = p.mu[idx] * normal
            new = np.stack([normal, np.clip(step[:, 1], -bound, bound)], axis=1)
            p._push(dv, dw, idx, new - lam[idx])
            np.maximum.at(change, p.step_of[idx], np.abs(new - lam[idx]).max(axis=1))
            lam[idx] = new
        done = active & (change < threshold)
        sweeps[done] = k + 1
        active &= ~done
        if not active.any():
            break
    return lam, sweeps
