/* The face route after its classifier, whole, in one call: a classifier's answer read as labels,
 * the step solved on them, the result admitted into the friction cones, and how far the
 * admitted impulses leave the labels' equations unmet (deepcontact.faces.solved_on_labels,
 * with its shipped settings: the dual solve, no damping, no relabelling).
 *
 * deepcontact/faces.py owns the route and documents it, and runs it in NumPy and the compiled
 * pieces (deepcontact/_faces.c, _admission.c) where a card asks for what this does not do; the
 * arithmetic here is theirs (face_kernels.h, admission_kernels.h, contact_jacobian.h,
 * contact_records.h). Called per served step, it takes the Python glue between those pieces out
 * of the step: the contact frame, the labels, the system's index, the unpacking, the
 * admissibility test and the residual were two dozen NumPy calls, about 0.15-0.25 ms of a
 * step. tests/deepcontact/test_route.py checks it against faces.solved_on_labels.
 * -ffp-contract=off (setup.py), as for every kernel here.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "admission_kernels.h"
#include "contact_jacobian.h"
#include "contact_records.h"
#include "face_kernels.h"

/* deepcontact.faces' labels. */
enum { OPEN = 0, STICKS = 1, SLIDES_PLUS = 2, SLIDES_MINUS = 3 };
/* solve_and_admit's outcomes. */
enum { ROUTE_SERVED = 0, ROUTE_NOT_DEFINITE = 1, ROUTE_INCONSISTENT = 2 };

/* What a step's geometry gives the route, whatever its labels: the contact frame
 * (kinematics.contact_frame), the velocities before any impulse, and the admission's J^T, body
 * order and factor of J^T J (admission.admission_factors). Built by prepare (on another thread,
 * while the classifier runs) or by solve_and_admit itself; all malloc'd. */
struct geometry {
    int64_t P, B;
    int32_t n_dyn, rows;
    int64_t *pa, *pb;
    int32_t *row, *jp, *ji, *order, *inverse;
    unsigned char *dynamic;
    double *inv_mass, *inv_inertia, *n, *t, *ra, *rb, *vx, *vy, *w, *before, *jd, *weight;
    /* (P,) the normal velocity Box2D's velocity constraint holds each point at (m/s, >= 0): its
     * restitution's bounce where it closes faster than b2_velocityThreshold, else 0. */
    double *bias;
    spchol_factor_t factor;
    int factored;
};

static void geometry_free(struct geometry *g)
{
    free(g->pa), free(g->pb), free(g->row), free(g->jp), free(g->ji), free(g->order), free(g->inverse);
    free(g->dynamic), free(g->inv_mass), free(g->inv_inertia), free(g->n), free(g->t), free(g->ra), free(g->rb);
    free(g->vx), free(g->vy), free(g->w), free(g->before), free(g->jd), free(g->weight), free(g->bias);
    spchol_free(&g->factor);
    memset(g, 0, sizeof *g);
}

/* Box2D's b2_velocityThreshold (m/s): a point closing slower than this does not bounce. */
#define VELOCITY_THRESHOLD 1.0

/* The frame and the velocities before any impulse, gravity added, and each point's bounce
 * (b2ContactSolver::InitializeVelocityConstraints' velocityBias: -restitution times the normal
 * velocity before any impulse, where the point closes faster than VELOCITY_THRESHOLD) from
 * restitution (P,) (Box2D's mix of its two fixtures', the larger), or none where NULL. Returns
 * 0, or -1 (memory). */
static int geometry_build(struct geometry *g, const char *bodies, const char *points, int64_t P, int64_t B, double dt,
                          double gx, double gy, const double *restitution)
{
    memset(g, 0, sizeof *g);
    g->P = P, g->B = B;
    const size_t p = (size_t)P + 1, b = (size_t)B + 1;
    g->pa = malloc(p * sizeof(int64_t));
    g->pb = malloc(p * sizeof(int64_t));
    g->row = malloc(b * sizeof(int32_t));
    g->dynamic = malloc(b);
    g->bias = malloc(p * sizeof(double));
    double **per_body[] = {&g->inv_mass, &g->inv_inertia, &g->vx, &g->vy, &g->w};
    for (size_t k = 0; k < sizeof per_body / sizeof per_body[0]; k++)
        *per_body[k] = malloc(b * sizeof(double));
    double **per_point[] = {&g->n, &g->t, &g->ra, &g->rb, &g->before};
    for (size_t k = 0; k < sizeof per_point / sizeof per_point[0]; k++)
        *per_point[k] = malloc(2 * p * sizeof(double));
    if (!(g->pa && g->pb && g->row && g->dynamic && g->inv_mass && g->inv_inertia && g->vx && g->vy && g->w && g->n
          && g->t && g->ra && g->rb && g->before && g->bias))
        return -1;
    for (int64_t k = 0; k < B; k++) {
        const char *body = bodies + k * BODY_SIZE;
        const int dynamic = i32_at(body, BODY_TYPE) == BODY_DYNAMIC;
        const double on = dynamic ? 1.0 : 0.0;
        /* A kinematic body moves as it was sent (a turning drum, a lift) and no impulse moves it:
         * its velocity enters the points' relative velocities, gravity does not. A static body's
         * is zero. */
        const double moves = i32_at(body, BODY_TYPE) == BODY_STATIC ? 0.0 : 1.0;
        g->dynamic[k] = (unsigned char)dynamic;
        g->row[k] = dynamic ? g->n_dyn++ : -1;
        g->vx[k] = f32_at(body, BODY_VELOCITY) * moves;
        g->vy[k] = f32_at(body, BODY_VELOCITY + 4) * moves;
        g->w[k] = f32_at(body, BODY_ANGULAR_VELOCITY) * moves;
        if (dt != 0.0) {
            g->vx[k] += (dt * gx) * on;
            g->vy[k] += (dt * gy) * on;
        }
        g->inv_mass[k] = inverse_of(f32_at(body, BODY_MASS), dynamic);
        g->inv_inertia[k] = inverse_of(f32_at(body, BODY_INERTIA), dynamic);
    }
    g->rows = 3 * g->n_dyn;
    struct frame f;
    for (int64_t i = 0; i < P; i++) {
        frame_of(points + i * POINT_SIZE, bodies, &f);
        g->pa[i] = f.a;
        g->pb[i] = f.b;
        g->n[2 * i] = f.n0, g->n[2 * i + 1] = f.n1, g->t[2 * i] = f.t0, g->t[2 * i + 1] = f.t1;
        g->ra[2 * i] = f.ra0, g->ra[2 * i + 1] = f.ra1, g->rb[2 * i] = f.rb0, g->rb[2 * i + 1] = f.rb1;
        relative_velocity(&f, g->vx, g->vy, g->w, g->before + 2 * i);
        const double closing = g->before[2 * i];
        g->bias[i] = restitution != NULL && closing < -VELOCITY_THRESHOLD ? -restitution[i] * closing : 0.0;
    }
    return 0;
}

/* The step's J^T and its rows in a minimum degree order of the bodies (each body's three rows
 * together): what both the admission's factor and the face solve in the bodies' space
 * (face_kernels.h, face_body_solve) are built on. Returns 0, or -1 (memory). */
static int geometry_jacobian(struct geometry *g)
{
    if (g->jp != NULL)
        return 0;
    const int32_t rows = g->rows;
    const int64_t P = g->P;
    g->jp = malloc(((size_t)rows + 1) * sizeof(int32_t));
    g->ji = malloc(((size_t)12 * P + 1) * sizeof(int32_t));
    g->jd = malloc(((size_t)12 * P + 1) * sizeof(double));
    g->order = malloc(((size_t)rows + 1) * sizeof(int32_t));
    g->inverse = malloc(((size_t)rows + 1) * sizeof(int32_t));
    g->weight = malloc(((size_t)rows + 1) * sizeof(double));
    if (g->jp == NULL || g->ji == NULL || g->jd == NULL || g->order == NULL || g->inverse == NULL || g->weight == NULL) {
        free(g->jp), free(g->ji), free(g->jd), free(g->order), free(g->inverse), free(g->weight);
        g->jp = g->ji = g->order = g->inverse = NULL;
        g->jd = g->weight = NULL;
        return -1;
    }
    jacobian_transpose_csr(P, g->pa, g->pb, g->row, g->n, g->t, g->ra, g->rb, rows, g->jp, g->ji, g->jd);
    for (int64_t k = 0; k < g->B; k++)
        if (g->row[k] >= 0) {
            const int32_t r = 3 * g->row[k];
            g->weight[r] = g->weight[r + 1] = sqrt(g->inv_mass[k]);
            g->weight[r + 2] = sqrt(g->inv_inertia[k]);
        }
    if (body_order_min_degree(P, g->pa, g->pb, g->row, g->n_dyn, g->order) != 0)
        return -1;
    for (int32_t q = g->n_dyn - 1; q >= 0; q--) /* each body's three rows, in its order */
        for (int d = 2; d >= 0; d--)
            g->order[3 * q + d] = 3 * g->order[q] + d;
    return 0;
}

/* The admission's factor of J^T J, on geometry_jacobian's J^T and order. Returns 0, -1
 * (memory) or 1 (a pivot). */
static int geometry_factor(struct geometry *g)
{
    if (g->factored)
        return 0;
    if (geometry_jacobian(g) != 0)
        return -1;
    int status = gram_factor(g->rows, (int32_t)(2 * g->P), g->jp, g->ji, g->jd, g->order, 1e-9, g->inverse, &g->factor);
    g->factored = status == 0;
    return status;
}

/* What one step's labels give the route, all malloc'd at once. */
struct step {
    int64_t *index;
    unsigned char *face;
    double *slide, *rhs, *x, *keep, *after;
};

static void free_step(struct step *s)
{
    free(s->index), free(s->face), free(s->slide), free(s->rhs), free(s->x), free(s->keep), free(s->after);
}

static int alloc_step(struct step *s, int64_t P)
{
    memset(s, 0, sizeof *s);
    const size_t p = (size_t)P + 1;
    s->index = malloc(2 * p * sizeof(int64_t));
    s->face = malloc(p);
    s->slide = malloc(p * sizeof(double));
    s->keep = malloc(p * sizeof(double));
    s->rhs = malloc(2 * p * sizeof(double));
    s->x = malloc(2 * p * sizeof(double));
    s->after = malloc(2 * p * sizeof(double));
    return s->index && s->face && s->slide && s->keep && s->rhs && s->x && s->after;
}

/* A kept point key and its row, sorted by key for carry_begin's binary search. */
struct keyed {
    uint64_t key;
    int64_t row;
};

static int by_key(const void *x, const void *y)
{
    const uint64_t a = ((const struct keyed *)x)->key, b = ((const struct keyed *)y)->key;
    return a < b ? -1 : (a > b);
}

/* The admission's starting state (P, 4) of this step's points (records, their key at offset 0)
 * from the state kept (Q, 4) under keys (Q,) on the step before: a point found there begins at
 * its z (and its s with dual, else 0), the others NaN (cold). Returns 0, or -1 (memory). */
static int carry_begin(const uint64_t *keys, const double *kept, int64_t Q, const char *points, int64_t P, int dual,
                       double *state)
{
    struct keyed *sorted = malloc(((size_t)Q + 1) * sizeof *sorted);
    if (sorted == NULL)
        return -1;
    for (int64_t q = 0; q < Q; q++)
        sorted[q].key = keys[q], sorted[q].row = q;
    qsort(sorted, (size_t)Q, sizeof *sorted, by_key);
    for (int64_t i = 0; i < P; i++) {
        struct keyed want;
        memcpy(&want.key, points + i * POINT_SIZE + POINT_KEY, sizeof want.key);
        const struct keyed *found = Q ? bsearch(&want, sorted, (size_t)Q, sizeof *sorted, by_key) : NULL;
        double *to = state + 4 * i;
        if (found == NULL) {
            to[0] = to[1] = to[2] = to[3] = NAN;
        } else {
            const double *from = kept + 4 * found->row;
            to[0] = from[0], to[1] = from[1];
            to[2] = dual ? from[2] : 0.0, to[3] = dual ? from[3] : 0.0;
        }
    }
    free(sorted);
    return 0;
}

static const char GEOMETRY[] = "deepcontact._route.geometry";

static void geometry_capsule_free(PyObject *capsule)
{
    struct geometry *g = PyCapsule_GetPointer(capsule, GEOMETRY);
    if (g != NULL) {
        geometry_free(g);
        free(g);
    }
}

/* The step's geometry where a caller passed prepare's (a capsule for these P points and B
 * bodies), else `own`, zeroed, for the caller to build; NULL with a Python error set for an
 * object that is not one, or one prepared for another step. `who` names the caller. */
static struct geometry *prepared_or_own(PyObject *prepared, int64_t P, int64_t B, struct geometry *own, const char *who)
{
    memset(own, 0, sizeof *own);
    if (prepared == Py_None)
        return own;
    struct geometry *g = PyCapsule_GetPointer(prepared, GEOMETRY);
    if (g != NULL && (g->P != P || g->B != B)) {
        PyErr_Format(PyExc_ValueError, "_route.%s: a geometry prepared for another step", who);
        return NULL;
    }
    return g;
}

/* prepare(bodies, n_bodies, points, n_points, dt, gx, gy[, restitution]) -> geometry
 *
 * restitution: None, or float64 (P,) each point's restitution (geometry_build's bounce).
 * A step's geometry (struct geometry), its admission's factor included, for solve_and_admit to
 * take: built without the GIL, so that a server can build it on another core while its
 * classifier runs on the same step (deepcontact.faces.prepare_route). An opaque capsule. */
static PyObject *prepare(PyObject *self, PyObject *args)
{
    Py_buffer b[3];
    Py_ssize_t n_bodies, n_points;
    double dt, gx, gy;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*ny*nddd|z*", &b[0], &n_bodies, &b[1], &n_points, &dt, &gx, &gy, &b[2]))
        return NULL;
    PyObject *result = NULL;
    struct geometry *g = NULL;
    if (n_bodies < 0 || n_points < 0 || n_points > INT32_MAX / 16 || b[0].len != n_bodies * BODY_SIZE
        || b[1].len != n_points * POINT_SIZE || (b[2].buf != NULL && b[2].len != n_points * (Py_ssize_t)sizeof(double))) {
        PyErr_SetString(PyExc_ValueError, "_route.prepare: arrays of the wrong size");
        goto done;
    }
    if (!points_in_range(b[1].buf, n_points, n_bodies)) {
        PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
        goto done;
    }
    int status;
    Py_BEGIN_ALLOW_THREADS
    g = calloc(1, sizeof *g);
    status = g == NULL ? -1 : geometry_build(g, b[0].buf, b[1].buf, n_points, n_bodies, dt, gx, gy, b[2].buf);
    if (status == 0)
        status = geometry_factor(g);
    Py_END_ALLOW_THREADS
    if (status != 0) {
        if (g != NULL)
            geometry_free(g);
        free(g);
        if (status < 0)
            PyErr_NoMemory();
        else
            PyErr_SetString(PyExc_ArithmeticError, "_route.prepare: a pivot");
        goto done;
    }
    result = PyCapsule_New(g, GEOMETRY, geometry_capsule_free);
    if (result == NULL) {
        geometry_free(g);
        free(g);
    }
done:
    for (int k = 0; k < 3; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

/* solve_and_admit(bodies, n_bodies, points, n_points, labels, mu, read_mu, dt, gx, gy, pressing,
 *                 share, rounds, relax, rho, until, ridge, refinements, optimality, slide_in_bodies,
 *                 impulses, geometry[, carry[, restitution]])
 *     -> (outcome, residual, solve_seconds, admit_seconds, admission_rounds, in_bodies)
 *
 * bodies, points: BODY_DTYPE and CONTACT_DTYPE records; labels float64 (P, 2), the classifier's
 * answer (N s); mu float64 (P,) each point's friction; read_mu float64 (P,) the friction the
 * sliding labels are read at (mu, or the card's label_friction everywhere); dt (s), gx, gy
 * (m/s^2); pressing (N s) and share: how the labels are read (faces.contact_face); rounds,
 * relax (its over-relaxation, admission_kernels.h), rho (its ADMM penalty), until (CLOCK_MONOTONIC
 * s, 0: none): the admission's; ridge, refinements, optimality: the dual solve's (faces.DUAL_*);
 * slide_in_bodies: whether a step where points slide is tried in the bodies' space
 * (face_body_solve); impulses float64 (P, 2) out; geometry: prepare's for these
 * bodies and points, or None (built here); carry: None, or (kept_keys, kept, state, dual): the
 * admission state (z, s) of the stream's step before, kept (Q, 4) float64 under kept_keys (Q,)
 * uint64 point keys, each point of this step that is among them begins there (its s only with
 * dual; elsewhere cold), and state (P, 4) float64 gets the state this step's rounds end in
 * (admission_kernels.h; (impulses, 0) where no round ran), for the next; restitution: None, or float64
 * (P,) each point's (geometry_build's bounce, the velocity its normal equation holds; with
 * geometry, prepare's holds it already). outcome: ROUTE_SERVED (impulses written, residual
 * faces.face_residual of them), ROUTE_NOT_DEFINITE (the sparse factor met a pivot below zero:
 * the caller solves densely) or ROUTE_INCONSISTENT (the labels' system is far from
 * consistent); in_bodies: 1 where the bodies' space answered the solve (face_body_solve), 0 where
 * the dual did or nothing was solved. */
static PyObject *solve_and_admit(PyObject *self, PyObject *args)
{
    Py_buffer b[8];
    Py_ssize_t n_bodies, n_points;
    double dt, gx, gy, pressing, share, relax, rho, until, ridge, optimality;
    long rounds;
    int refinements, slide_in_bodies;
    PyObject *prepared, *carried = Py_None;
    Py_buffer kept[2];
    int dual = 0;
    memset(b, 0, sizeof b);
    memset(kept, 0, sizeof kept);
    if (!PyArg_ParseTuple(args, "y*ny*ny*y*y*dddddlddddidpw*O|Oz*", &b[0], &n_bodies, &b[1], &n_points, &b[2], &b[3],
                          &b[4], &dt, &gx, &gy, &pressing, &share, &rounds, &relax, &rho, &until, &ridge, &refinements,
                          &optimality, &slide_in_bodies, &b[5], &prepared, &carried, &b[7]))
        return NULL;
    if (carried != Py_None && !PyArg_ParseTuple(carried, "y*y*w*p", &kept[0], &kept[1], &b[6], &dual)) {
        for (int k = 0; k < 6; k++)
            PyBuffer_Release(&b[k]);
        if (b[7].obj != NULL || b[7].buf != NULL)
            PyBuffer_Release(&b[7]);
        return NULL;
    }
    PyObject *result = NULL;
    const int64_t P = n_points, B = n_bodies;
    const Py_ssize_t vec = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (n_bodies < 0 || n_points < 0 || n_points > INT32_MAX / 16 || b[0].len != n_bodies * BODY_SIZE
        || b[1].len != n_points * POINT_SIZE || b[2].len != vec || b[3].len != vec / 2 || b[4].len != vec / 2
        || b[5].len != vec || (b[7].buf != NULL && b[7].len != vec / 2)
        || (carried != Py_None && (b[6].len != 2 * vec || kept[1].len != 4 * kept[0].len || kept[0].len % 8 != 0))
        || rounds < 0 || refinements < 0 || !(relax > 0.0 && relax < 2.0) || !(rho > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "_route.solve_and_admit: arrays of the wrong size");
        goto done;
    }
    const char *bodies = b[0].buf, *points = b[1].buf;
    if (!points_in_range(points, P, B)) {
        PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
        goto done;
    }
    struct geometry own, *g = prepared_or_own(prepared, P, B, &own, "solve_and_admit");
    if (g == NULL)
        goto done;
    const double *labels = b[2].buf, *mu = b[3].buf, *read_mu = b[4].buf;
    double *impulses = b[5].buf, *carry = carried != Py_None ? b[6].buf : NULL;
    struct step s;
    memset(&s, 0, sizeof s);
    int outcome = -1;
    long used = 0;
    int in_bodies = 0;
    double residual = 0.0, t0, t1 = 0.0, t2;
    int32_t *sp = NULL, *si = NULL;
    double *sx = NULL, *scratch = NULL;
    Py_BEGIN_ALLOW_THREADS
    t0 = monotonic_seconds();
    if (!alloc_step(&s, P) || (g == &own && geometry_build(g, bodies, points, P, B, dt, gx, gy, b[7].buf) != 0))
        goto out;
    if (carry != NULL && carry_begin(kept[0].buf, kept[1].buf, kept[0].len / 8, points, P, dual, carry) != 0)
        goto out;
    /* The labels (faces.contact_face) and the system's unknowns: the pressing points' normal
     * impulses first, then the sticking points' tangent ones (faces.face_system_sparse). */
    int64_t k_press = 0, m = 0;
    for (int64_t i = 0; i < P; i++) {
        const double ln = labels[2 * i], lt = labels[2 * i + 1];
        const int on = ln > pressing;
        const int slides = on && fabs(lt) >= share * read_mu[i] * ln;
        s.face[i] = !on ? OPEN : (slides ? (lt > 0 ? SLIDES_PLUS : SLIDES_MINUS) : STICKS);
        s.slide[i] = s.face[i] == SLIDES_PLUS ? mu[i] : (s.face[i] == SLIDES_MINUS ? -mu[i] : 0.0);
        s.keep[i] = s.face[i] == OPEN ? 0.0 : 1.0;
        k_press += s.face[i] != OPEN;
    }
    int64_t next_press = 0, next_stick = k_press;
    for (int64_t i = 0; i < P; i++) {
        s.index[2 * i] = s.face[i] != OPEN ? next_press++ : -1;
        s.index[2 * i + 1] = s.face[i] == STICKS ? next_stick++ : -1;
    }
    m = next_stick;
    memset(impulses, 0, (size_t)P * 2 * sizeof(double));
    if (m > 0) {
        for (int64_t i = 0; i < P; i++) { /* rhs = the velocity each unknown's equation holds, less the one before */
            if (s.index[2 * i] >= 0)
                s.rhs[s.index[2 * i]] = g->bias[i] - g->before[2 * i];
            if (s.index[2 * i + 1] >= 0)
                s.rhs[s.index[2 * i + 1]] = -g->before[2 * i + 1];
        }
        /* Solved in the bodies' space on factors of order 3 D (face_body_solve), where it answers;
         * elsewhere by the dual. */
        if (geometry_jacobian(g) != 0)
            goto out;
        int solved = face_body_solve(g->rows, g->jp, g->ji, g->jd, g->weight, g->order, s.index, s.slide, P, m, s.rhs,
                                     FACE_BODY_RIDGE, refinements, optimality, slide_in_bodies, s.x);
        if (solved < 0)
            goto out;
        in_bodies = solved == 0;
        if (solved != 0) {
            int64_t nnz;
            if (face_system_csr(P, B, g->pa, g->pb, g->dynamic, g->inv_mass, g->inv_inertia, g->n, g->t, g->ra,
                                g->rb, s.index, s.slide, m, &sp, &si, &sx, &nnz) != 0)
                goto out;
            solved = face_dual_solve(m, sp, si, sx, s.rhs, ridge, refinements, optimality, s.x);
        }
        if (solved != 0) {
            outcome = solved < 0 ? -1 : (solved == 1 ? ROUTE_NOT_DEFINITE : ROUTE_INCONSISTENT);
            goto out;
        }
        for (int64_t i = 0; i < P; i++) { /* a sliding point's tangent impulse is slide times its normal one */
            if (s.index[2 * i] >= 0) {
                impulses[2 * i] = s.x[s.index[2 * i]];
                impulses[2 * i + 1] = s.slide[i] * s.x[s.index[2 * i]];
            }
            if (s.index[2 * i + 1] >= 0)
                impulses[2 * i + 1] = s.x[s.index[2 * i + 1]];
        }
    }
    t1 = monotonic_seconds();
    /* Admitted as they are where every point already lies in its cone (and the open ones at 0):
     * the rounds would end in the first, after a factorization that costs more than they do. */
    project_cones(impulses, mu, s.keep, P, s.after);
    int admissible = 1;
    for (int64_t k = 0; k < 2 * P && admissible; k++)
        admissible = s.after[k] == impulses[k];
    if (!admissible) {
        if (geometry_factor(g) != 0)
            goto out;
        memcpy(s.rhs, impulses, (size_t)P * 2 * sizeof(double)); /* c, the solve's answer */
        used = admission_rounds_run(g->rows, 2 * P, g->jp, g->ji, g->jd, &g->factor, g->inverse, s.rhs, mu, s.keep,
                                    rho, rounds, 1e-5, relax, until, impulses, carry);
        if (used < 0)
            goto out;
    } else if (carry != NULL) {
        for (int64_t i = 0; i < P; i++) {
            carry[4 * i] = impulses[2 * i], carry[4 * i + 1] = impulses[2 * i + 1];
            carry[4 * i + 2] = carry[4 * i + 3] = 0.0;
        }
    }
    /* faces.face_residual: the velocity left where the labels ask for none (the normal where a
     * point presses, the tangent where it sticks) and the closing velocity where a point lets
     * go, over the norm of every point's velocity before any impulse. */
    scratch = malloc(((size_t)3 * B + 1) * sizeof(double));
    if (scratch == NULL)
        goto out;
    velocities_after_impulses(bodies, points, P, B, g->vx, g->vy, g->w, g->inv_mass, g->inv_inertia, impulses, scratch,
                              scratch + B, scratch + 2 * B, s.after);
    double left = 0.0, scale = 0.0;
    for (int64_t i = 0; i < P; i++) { /* in face_residual's order: pressing normals, sticking tangents, open */
        if (s.face[i] != OPEN)
            left += (s.after[2 * i] - g->bias[i]) * (s.after[2 * i] - g->bias[i]);
        scale += g->before[2 * i] * g->before[2 * i] + g->before[2 * i + 1] * g->before[2 * i + 1];
    }
    for (int64_t i = 0; i < P; i++)
        if (s.face[i] == STICKS)
            left += s.after[2 * i + 1] * s.after[2 * i + 1];
    for (int64_t i = 0; i < P; i++)
        if (s.face[i] == OPEN && s.after[2 * i] < g->bias[i])
            left += (s.after[2 * i] - g->bias[i]) * (s.after[2 * i] - g->bias[i]);
    residual = scale > 0.0 ? sqrt(left) / sqrt(scale) : 0.0;
    outcome = ROUTE_SERVED;
out:
    t2 = monotonic_seconds();
    free_step(&s);
    geometry_free(&own);
    free(sp), free(si), free(sx), free(scratch);
    Py_END_ALLOW_THREADS
    if (outcome < 0)
        PyErr_NoMemory();
    else
        result = Py_BuildValue("(iddd li)", outcome, residual, (outcome == ROUTE_SERVED ? t1 : t2) - t0,
                               outcome == ROUTE_SERVED ? t2 - t1 : 0.0, used, in_bodies);
done:
    for (int k = 0; k < 8; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    for (int k = 0; k < 2; k++)
        if (kept[k].obj != NULL || kept[k].buf != NULL)
            PyBuffer_Release(&kept[k]);
    return result;
}

/* A point's part in Box2D's velocity constraints: alone (one-point manifold), the first or
 * second of a two-point manifold solved as a block, or a second point Box2D drops (its two
 * points' normal rows nearly parallel: b2ContactSolver's condition number test). */
enum { ALONE = 0, BLOCK_FIRST = 1, BLOCK_SECOND = 2, DROPPED = 3 };

/* Box2D's b2ContactSolver::SolveVelocityConstraints on the server's copy of the step, one
 * constraint at a time: the tangent rows of its points first, each held inside mu times its
 * normal impulse, then its normal rows, one point's held >= 0, a two-point manifold's solved
 * as a 2 x 2 complementarity problem by total enumeration, as Box2D's block solver does. A
 * manifold's two points are consecutive in the export (deepcontact/box2d's patch) and share
 * their bodies and normal. The largest change any impulse made is returned; v (3 B,) the
 * bodies' velocities and lam (2 P,) the impulses are updated. */
static double solve_sweep(const struct geometry *g, const double *mu, const double *mass, const unsigned char *role,
                          const double *block, double *vx, double *vy, double *w, double *lam,
                          const int32_t *island, double *island_change)
{
    const int64_t P = g->P;
    double change = 0.0;
    for (int64_t i = 0; i < P; i++) {
        if (role[i] == BLOCK_SECOND || role[i] == DROPPED)
            continue;
        const int64_t a = g->pa[i], b = g->pb[i];
        const int count = role[i] == BLOCK_FIRST ? 2 : 1;
        const double ma = g->inv_mass[a], mb = g->inv_mass[b], ia = g->inv_inertia[a], ib = g->inv_inertia[b];
        for (int j = 0; j < count; j++) { /* the tangent rows */
            const int64_t q = i + j;
            const double *ra = g->ra + 2 * q, *rb = g->rb + 2 * q, t0 = g->t[2 * q], t1 = g->t[2 * q + 1];
            const double rel0 = vx[b] - w[b] * rb[1] - vx[a] + w[a] * ra[1];
            const double rel1 = vy[b] + w[b] * rb[0] - vy[a] - w[a] * ra[0];
            const double limit = mu[q] * lam[2 * q];
            double next = lam[2 * q + 1] - mass[2 * q + 1] * (rel0 * t0 + rel1 * t1);
            next = next > limit ? limit : (next < -limit ? -limit : next);
            const double step = next - lam[2 * q + 1];
            lam[2 * q + 1] = next;
            change = fabs(step) > change ? fabs(step) : change;
            if (island != NULL && fabs(step) > island_change[island[q]])
                island_change[island[q]] = fabs(step);
            const double i0 = step * t0, i1 = step * t1;
            vx[a] -= i0 * ma, vy[a] -= i1 * ma, w[a] -= (ra[0] * i1 - ra[1] * i0) * ia;
            vx[b] += i0 * mb, vy[b] += i1 * mb, w[b] += (rb[0] * i1 - rb[1] * i0) * ib;
        }
        const double n0 = g->n[2 * i], n1 = g->n[2 * i + 1];
        double vn[2];
        for (int j = 0; j < count; j++) {
            const double *ra = g->ra + 2 * (i + j), *rb = g->rb + 2 * (i + j);
            const double rel0 = vx[b] - w[b] * rb[1] - vx[a] + w[a] * ra[1];
            const double rel1 = vy[b] + w[b] * rb[0] - vy[a] - w[a] * ra[0];
            vn[j] = rel0 * n0 + rel1 * n1 - g->bias[i + j]; /* Box2D's vn - velocityBias */
        }
        double x[2];
        if (count == 1) {
            x[0] = lam[2 * i] - mass[2 * i] * vn[0];
            x[0] = x[0] > 0.0 ? x[0] : 0.0;
        } else {
            /* K, K^-1 (block + 6 i: k11, k12, k22, then the inverse's) and b = vn - K a */
            const double *k = block + 6 * i, *kinv = k + 3, a0 = lam[2 * i], a1 = lam[2 * i + 2];
            const double b0 = vn[0] - (k[0] * a0 + k[1] * a1), b1 = vn[1] - (k[1] * a0 + k[2] * a1);
            x[0] = -(kinv[0] * b0 + kinv[1] * b1), x[1] = -(kinv[1] * b0 + kinv[2] * b1);
            if (!(x[0] >= 0.0 && x[1] >= 0.0)) {
                x[0] = -b0 / k[0], x[1] = 0.0;
                if (!(x[0] >= 0.0 && k[1] * x[0] + b1 >= 0.0)) {
                    x[0] = 0.0, x[1] = -b1 / k[2];
                    if (!(x[1] >= 0.0 && k[1] * x[1] + b0 >= 0.0)) {
                        x[0] = 0.0, x[1] = 0.0;
                        if (!(b0 >= 0.0 && b1 >= 0.0))
                            x[0] = a0, x[1] = a1; /* no case holds: Box2D leaves them */
                    }
                }
            }
        }
        for (int j = 0; j < count; j++) {
            const int64_t q = i + j;
            const double *ra = g->ra + 2 * q, *rb = g->rb + 2 * q;
            const double step = x[j] - lam[2 * q];
            lam[2 * q] = x[j];
            change = fabs(step) > change ? fabs(step) : change;
            if (island != NULL && fabs(step) > island_change[island[q]])
                island_change[island[q]] = fabs(step);
            const double i0 = step * n0, i1 = step * n1;
            vx[a] -= i0 * ma, vy[a] -= i1 * ma, w[a] -= (ra[0] * i1 - ra[1] * i0) * ia;
            vx[b] += i0 * mb, vy[b] += i1 * mb, w[b] += (rb[0] * i1 - rb[1] * i0) * ib;
        }
        i += count - 1;
    }
    return change;
}

/* The largest change the solver's sweep number `sweeps` would make, from each of several starts:
 * Box2D's velocity constraints (solve_sweep) after each start is applied as its warm start (a
 * dropped point's not), on the server's copy of the step, each point's bounce held, and with the rigid
 * revolute joints of jr (NULL: none) started and swept as Box2D does: what the server knows of it. The solver stops after the first sweep that changes no impulse by more
 * than its threshold, so of two starts the one whose sweep `sweeps` changes less is the nearer
 * to its end; one projected Jacobi step (sweeps 1, kinematics.jacobi_change, every point from
 * the same velocities) is the crude version of this. g: the step's geometry (velocities with
 * gravity added); mu (P,); starts (n_starts, P, 2) N s; changes (n_starts,) out, N s. Returns
 * 0, or -1 (memory). */
/* Joints on the server's copy of the step, as Box2D's solver holds them. Each is a revolute
 * joint (a point-to-point row pair between body A and body B at the joint's anchor, and where
 * limits is given its angle limit and motor; a rigid weld is one at equal limits, as
 * b2WeldJoint solves it) or a prismatic one (a row across its axis and an angular row, and its
 * translation's limit and motor). ab (J, 2) the bodies' rows; arms (J, 4) m, rA then rB, each
 * from its body's centre of mass to the joint's anchor on it, world frame; starts (n_starts, J,
 * 2), each start's joint impulses: a revolute joint's point impulse on body B, world frame, N s
 * (Box2D's m_impulse.x, .y, the joints' warm start), a prismatic joint's across its axis (N s)
 * and its angular one (N m s); limits (J, JOINT_COLUMNS) or NULL (every joint a revolute one with
 * no limit and no motor): JOINT_KIND, the limit's state (LIMIT_*), its impulse, the motor on (1)
 * or off (0), its impulse, its largest impulse (the largest torque or force times dt) and its
 * speed, then a prismatic joint's axis (world) and its arms' cross products with the axis and
 * with the normal across it (Box2D's a1, a2, s1, s2, m); the limits' and the motors' impulses
 * the same in every start (the client keeps its own). */
enum { LIMIT_INACTIVE = 0, LIMIT_LOWER = 1, LIMIT_UPPER = 2, LIMIT_EQUAL = 3 };
enum { JOINT_REVOLUTE = 0, JOINT_PRISMATIC = 1, JOINT_COLUMNS = 13 };

struct joint_rows {
    int64_t J;
    const int64_t *ab;
    const double *arms, *starts, *limits;
};

/* b2Mat33::Solve33 of rhs for the symmetric m (its 11, 12, 13, 22, 23, 33 entries): out (3,). */
static void solve33(const double *m, const double *rhs, double *out)
{
    const double ex[3] = {m[0], m[1], m[2]}, ey[3] = {m[1], m[3], m[4]}, ez[3] = {m[2], m[4], m[5]};
    const double cyz[3] = {ey[1] * ez[2] - ey[2] * ez[1], ey[2] * ez[0] - ey[0] * ez[2], ey[0] * ez[1] - ey[1] * ez[0]};
    double det = ex[0] * cyz[0] + ex[1] * cyz[1] + ex[2] * cyz[2];
    det = det != 0.0 ? 1.0 / det : 0.0;
    const double cbz[3] = {rhs[1] * ez[2] - rhs[2] * ez[1], rhs[2] * ez[0] - rhs[0] * ez[2], rhs[0] * ez[1] - rhs[1] * ez[0]};
    const double cyb[3] = {ey[1] * rhs[2] - ey[2] * rhs[1], ey[2] * rhs[0] - ey[0] * rhs[2], ey[0] * rhs[1] - ey[1] * rhs[0]};
    out[0] = det * (rhs[0] * cyz[0] + rhs[1] * cyz[1] + rhs[2] * cyz[2]);
    out[1] = det * (ex[0] * cbz[0] + ex[1] * cbz[1] + ex[2] * cbz[2]);
    out[2] = det * (ex[0] * cyb[0] + ex[1] * cyb[1] + ex[2] * cyb[2]);
}

/* b2Mat33::Solve22 of (q0, q1) on m's upper 2 x 2 block: out (2,). */
static void solve22(const double *m, double q0, double q1, double *out)
{
    double det = m[0] * m[3] - m[1] * m[1];
    det = det != 0.0 ? 1.0 / det : 0.0;
    out[0] = det * (m[3] * q0 - m[1] * q1), out[1] = det * (m[0] * q1 - m[1] * q0);
}

/* Box2D's b2PrismaticJoint::SolveVelocityConstraints of joint j: its motor along the axis, then
 * the row across the axis and the angular row together, with the translation's limit where it is
 * active (the limit's impulse kept on its side of zero and the other two re-solved for it). m:
 * its K (k3's 6 entries). */
static void solve_prismatic(const struct geometry *g, const struct joint_rows *jr, const double *m, int64_t j,
                            double *vx, double *vy, double *w, double *lam, double *lz, double *lm)
{
    const int64_t a = jr->ab[2 * j], b = jr->ab[2 * j + 1];
    const double *lim = jr->limits + JOINT_COLUMNS * j;
    const int state = (int)lim[1];
    const double ma = g->inv_mass[a], mb = g->inv_mass[b], ia = g->inv_inertia[a], ib = g->inv_inertia[b];
    const double ax = lim[7], ay = lim[8], px = -ay, py = ax, a1 = lim[9], a2 = lim[10], s1 = lim[11], s2 = lim[12];
    if (lim[3] != 0.0 && state != LIMIT_EQUAL) {
        const double k = ma + mb + ia * a1 * a1 + ib * a2 * a2, mass = k > 0.0 ? 1.0 / k : 0.0;
        const double cdot = ax * (vx[b] - vx[a]) + ay * (vy[b] - vy[a]) + a2 * w[b] - a1 * w[a];
        const double old = lm[j], most = lim[5];
        double next = old + mass * (lim[6] - cdot);
        next = next < -most ? -most : next > most ? most : next;
        lm[j] = next;
        const double p = next - old;
        vx[a] -= ma * p * ax, vy[a] -= ma * p * ay, w[a] -= ia * p * a1;
        vx[b] += mb * p * ax, vy[b] += mb * p * ay, w[b] += ib * p * a2;
    }
    const double c0 = px * (vx[b] - vx[a]) + py * (vy[b] - vy[a]) + s2 * w[b] - s1 * w[a], c1 = w[b] - w[a];
    double d0, d1, dz = 0.0;
    if (state != LIMIT_INACTIVE) {
        const double c2 = ax * (vx[b] - vx[a]) + ay * (vy[b] - vy[a]) + a2 * w[b] - a1 * w[a];
        const double rhs[3] = {-c0, -c1, -c2};
        double df[3], f2[2];
        solve33(m, rhs, df);
        double z = lz[j] + df[2];
        if (state == LIMIT_LOWER)
            z = z > 0.0 ? z : 0.0;
        else if (state == LIMIT_UPPER)
            z = z < 0.0 ? z : 0.0;
        dz = z - lz[j];
        solve22(m, -c0 - dz * m[2], -c1 - dz * m[4], f2);
        d0 = f2[0], d1 = f2[1];
        lz[j] = z;
    } else {
        double f2[2];
        solve22(m, -c0, -c1, f2);
        d0 = f2[0], d1 = f2[1];
    }
    lam[2 * j] += d0, lam[2 * j + 1] += d1;
    const double P0 = d0 * px + dz * ax, P1 = d0 * py + dz * ay;
    vx[a] -= ma * P0, vy[a] -= ma * P1, w[a] -= ia * (d0 * s1 + d1 + dz * a1);
    vx[b] += mb * P0, vy[b] += mb * P1, w[b] += ib * (d0 * s2 + d1 + dz * a2);
}

/* Box2D's b2RevoluteJoint::SolveVelocityConstraints (or b2PrismaticJoint's), each joint in turn:
 * its motor (the relative angular velocity driven to the motor's speed within its largest
 * impulse), then, where its limit is active, the point and the angle together through K's 3 x 3
 * inverse (the angle's impulse kept on its side of zero at a lower or an upper limit, the point
 * alone re-solved where it would cross), else the relative velocity of the anchor's two points set
 * to zero through K's 2 x 2 inverse (kinv (J, 3): its 11, 12 and 22 entries; k3 (J, 6): K's 3 x 3
 * entries 11, 12, 13, 22, 23, 33). The solver's stopping rule reads the contacts' changes alone
 * (the patch), so none is returned. lam (J, 2) the joints' impulses (starts' units), lz and lm
 * (J,) their limits' and motors'. */
static void solve_joints(const struct geometry *g, const struct joint_rows *jr, const double *kinv, const double *k3,
                         double *vx, double *vy, double *w, double *lam, double *lz, double *lm)
{
    for (int64_t j = 0; j < jr->J; j++) {
        const double *lim = jr->limits == NULL ? NULL : jr->limits + JOINT_COLUMNS * j;
        if (lim != NULL && lim[0] == JOINT_PRISMATIC) {
            solve_prismatic(g, jr, k3 + 6 * j, j, vx, vy, w, lam, lz, lm);
            continue;
        }
        const int64_t a = jr->ab[2 * j], b = jr->ab[2 * j + 1];
        const double *r = jr->arms + 4 * j, *k = kinv + 3 * j;
        const double ia = g->inv_inertia[a], ib = g->inv_inertia[b];
        const int state = lim == NULL ? LIMIT_INACTIVE : (int)lim[1];
        if (lim != NULL && lim[3] != 0.0 && state != LIMIT_EQUAL && ia + ib > 0.0) {
            const double old = lm[j], most = lim[5];
            double next = old - (w[b] - w[a] - lim[6]) / (ia + ib);
            next = next < -most ? -most : next > most ? most : next;
            lm[j] = next;
            w[a] -= ia * (next - old), w[b] += ib * (next - old);
        }
        const double c0 = vx[b] - w[b] * r[3] - vx[a] + w[a] * r[1];
        const double c1 = vy[b] + w[b] * r[2] - vy[a] - w[a] * r[0];
        double p0, p1, pz = 0.0;
        if (state != LIMIT_INACTIVE && ia + ib > 0.0) {
            const double *m = k3 + 6 * j, rhs[3] = {-c0, -c1, -(w[b] - w[a])};
            double out[3];
            solve33(m, rhs, out);
            p0 = out[0], p1 = out[1], pz = out[2];
            const double total = lz[j] + pz;
            if ((state == LIMIT_LOWER && total < 0.0) || (state == LIMIT_UPPER && total > 0.0)) {
                /* the angle's impulse would cross zero: it goes to zero and the point alone is solved */
                solve22(m, -c0 + lz[j] * m[2], -c1 + lz[j] * m[4], out);
                p0 = out[0], p1 = out[1], pz = -lz[j];
            }
            lz[j] += pz;
        } else {
            p0 = -(k[0] * c0 + k[1] * c1), p1 = -(k[1] * c0 + k[2] * c1);
        }
        lam[2 * j] += p0, lam[2 * j + 1] += p1;
        vx[a] -= p0 * g->inv_mass[a], vy[a] -= p1 * g->inv_mass[a], w[a] -= (r[0] * p1 - r[1] * p0 + pz) * ia;
        vx[b] += p0 * g->inv_mass[b], vy[b] += p1 * g->inv_mass[b], w[b] += (r[2] * p1 - r[3] * p0 + pz) * ib;
    }
}

/* A step's islands, as Box2D's solver forms them (bodies joined by contacts and joints, never
 * through a static body): island (P,) each point's, 0..I-1; counts and changes (n_starts, I), the
 * sweep each island stops at and its change there (or at the last sweep), filled by sweep_changes. */
struct islands {
    int64_t I;
    const int32_t *island;
    long *counts;
    double *changes;
};

static int sweep_changes(const struct geometry *g, const double *mu, const double *starts, int n_starts, long sweeps,
                         double tolerance, const struct joint_rows *jr, double *changes, long *counts,
                         const struct islands *isl)
{
    const int64_t P = g->P, B = g->B;
    double *vx = malloc(((size_t)3 * B + 1) * sizeof(double)), *vy = vx + B, *w = vy + B;
    double *mass = malloc(((size_t)2 * P + 1) * sizeof(double)), *lam = malloc(((size_t)2 * P + 1) * sizeof(double));
    double *block = malloc(((size_t)6 * P + 1) * sizeof(double));
    unsigned char *role = calloc((size_t)P + 1, 1);
    const int64_t J = jr == NULL ? 0 : jr->J, I = isl == NULL ? 0 : isl->I;
    double *island_change = malloc(((size_t)I + 1) * sizeof(double));
    /* per joint: its point impulses (2), its limit's and motor's (2), K's 2 x 2 inverse (3), K (6) */
    double *jlam = malloc(((size_t)13 * J + 1) * sizeof(double)), *jz = jlam + 2 * J, *jm = jz + J;
    double *kinv = jm + J, *k3 = kinv + 3 * J;
    if (vx == NULL || mass == NULL || lam == NULL || block == NULL || role == NULL || jlam == NULL
        || island_change == NULL) {
        free(vx), free(mass), free(lam), free(block), free(role), free(jlam), free(island_change);
        return -1;
    }
    for (int64_t j = 0; j < J; j++) { /* each joint's K (b2RevoluteJoint::InitVelocityConstraints) and its inverse */
        const int64_t a = jr->ab[2 * j], b = jr->ab[2 * j + 1];
        const double *r = jr->arms + 4 * j, ma = g->inv_mass[a], mb = g->inv_mass[b];
        const double ia = g->inv_inertia[a], ib = g->inv_inertia[b];
        const double k11 = ma + mb + r[1] * r[1] * ia + r[3] * r[3] * ib;
        const double k12 = -r[1] * r[0] * ia - r[3] * r[2] * ib;
        const double k22 = ma + mb + r[0] * r[0] * ia + r[2] * r[2] * ib;
        double det = k11 * k22 - k12 * k12;
        det = det != 0.0 ? 1.0 / det : 0.0; /* b2Mat33::Solve22's */
        kinv[3 * j] = det * k22, kinv[3 * j + 1] = -det * k12, kinv[3 * j + 2] = det * k11;
        double *m = k3 + 6 * j;
        m[0] = k11, m[1] = k12, m[2] = -r[1] * ia - r[3] * ib, m[3] = k22, m[4] = r[0] * ia + r[2] * ib, m[5] = ia + ib;
        const double *lim = jr->limits == NULL ? NULL : jr->limits + JOINT_COLUMNS * j;
        if (lim != NULL && lim[0] == JOINT_PRISMATIC) { /* b2PrismaticJoint::InitVelocityConstraints's K */
            const double a1 = lim[9], a2 = lim[10], s1 = lim[11], s2 = lim[12];
            m[0] = ma + mb + ia * s1 * s1 + ib * s2 * s2, m[1] = ia * s1 + ib * s2, m[2] = ia * s1 * a1 + ib * s2 * a2;
            m[3] = ia + ib != 0.0 ? ia + ib : 1.0, m[4] = ia * a1 + ib * a2, m[5] = ma + mb + ia * a1 * a1 + ib * a2 * a2;
        }
    }
    for (int64_t i = 0; i < P; i++) { /* effective masses along the normal and the tangent */
        const int64_t a = g->pa[i], b = g->pb[i];
        for (int d = 0; d < 2; d++) {
            const double d0 = d ? g->t[2 * i] : g->n[2 * i], d1 = d ? g->t[2 * i + 1] : g->n[2 * i + 1];
            const double ca = g->ra[2 * i] * d1 - g->ra[2 * i + 1] * d0, cb = g->rb[2 * i] * d1 - g->rb[2 * i + 1] * d0;
            const double k = g->inv_mass[a] + g->inv_mass[b] + ca * ca * g->inv_inertia[a] + cb * cb * g->inv_inertia[b];
            mass[2 * i + d] = k > 0.0 ? 1.0 / k : 0.0;
        }
    }
    for (int64_t i = 0; i + 1 < P; i++) { /* two-point manifolds: a block, or their second point dropped */
        const int64_t a = g->pa[i], b = g->pb[i];
        if (role[i] != ALONE || g->pa[i + 1] != a || g->pb[i + 1] != b || g->n[2 * i] != g->n[2 * i + 2]
            || g->n[2 * i + 1] != g->n[2 * i + 3])
            continue;
        const double n0 = g->n[2 * i], n1 = g->n[2 * i + 1], ma = g->inv_mass[a], mb = g->inv_mass[b];
        const double ia = g->inv_inertia[a], ib = g->inv_inertia[b];
        const double r1a = g->ra[2 * i] * n1 - g->ra[2 * i + 1] * n0, r1b = g->rb[2 * i] * n1 - g->rb[2 * i + 1] * n0;
        const double r2a = g->ra[2 * i + 2] * n1 - g->ra[2 * i + 3] * n0;
        const double r2b = g->rb[2 * i + 2] * n1 - g->rb[2 * i + 3] * n0;
        const double k11 = ma + mb + ia * r1a * r1a + ib * r1b * r1b, k22 = ma + mb + ia * r2a * r2a + ib * r2b * r2b;
        const double k12 = ma + mb + ia * r1a * r2a + ib * r1b * r2b, det = k11 * k22 - k12 * k12;
        if (k11 * k11 < 1000.0 * det) { /* Box2D's k_maxConditionNumber */
            double *k = block + 6 * i;
            k[0] = k11, k[1] = k12, k[2] = k22, k[3] = k22 / det, k[4] = -k12 / det, k[5] = k11 / det;
            role[i] = BLOCK_FIRST, role[i + 1] = BLOCK_SECOND;
        } else {
            role[i + 1] = DROPPED;
        }
        i++;
    }
    for (int k = 0; k < n_starts; k++) {
        const double *start = starts + (size_t)2 * P * k;
        memcpy(lam, start, (size_t)2 * P * sizeof(double));
        memcpy(vx, g->vx, (size_t)B * sizeof(double));
        memcpy(vy, g->vy, (size_t)B * sizeof(double));
        memcpy(w, g->w, (size_t)B * sizeof(double));
        for (int64_t i = 0; i < P; i++) { /* the start, as Box2D's warm start applies it */
            if (role[i] == DROPPED)
                continue;
            const int64_t a = g->pa[i], b = g->pb[i];
            const double *ra = g->ra + 2 * i, *rb = g->rb + 2 * i;
            const double i0 = lam[2 * i] * g->n[2 * i] + lam[2 * i + 1] * g->t[2 * i];
            const double i1 = lam[2 * i] * g->n[2 * i + 1] + lam[2 * i + 1] * g->t[2 * i + 1];
            vx[a] -= i0 * g->inv_mass[a], vy[a] -= i1 * g->inv_mass[a];
            w[a] -= (ra[0] * i1 - ra[1] * i0) * g->inv_inertia[a];
            vx[b] += i0 * g->inv_mass[b], vy[b] += i1 * g->inv_mass[b];
            w[b] += (rb[0] * i1 - rb[1] * i0) * g->inv_inertia[b];
        }
        if (J > 0) { /* the joints' start, as their InitVelocityConstraints applies it */
            memcpy(jlam, jr->starts + (size_t)2 * J * k, (size_t)2 * J * sizeof(double));
            for (int64_t j = 0; j < J; j++) {
                const int64_t a = jr->ab[2 * j], b = jr->ab[2 * j + 1];
                const double *r = jr->arms + 4 * j, p0 = jlam[2 * j], p1 = jlam[2 * j + 1];
                const double *lim = jr->limits == NULL ? NULL : jr->limits + JOINT_COLUMNS * j;
                jz[j] = lim == NULL ? 0.0 : lim[2];
                jm[j] = lim == NULL ? 0.0 : lim[4];
                const double turn = jz[j] + jm[j];
                if (lim != NULL && lim[0] == JOINT_PRISMATIC) { /* across the axis, the angle, then along it */
                    const double ax = lim[7], ay = lim[8], P0 = -ay * p0 + turn * ax, P1 = ax * p0 + turn * ay;
                    vx[a] -= P0 * g->inv_mass[a], vy[a] -= P1 * g->inv_mass[a];
                    w[a] -= (p0 * lim[11] + p1 + turn * lim[9]) * g->inv_inertia[a];
                    vx[b] += P0 * g->inv_mass[b], vy[b] += P1 * g->inv_mass[b];
                    w[b] += (p0 * lim[12] + p1 + turn * lim[10]) * g->inv_inertia[b];
                    continue;
                }
                vx[a] -= p0 * g->inv_mass[a], vy[a] -= p1 * g->inv_mass[a];
                w[a] -= (r[0] * p1 - r[1] * p0 + turn) * g->inv_inertia[a];
                vx[b] += p0 * g->inv_mass[b], vy[b] += p1 * g->inv_mass[b];
                w[b] += (r[2] * p1 - r[3] * p0 + turn) * g->inv_inertia[b];
            }
        }
        /* With a tolerance, the start's run ends at the first sweep that changes nothing by more
         * than it, where the client's solver would stop: counts[k] is that sweep's number, or
         * sweeps + 1 where none of the first `sweeps` does. */
        double change = 0.0;
        counts[k] = sweeps + 1;
        long *own_counts = I > 0 ? isl->counts + (size_t)I * k : NULL;
        double *own_changes = I > 0 ? isl->changes + (size_t)I * k : NULL;
        int64_t running = I; /* islands not yet stopped */
        for (int64_t i = 0; i < I; i++)
            own_counts[i] = sweeps + 1;
        for (long sweep = 0; sweep < sweeps; sweep++) {
            if (J > 0) /* Box2D's island solves its joints first in each sweep, then its contacts */
                solve_joints(g, jr, kinv, k3, vx, vy, w, jlam, jz, jm);
            for (int64_t i = 0; i < I; i++)
                island_change[i] = 0.0;
            change = solve_sweep(g, mu, mass, role, block, vx, vy, w, lam, I > 0 ? isl->island : NULL, island_change);
            /* Box2D stops each island at its own first sweep under the tolerance: an island's
             * count and change are that sweep's, or the last sweep's where it does not stop. */
            for (int64_t i = 0; i < I; i++) {
                if (own_counts[i] <= sweeps)
                    continue;
                own_changes[i] = island_change[i];
                if (tolerance > 0.0 && island_change[i] <= tolerance)
                    own_counts[i] = sweep + 1, running--;
            }
            if (tolerance > 0.0 && (I > 0 ? running == 0 : change <= tolerance)) {
                counts[k] = sweep + 1;
                break;
            }
        }
        changes[k] = change;
        for (int64_t i = 0; i < I; i++) /* where every island stops, the tie is read by theirs */
            changes[k] = i == 0 || own_changes[i] > changes[k] ? own_changes[i] : changes[k];
    }
    free(vx), free(mass), free(lam), free(block), free(role), free(jlam), free(island_change);
    return 0;
}

static int64_t island_root(int64_t *parent, int64_t k)
{
    while (parent[k] != k)
        k = parent[k] = parent[parent[k]];
    return k;
}

/* The step's islands as Box2D's solver forms them (b2World::Solve's search): bodies joined by the
 * points and the joints of jr (NULL: none) where neither body is static (a kinematic body joins
 * them, a static one joins none). point_island (P,) each point's island, numbered 0.. in the order
 * of their first points; joint_island (J,) each joint's, or -1 where no point is on its island.
 * Returns the number of islands, or -1 (memory). */
static Py_ssize_t find_islands(const char *bodies, Py_ssize_t B, const char *points, Py_ssize_t P,
                               const struct joint_rows *jr, int32_t *point_island, int32_t *joint_island)
{
    int64_t *parent = malloc(((size_t)B + 1) * sizeof(int64_t)), *number = malloc(((size_t)B + 1) * sizeof(int64_t));
    unsigned char *moves = malloc((size_t)B + 1);
    if (parent == NULL || number == NULL || moves == NULL) {
        free(parent), free(number), free(moves);
        return -1;
    }
    for (Py_ssize_t k = 0; k < B; k++) {
        parent[k] = k, number[k] = -1;
        moves[k] = i32_at(bodies + k * BODY_SIZE, BODY_TYPE) != BODY_STATIC;
    }
    const Py_ssize_t J = jr == NULL ? 0 : jr->J;
    for (Py_ssize_t i = 0; i < P + J; i++) {
        const int64_t a = i < P ? i32_at(points + i * POINT_SIZE, POINT_BODY_A) : jr->ab[2 * (i - P)];
        const int64_t c = i < P ? i32_at(points + i * POINT_SIZE, POINT_BODY_B) : jr->ab[2 * (i - P) + 1];
        if (moves[a] && moves[c]) {
            const int64_t ra = island_root(parent, a), rc = island_root(parent, c);
            if (ra != rc)
                parent[ra] = rc;
        }
    }
    Py_ssize_t n = 0;
    for (Py_ssize_t i = 0; i < P + J; i++) {
        const int64_t a = i < P ? i32_at(points + i * POINT_SIZE, POINT_BODY_A) : jr->ab[2 * (i - P)];
        const int64_t c = i < P ? i32_at(points + i * POINT_SIZE, POINT_BODY_B) : jr->ab[2 * (i - P) + 1];
        const int64_t root = island_root(parent, moves[a] ? a : c);
        if (i < P) {
            if (number[root] < 0)
                number[root] = n++;
            point_island[i] = (int32_t)number[root];
        } else {
            joint_island[i - P] = (int32_t)number[root];
        }
    }
    free(parent), free(number), free(moves);
    return n;
}

/* compare_starts(bodies, n_bodies, points, n_points, mu, dt, gx, gy, starts, sweeps, geometry, tolerance
 *                [, joint_bodies, joint_arms, joint_starts, joint_limits, by_island, restitution])
 *     -> ([change, ...], [sweeps run, ...][, island counts, island changes, point islands, joint islands, I])
 *
 * sweep_changes of each start: starts float64 (n_starts, P, 2) N s (n_starts from its size);
 * mu float64 (P,); geometry: prepare's for these bodies, points and physics, or None;
 * tolerance (N s): 0 runs every start `sweeps` sweeps and each change is its last sweep's;
 * above 0 a start stops at its first sweep that changes nothing by more, and its count is that
 * sweep's number (sweeps + 1 where it does not stop). With the joints (struct joint_rows):
 * joint_bodies int64 (J, 2), joint_arms float64 (J, 4) m, joint_starts float64 (n_starts, J, 2)
 * N s, each start's joint impulses beside its contact impulses; joint_limits float64 (J, 13), each
 * joint's kind, limit and motor (struct joint_rows), or absent: every one a revolute joint with
 * neither (the joint arguments may be None). by_island (true): the step's islands as Box2D forms
 * them (find_islands), each stopped at its own first sweep under the tolerance, a start's count the
 * sweep where its last island stops and its change the largest of the islands' changes there;
 * the reply then adds (n_starts, I) int64 and float64 bytes, each island's count and change, the
 * points' and the joints' islands as int32 bytes, and I. restitution: None, or float64 (P,) each
 * point's, for the geometry built here (geometry_build's bounce; prepare's holds it already). */
static PyObject *compare_starts(PyObject *self, PyObject *args)
{
    Py_buffer b[8];
    Py_ssize_t n_bodies, n_points;
    double dt, gx, gy, tolerance;
    long sweeps;
    PyObject *prepared;
    int by_island = 0;
    memset(b, 0, sizeof b);
    Py_buffer rest;
    memset(&rest, 0, sizeof rest);
    if (!PyArg_ParseTuple(args, "y*ny*ny*dddy*lOd|z*z*z*z*pz*", &b[0], &n_bodies, &b[1], &n_points, &b[2], &dt, &gx,
                          &gy, &b[3], &sweeps, &prepared, &tolerance, &b[4], &b[5], &b[6], &b[7], &by_island, &rest))
        return NULL;
    PyObject *result = NULL;
    long *island_counts = NULL;
    double *island_changes = NULL;
    int32_t *point_island = NULL, *joint_island = NULL;
    Py_ssize_t n_islands = 0;
    const Py_ssize_t per_start = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (n_bodies < 0 || n_points <= 0 || n_points > INT32_MAX / 16 || b[0].len != n_bodies * BODY_SIZE
        || b[1].len != n_points * POINT_SIZE || b[2].len != per_start / 2 || b[3].len % per_start != 0
        || b[3].len / per_start > 64 || sweeps < 1 || !(tolerance >= 0.0)
        || (rest.buf != NULL && rest.len != per_start / 2)) {
        PyErr_SetString(PyExc_ValueError, "_route.compare_starts: arrays of the wrong size");
        goto done;
    }
    if (!points_in_range(b[1].buf, n_points, n_bodies)) {
        PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
        goto done;
    }
    const int n_starts = (int)(b[3].len / per_start);
    struct islands islands = {0, NULL, NULL, NULL}, *isl = NULL;
    struct joint_rows joints = {0, NULL, NULL, NULL, NULL}, *jr = NULL;
    if (b[4].obj != NULL) {
        const Py_ssize_t J = b[4].len / (Py_ssize_t)(2 * sizeof(int64_t));
        if (b[5].obj == NULL || b[6].obj == NULL || b[4].len != J * 2 * (Py_ssize_t)sizeof(int64_t)
            || b[5].len != J * 4 * (Py_ssize_t)sizeof(double) || b[6].len != n_starts * J * 2 * (Py_ssize_t)sizeof(double)
            || (b[7].obj != NULL && b[7].len != J * JOINT_COLUMNS * (Py_ssize_t)sizeof(double))) {
            PyErr_SetString(PyExc_ValueError, "_route.compare_starts: joint arrays of the wrong size");
            goto done;
        }
        const int64_t *ab = b[4].buf;
        for (Py_ssize_t j = 0; j < 2 * J; j++)
            if (ab[j] < 0 || ab[j] >= n_bodies) {
                PyErr_Format(PyExc_ValueError, "joints name bodies outside 0..%zd", n_bodies - 1);
                goto done;
            }
        const double *limits = b[7].obj != NULL ? b[7].buf : NULL;
        for (Py_ssize_t j = 0; limits != NULL && j < J; j++) {
            const double *lim = limits + JOINT_COLUMNS * j;
            if (!(lim[0] == JOINT_REVOLUTE || lim[0] == JOINT_PRISMATIC)
                || !(lim[1] == LIMIT_INACTIVE || lim[1] == LIMIT_LOWER || lim[1] == LIMIT_UPPER || lim[1] == LIMIT_EQUAL)) {
                PyErr_SetString(PyExc_ValueError, "joint limits: a kind other than 0 or 1, or a state other than 0-3");
                goto done;
            }
        }
        joints = (struct joint_rows){J, ab, b[5].buf, b[6].buf, limits};
        jr = &joints;
    }
    if (by_island) {
        point_island = malloc(((size_t)n_points + 1) * sizeof(int32_t));
        joint_island = malloc(((size_t)joints.J + 1) * sizeof(int32_t));
        n_islands = point_island == NULL || joint_island == NULL ? -1
                    : find_islands(b[0].buf, n_bodies, b[1].buf, n_points, jr, point_island, joint_island);
        if (n_islands >= 0) {
            island_counts = malloc(((size_t)n_starts * n_islands + 1) * sizeof(long));
            island_changes = malloc(((size_t)n_starts * n_islands + 1) * sizeof(double));
        }
        if (n_islands < 0 || island_counts == NULL || island_changes == NULL) {
            PyErr_NoMemory();
            goto done;
        }
        islands = (struct islands){n_islands, point_island, island_counts, island_changes};
        isl = &islands;
    }
    struct geometry own, *g = prepared_or_own(prepared, n_points, n_bodies, &own, "compare_starts");
    if (g == NULL)
        goto done;
    double changes[64];
    long counts[64];
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = g == &own ? geometry_build(g, b[0].buf, b[1].buf, n_points, n_bodies, dt, gx, gy, rest.buf) : 0;
    if (status == 0)
        status = sweep_changes(g, b[2].buf, b[3].buf, n_starts, sweeps, tolerance, jr, changes, counts, isl);
    geometry_free(&own);
    Py_END_ALLOW_THREADS
    if (status != 0) {
        PyErr_NoMemory();
        goto done;
    }
    PyObject *last = PyList_New(n_starts), *run = PyList_New(n_starts);
    for (int k = 0; last != NULL && run != NULL && k < n_starts; k++) {
        PyObject *x = PyFloat_FromDouble(changes[k]), *c = PyLong_FromLong(counts[k]);
        if (x == NULL || c == NULL) {
            Py_XDECREF(x), Py_XDECREF(c);
            Py_CLEAR(last);
            break;
        }
        PyList_SET_ITEM(last, k, x);
        PyList_SET_ITEM(run, k, c);
    }
    if (last != NULL && run != NULL && isl != NULL) { /* int64 and float64 bytes, (n_starts, I) */
        int64_t *c64 = malloc((size_t)n_starts * n_islands * sizeof(int64_t));
        if (c64 == NULL) {
            PyErr_NoMemory();
        } else {
            for (Py_ssize_t i = 0; i < n_starts * n_islands; i++)
                c64[i] = island_counts[i];
            PyObject *ic = PyBytes_FromStringAndSize((const char *)c64, n_starts * n_islands * (Py_ssize_t)sizeof(int64_t));
            PyObject *ix = PyBytes_FromStringAndSize((const char *)island_changes,
                                                     n_starts * n_islands * (Py_ssize_t)sizeof(double));
            PyObject *pi = PyBytes_FromStringAndSize((const char *)point_island, n_points * (Py_ssize_t)sizeof(int32_t));
            PyObject *ji = PyBytes_FromStringAndSize((const char *)joint_island, joints.J * (Py_ssize_t)sizeof(int32_t));
            PyObject *ni = PyLong_FromSsize_t(n_islands);
            if (ic != NULL && ix != NULL && pi != NULL && ji != NULL && ni != NULL)
                result = PyTuple_Pack(7, last, run, ic, ix, pi, ji, ni);
            Py_XDECREF(ic), Py_XDECREF(ix), Py_XDECREF(pi), Py_XDECREF(ji), Py_XDECREF(ni);
            free(c64);
        }
    } else if (last != NULL && run != NULL)
        result = PyTuple_Pack(2, last, run);
    Py_XDECREF(last), Py_XDECREF(run);
done:
    free(island_counts), free(island_changes), free(point_island), free(joint_island);
    for (int k = 0; k < 8; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    if (rest.obj != NULL || rest.buf != NULL)
        PyBuffer_Release(&rest);
    return result;
}

static PyMethodDef methods[] = {
    {"solve_and_admit", solve_and_admit, METH_VARARGS,
     "The face route after its classifier: labels, solve, admission, residual (see the C source)."},
    {"prepare", prepare, METH_VARARGS, "A step's geometry for solve_and_admit, built ahead (see the C source)."},
    {"compare_starts", compare_starts, METH_VARARGS,
     "The largest change a sweep of the solver makes from each of several starts, and the sweeps each takes to a tolerance (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._route", "The face route after its classifier, compiled (see the C source).",
    -1, methods,
};

PyMODINIT_FUNC PyInit__route(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL)
        return NULL;
    if (PyModule_AddIntConstant(mod, "SERVED", ROUTE_SERVED) || PyModule_AddIntConstant(mod, "NOT_DEFINITE", ROUTE_NOT_DEFINITE)
        || PyModule_AddIntConstant(mod, "INCONSISTENT", ROUTE_INCONSISTENT)) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
