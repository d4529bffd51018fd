"""A loss that weighs a warm start's error by how long the solver takes to remove it.

The solver's iteration removes a warm start's error e (impulses, N s, per
point: normal, tangent) mode by mode: local, jagged errors go in a few sweeps,
smooth errors spread over a pile take hundreds. Iteration counts follow the
slow modes, so a plain MSE can fall while the iterations rise (docs/results.md,
the oracle experiments). This loss runs `sweeps` damped Jacobi sweeps of the
unconstrained contact problem on e and measures what is left:

    A e        = J M^-1 J^T e    relative velocity each point gets from e (m/s)
    e <- e - omega * m_eff * (A e)                       one sweep, per point

with J the points' Jacobian rows (normal and tangent at both bodies),
M^-1 the bodies' inverse masses and inertias, m_eff the effective masses
(1 / diag(A)). Friction limits and non-negative normal impulses are left out:
the loss is linear in e, so it is a weighted MSE whose weights favour the
slow modes.

    left = jacobi_error(e, ends, geometry, masses, inverse, sweeps=16, omega=0.3)
    # e (P, 2) N s; ends (P, 2) int32; geometry (P, 8); masses (P, 2) kg;
    # inverse (B, 2) (1/kg, 1/(kg m^2)); left (P, 2) N s
"""

from __future__ import annotations


def _cross(r, v):
    """2-D cross product of (P, 2) tensors: (P,)."""
    return r[:, 0] * v[:, 1] - r[:, 1] * v[:, 0]


def apply_delassus(e, ends, geometry, inverse):
    """A e: the relative (normal, tangent) velocity, (P, 2) m/s, that impulses e cause at every point."""
    import tensorflow as tf  # already imported by training; not import_tensorflow(), which autograph would trace

    a, b = ends[:, 0], ends[:, 1]
    n, t, ra, rb = geometry[:, 0:2], geometry[:, 2:4], geometry[:, 4:6], geometry[:, 6:8]
    n_bodies = tf.shape(inverse)[0]
    impulse = e[:, 0:1] * n + e[:, 1:2] * t  # on B; its opposite on A
    force = tf.math.unsorted_segment_sum(impulse, b, n_bodies) - tf.math.unsorted_segment_sum(impulse, a, n_bodies)
    torque = (tf.math.unsorted_segment_sum(_cross(rb, impulse), b, n_bodies)
              - tf.math.unsorted_segment_sum(_cross(ra, impulse), a, n_bodies))
    dv = force * inverse[:, 0:1]
    dw = torque * inverse[:, 1]

    def point_velocity(body, r):
        w = tf.gather(dw, body)[:, None]
        return tf.gather(dv, body) + w * tf.stack([-r[:, 1], r[:, 0]], axis=1)

    rel = point_velocity(b, rb) - point_velocity(a, ra)
    return tf.stack([tf.reduce_sum(rel * n, axis=1), tf.reduce_sum(rel * t, axis=1)], axis=1)


def jacobi_error(e, ends, geometry, masses, inverse, *, sweeps: int, omega: float):
    """The error left of e after `sweeps` damped Jacobi sweeps, (P, 2) N s."""
    for _ in range(sweeps):  # loop over sweeps, not points
        e = e - omega * masses * apply_delassus(e, ends, geometry, inverse)
    return e


def residuals_after(e, ends, geometry, masses, inverse, *, sweeps, omega: float):
    """The solver's residual m_eff * (A e_k), (P, 2) N s, after each k in the ascending
    `sweeps`: the impulse change sweep k+1 would make. The solver stops when
    the largest such change is below its threshold, so late sweeps' residuals are
    what the iteration count follows; null-space errors (impulses that move
    no body) leave none."""
    out, done = [], 0
    for k in sweeps:  # a few checkpoints
        e = jacobi_error(e, ends, geometry, masses, inverse, sweeps=k - done, omega=omega)
        done = k
        out.append(masses * apply_delassus(e, ends, geometry, inverse))
    return out


# -- with the contact problem's limits ----------------------------------------
#
# The sweeps above solve the problem without its limits: the error e alone, as
# if every contact held and friction never slid. The solver keeps the normal
# impulse >= 0 and the tangent one inside the friction cone, so contacts that
# let go and contacts that slide follow other rules. These sweeps run the whole
# problem from the served impulses lam (not from the error):
#
#     v   = v_free + A lam                 relative velocity after lam (m/s)
#     lam <- project(lam - omega * m_eff * v)
#
# with project: normal = max(0, normal), tangent clipped to +-mu * normal. The
# recorded solution is (to the solver's threshold) a fixed point; what a sweep
# still changes is what the solver's stopping rule measures.


def friction_bounds(solution, step_of):
    """mu per point, (P,): the largest |tangent| / normal of its step's solution
    (points pressing with more than 1e-4 N s). The friction coefficient is not
    recorded; this bound keeps every recorded solution inside its cone.
    solution (P, 2) N s; step_of (P,) int32, each point's step in the batch."""
    import tensorflow as tf

    pressing = solution[:, 0] > 1e-4
    ratio = tf.where(pressing, tf.abs(solution[:, 1]) / tf.where(pressing, solution[:, 0], 1.0), 0.0)
    per_step = tf.math.unsorted_segment_max(ratio, step_of, tf.reduce_max(step_of) + 1)
    return tf.maximum(tf.gather(per_step, step_of), 0.0)


def projected_sweep(lam, v_free, mu, ends, geometry, masses, inverse, *, omega: float):
    """One damped projected Jacobi sweep from impulses lam (P, 2) N s; v_free (P, 2) m/s
    is the relative velocity before any impulse (after gravity); mu (P,)."""
    import tensorflow as tf

    step = lam - omega * masses * (v_free + apply_delassus(lam, ends, geometry, inverse))
    normal = tf.nn.relu(step[:, 0])
    bound = mu * normal
    return tf.stack([normal, tf.clip_by_value(step[:, 1], -bound, bound)], axis=1)


def projected_changes_after(lam, v_free, mu, ends, geometry, masses, inverse, *, sweeps, omega: float):
    """The change, (P, 2) N s, that projected sweep k+1 would make, after each k in the
    ascending `sweeps`, starting from impulses lam: the solver's stopping measure."""
    out, done = [], 0
    for k in sweeps:  # a few checkpoints
        for _ in range(k - done):  # loop over sweeps, not points
            lam = projected_sweep(lam, v_free, mu, ends, geometry, masses, inverse, omega=omega)
        done = k
        out.append(projected_sweep(lam, v_free, mu, ends, geometry, masses, inverse, omega=omega) - lam)
    return out


NORM_FLOOR = 3e-5  # N s: a step's largest change counts as at least this, below the 1e-4 N s stopping rule


def step_log_norms(change, step_of, n_steps, *, p: int = 8, weight=None):
    """log of the p-norm over each step's points of `change` (P, 2) N s, (n_steps,): for
    large p nearly the step's largest change, what the stopping rule compares with 1e-4 N s;
    floored at NORM_FLOOR. weight (2,) scales the normal and tangent terms (default 1, 1).
    step_of (P,) int32: each point's step. p above 8 underflows float32."""
    import tensorflow as tf

    terms = tf.abs(change) ** p
    if weight is not None:
        terms = terms * weight
    return tf.math.log(tf.math.unsorted_segment_sum(tf.reduce_sum(terms, axis=1), step_of, n_steps)
                       + NORM_FLOOR ** p) / p

