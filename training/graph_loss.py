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
    return _relative_velocities(*_body_velocities(e, ends, geometry, inverse), ends, geometry)


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


def self_stress_part(e, ends, geometry, inverse, *, iterations: int = 40):
    """The self-stress part of impulses e (P, 2) N s: e minus its least-norm part that moves
    the bodies as e does, the TensorFlow twin of deepcontact.kinematics.body_space_part.

    Solves (J^T J) y = J^T e for the bodies' y (B, 3) by `iterations` conjugate-gradient
    steps, preconditioned by the diagonal of J^T J, over the whole batch (its steps are
    independent blocks of one system), and returns e - J y, which moves no dynamic body
    (J^T of it is 0 to the steps' accuracy). Linear in e, so a loss can weigh the two
    parts of an error apart. inverse (B, 2) only says which bodies are dynamic (> 0):
    the split does not depend on the masses.
    """
    import tensorflow as tf

    dynamic = tf.cast(inverse > 0, e.dtype)
    a, b = ends[:, 0], ends[:, 1]
    n, ra, rb = geometry[:, 0:2], geometry[:, 4:6], geometry[:, 6:8]
    n_bodies = tf.shape(inverse)[0]

    def jt(lam):  # J^T: impulses at points to (force (B, 2), torque (B,)) on dynamic bodies
        return _body_velocities(lam, ends, geometry, dynamic)

    def j(y):  # J: the bodies' (v, w) to relative (normal, tangent) at points
        return _relative_velocities(y[0], y[1], ends, geometry)

    def per_body(x_a, x_b):
        return tf.math.unsorted_segment_sum(x_a, a, n_bodies) + tf.math.unsorted_segment_sum(x_b, b, n_bodies)

    # diag(J^T J): n and t are orthonormal, so each point adds 1 to either translation and
    # (r x n)^2 + (r x t)^2 = |r|^2 to the rotation of each of its bodies.
    ones = tf.ones_like(n)
    diag_v = per_body(ones, ones) * dynamic[:, 0:1]
    diag_w = per_body(tf.reduce_sum(ra * ra, axis=1), tf.reduce_sum(rb * rb, axis=1)) * dynamic[:, 1]
    inv_v = tf.where(diag_v > 0, 1.0 / tf.maximum(diag_v, 1e-12), 0.0)
    inv_w = tf.where(diag_w > 0, 1.0 / tf.maximum(diag_w, 1e-12), 0.0)

    def dot(u, v):
        return tf.reduce_sum(u[0] * v[0]) + tf.reduce_sum(u[1] * v[1])

    r = jt(e)
    y = (tf.zeros_like(r[0]), tf.zeros_like(r[1]))
    z = (r[0] * inv_v, r[1] * inv_w)
    d, rz = z, dot(r, z)
    floor = 1e-10 * rz  # converged to float32's round-off: further steps would only divide noise by noise
    for _ in range(iterations):  # conjugate-gradient steps, not points
        ad = jt(j(d))
        going = tf.logical_and(rz > floor, dot(d, ad) > 0)
        alpha = tf.where(going, rz / tf.maximum(dot(d, ad), 1e-30), 0.0)
        y = (y[0] + alpha * d[0], y[1] + alpha * d[1])
        r = (r[0] - alpha * ad[0], r[1] - alpha * ad[1])
        z = (r[0] * inv_v, r[1] * inv_w)
        rz_next = dot(r, z)
        beta = tf.where(going, rz_next / tf.maximum(rz, 1e-30), 0.0)
        d, rz = (z[0] + beta * d[0], z[1] + beta * d[1]), tf.where(going, rz_next, rz)
    return e - j(y)


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



# -- in the solver's order ------------------------------------------------------
#
# Box2D's solver is Gauss-Seidel: it updates one contact at a time and the next
# one already sees the change. The sweeps above are Jacobi's (every point from the
# same old impulses, damped to stay stable), whose slow modes fall at another
# rate. A colouring makes Gauss-Seidel cheap to run in a graph: points of one
# colour share no body that moves, so updating a whole colour at once is exactly
# updating its points one after another. A sweep runs the colours in turn, each
# seeing the velocities the earlier colours left; undamped (omega 1), as Box2D does.

MAX_COLOURS = 16
"""Colours a batch may need (piles of circles need about 6: a body touches a few others)."""


def colour_points(ends, inverse, seed: int = 0):
    """(P,) int32 colours, 0 .. at most MAX_COLOURS - 1, such that no two points of one
    colour share a body that moves (inverse mass or inertia > 0; a static body
    takes any number). ends (P, 2) int32 rows of inverse (B, 2).

    Luby's rounds with a seeded random priority: each round, every uncoloured point
    that outranks the others still free at both its moving bodies takes the colour;
    a few rounds per colour, each a handful of array operations."""
    import numpy as np

    ends = np.asarray(ends)
    n_points, n_bodies = len(ends), len(inverse)
    moves = (np.asarray(inverse) > 0).any(axis=1)
    priority = np.random.default_rng(seed).permutation(n_points)
    colour = np.full(n_points, -1, np.int32)
    left = np.ones(n_points, bool)
    c = 0
    while left.any():  # loop over colours
        if c == MAX_COLOURS:
            raise ValueError(f"the contact points need more than {MAX_COLOURS} colours (a body touching more "
                             f"than about {MAX_COLOURS // 2} others)")
        free = left.copy()
        while free.any():  # Luby's rounds, a few per colour
            idx = np.flatnonzero(free)
            best = np.full(n_bodies, n_points, np.int64)
            for k in (0, 1):  # the point's two bodies
                np.minimum.at(best, ends[idx, k], priority[idx])
            a, b = ends[idx, 0], ends[idx, 1]
            wins = idx[((best[a] == priority[idx]) | ~moves[a]) & ((best[b] == priority[idx]) | ~moves[b])]
            colour[wins], left[wins] = c, False
            taken = np.zeros(n_bodies, bool)
            taken[ends[wins].ravel()] = True
            taken &= moves
            free &= ~(taken[ends[:, 0]] | taken[ends[:, 1]])
        c += 1
    return colour


def body_impulses(lam, ends, geometry, n_bodies):
    """(net impulse (B, 2) N s, torque impulse (B,) N m s) that impulses lam (P, 2) N s put on
    every body, static ones included: J^T lam, the TensorFlow twin of deepcontact.kinematics's."""
    import tensorflow as tf  # already imported by training; not import_tensorflow(), which autograph would trace

    a, b = ends[:, 0], ends[:, 1]
    n, t, ra, rb = geometry[:, 0:2], geometry[:, 2:4], geometry[:, 4:6], geometry[:, 6:8]
    impulse = lam[:, 0:1] * n + lam[:, 1:2] * t  # on B; its opposite on A
    force = tf.math.unsorted_segment_sum(impulse, b, n_bodies) - tf.math.unsorted_segment_sum(impulse, a, n_bodies)
    torque = (tf.math.unsorted_segment_sum(_cross(rb, impulse), b, n_bodies)
              - tf.math.unsorted_segment_sum(_cross(ra, impulse), a, n_bodies))
    return force, torque


def _body_velocities(lam, ends, geometry, inverse):
    """(dv (B, 2) m/s, dw (B,) rad/s): what impulses lam (P, 2) N s do to every body."""
    import tensorflow as tf  # already imported by training; not import_tensorflow(), which autograph would trace

    force, torque = body_impulses(lam, ends, geometry, tf.shape(inverse)[0])
    return force * inverse[:, 0:1], torque * inverse[:, 1]


def _relative_velocities(dv, dw, ends, geometry):
    """(P, 2) m/s: the (normal, tangent) relative velocity at points from body velocities dv, dw."""
    import tensorflow as tf

    n, t, ra, rb = geometry[:, 0:2], geometry[:, 2:4], geometry[:, 4:6], geometry[:, 6:8]

    def at(body, r):
        w = tf.gather(dw, body)[:, None]
        return tf.gather(dv, body) + w * tf.stack([-r[:, 1], r[:, 0]], axis=1)

    rel = at(ends[:, 1], rb) - at(ends[:, 0], ra)
    return tf.stack([tf.reduce_sum(rel * n, axis=1), tf.reduce_sum(rel * t, axis=1)], axis=1)


def gauss_seidel_changes_after(lam, v_free, mu, ends, geometry, masses, inverse, colour, *, sweeps,
                               omega: float = 1.0):
    """As projected_changes_after, with the sweeps in the solver's order: each sweep updates
    the colours (colour (P,) int32 from colour_points) in turn. Returns, after each k in the
    ascending `sweeps` (no repeats), the change (P, 2) N s that sweep k+1 would make."""
    import tensorflow as tf

    # One inert point per colour (no mass: a sweep leaves it at 0 and moves no body), since
    # TensorFlow's graphs fail on an empty colour (SIGFPE, TF 2.x on CPU).
    n_points = tf.shape(lam)[0]
    colour = tf.concat([colour, tf.range(MAX_COLOURS, dtype=colour.dtype)], axis=0)

    def parts(x):
        x = tf.convert_to_tensor(x)
        pad = tf.zeros(tf.concat([[MAX_COLOURS], tf.shape(x)[1:]], axis=0), x.dtype)
        return tf.dynamic_partition(tf.concat([x, pad], axis=0), colour, MAX_COLOURS)

    index = tf.dynamic_partition(tf.range(n_points + MAX_COLOURS), colour, MAX_COLOURS)
    E, G, M, V, U = (parts(x) for x in (ends, geometry, masses, v_free, mu))

    def sweep(lams, dv, dw):
        out = []
        for c in range(MAX_COLOURS):  # loop over colours, not points
            step = lams[c] - omega * M[c] * (V[c] + _relative_velocities(dv, dw, E[c], G[c]))
            normal = tf.nn.relu(step[:, 0])
            bound = U[c] * normal
            new = tf.stack([normal, tf.clip_by_value(step[:, 1], -bound, bound)], axis=1)
            ddv, ddw = _body_velocities(new - lams[c], E[c], G[c], inverse)
            dv, dw = dv + ddv, dw + ddw
            out.append(new)
        return out, dv, dw

    lams = parts(lam)
    dv, dw = _body_velocities(lam, ends, geometry, inverse)
    out, done = [], 0
    for k in sweeps:  # a few checkpoints
        n = k - done
        if n > 0:  # a loop of no sweeps would still be traced, and its gradient with it
            _, lams, dv, dw = tf.while_loop(lambda i, *_: i < n, lambda i, ls, v, w: (i + 1, *sweep(ls, v, w)),
                                            (tf.constant(0), lams, dv, dw), maximum_iterations=n)
        after, dv, dw = sweep(lams, dv, dw)
        out.append(tf.dynamic_stitch(index, [x - y for x, y in zip(after, lams)])[:n_points])
        lams, done = after, k + 1  # the checkpoint's sweep is the next stretch's first
    return out
