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

/* What one step needs kept, all malloc'd at once. */
struct step {
    int64_t *pa, *pb, *index;
    int32_t *row;
    unsigned char *dynamic, *face;
    double *inv_mass, *inv_inertia, *n, *t, *ra, *rb, *vx, *vy, *w, *before, *slide, *rhs, *x, *keep, *after;
};

static void free_step(struct step *s)
{
    free(s->pa), free(s->pb), free(s->index), free(s->row), free(s->dynamic), free(s->face);
    free(s->inv_mass), free(s->inv_inertia), free(s->n), free(s->t), free(s->ra), free(s->rb);
    free(s->vx), free(s->vy), free(s->w), free(s->before), free(s->slide), free(s->rhs), free(s->x), free(s->keep);
    free(s->after);
}

static int alloc_step(struct step *s, int64_t P, int64_t B)
{
    memset(s, 0, sizeof *s);
    const size_t p = (size_t)P + 1, b = (size_t)B + 1;
    s->pa = malloc(p * sizeof(int64_t));
    s->pb = malloc(p * sizeof(int64_t));
    s->index = malloc(2 * p * sizeof(int64_t));
    s->row = malloc(b * sizeof(int32_t));
    s->dynamic = malloc(b);
    s->face = malloc(p);
    s->inv_mass = malloc(b * sizeof(double));
    s->inv_inertia = malloc(b * sizeof(double));
    s->vx = malloc(b * sizeof(double));
    s->vy = malloc(b * sizeof(double));
    s->w = malloc(b * sizeof(double));
    double **per_point[] = {&s->n, &s->t, &s->ra, &s->rb, &s->before, &s->rhs, &s->x, &s->after};
    for (size_t k = 0; k < sizeof per_point / sizeof per_point[0]; k++)
        *per_point[k] = malloc(2 * p * sizeof(double));
    s->slide = malloc(p * sizeof(double));
    s->keep = malloc(p * sizeof(double));
    return s->pa && s->pb && s->index && s->row && s->dynamic && s->face && s->inv_mass && s->inv_inertia && s->vx
           && s->vy && s->w && s->n && s->t && s->ra && s->rb && s->before && s->rhs && s->x && s->after && s->slide
           && s->keep;
}

/* solve_and_admit(bodies, n_bodies, points, n_points, labels, mu, read_mu, dt, gx, gy, pressing,
 *                 share, rounds, until, ridge, refinements, optimality, impulses)
 *     -> (outcome, residual, solve_seconds, admit_seconds, admission_rounds)
 *
 * bodies, points: BODY_DTYPE and CONTACT_DTYPE records; labels float64 (P, 2), the classifier's
 * answer (N s); mu float64 (P,) each point's friction; read_mu float64 (P,) the friction the
 * sliding labels are read at (mu, or the card's label_friction everywhere); dt (s), gx, gy
 * (m/s^2); pressing (N s) and share: how the labels are read (faces.contact_face); rounds,
 * until (CLOCK_MONOTONIC s, 0: none): the admission's; ridge, refinements, optimality: the
 * dual solve's (faces.DUAL_*); impulses float64 (P, 2) out. outcome: ROUTE_SERVED (impulses
 * written, residual faces.face_residual of them), ROUTE_NOT_DEFINITE (the sparse factor met a
 * pivot below zero: the caller solves densely) or ROUTE_INCONSISTENT (the labels' system is
 * far from consistent: the caller solves it by least squares). */
static PyObject *solve_and_admit(PyObject *self, PyObject *args)
{
    Py_buffer b[6];
    Py_ssize_t n_bodies, n_points;
    double dt, gx, gy, pressing, share, until, ridge, optimality;
    long rounds;
    int refinements;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*ny*ny*y*y*dddddlddidw*", &b[0], &n_bodies, &b[1], &n_points, &b[2], &b[3], &b[4],
                          &dt, &gx, &gy, &pressing, &share, &rounds, &until, &ridge, &refinements, &optimality,
                          &b[5]))
        return NULL;
    PyObject *result = NULL;
    const int64_t P = n_points, B = n_bodies;
    const Py_ssize_t vec = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (n_bodies < 0 || n_points < 0 || n_points > INT32_MAX / 8 || b[0].len != n_bodies * BODY_SIZE
        || b[1].len != n_points * POINT_SIZE || b[2].len != vec || b[3].len != vec / 2 || b[4].len != vec / 2
        || b[5].len != vec || rounds < 0 || refinements < 0) {
        PyErr_SetString(PyExc_ValueError, "_route.solve_and_admit: arrays of the wrong size");
        goto done;
    }
    const char *bodies = b[0].buf, *points = b[1].buf;
    if (!points_in_range(points, P, B)) {
        PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
        goto done;
    }
    const double *labels = b[2].buf, *mu = b[3].buf, *read_mu = b[4].buf;
    double *impulses = b[5].buf;
    struct step s;
    int outcome = -1;
    long used = 0;
    double residual = 0.0, t0, t1, t2;
    int32_t *sp = NULL, *si = NULL, *jp = NULL, *ji = NULL, *order = NULL, *inverse = NULL;
    double *sx = NULL, *jd = NULL, *scratch = NULL;
    spchol_factor_t factor = {0, NULL, NULL, NULL};
    Py_BEGIN_ALLOW_THREADS
    t0 = monotonic_seconds();
    if (!alloc_step(&s, P, B))
        goto out;
    /* The frame (kinematics.contact_frame) and the velocities before any impulse, gravity added. */
    int32_t n_dyn = 0;
    for (int64_t k = 0; k < B; k++) {
        const char *body = bodies + k * BODY_SIZE;
        const int dynamic = i32_at(body, BODY_TYPE) == BODY_DYNAMIC;
        const double on = dynamic ? 1.0 : 0.0;
        s.dynamic[k] = (unsigned char)dynamic;
        s.row[k] = dynamic ? n_dyn++ : -1;
        s.vx[k] = f32_at(body, BODY_VELOCITY) * on;
        s.vy[k] = f32_at(body, BODY_VELOCITY + 4) * on;
        s.w[k] = f32_at(body, BODY_ANGULAR_VELOCITY) * on;
        if (dt != 0.0) {
            s.vx[k] += (dt * gx) * on;
            s.vy[k] += (dt * gy) * on;
        }
        s.inv_mass[k] = inverse_of(f32_at(body, BODY_MASS), dynamic);
        s.inv_inertia[k] = inverse_of(f32_at(body, BODY_INERTIA), dynamic);
    }
    struct frame f;
    for (int64_t i = 0; i < P; i++) {
        frame_of(points + i * POINT_SIZE, bodies, &f);
        s.pa[i] = f.a;
        s.pb[i] = f.b;
        s.n[2 * i] = f.n0, s.n[2 * i + 1] = f.n1, s.t[2 * i] = f.t0, s.t[2 * i + 1] = f.t1;
        s.ra[2 * i] = f.ra0, s.ra[2 * i + 1] = f.ra1, s.rb[2 * i] = f.rb0, s.rb[2 * i + 1] = f.rb1;
        relative_velocity(&f, s.vx, s.vy, s.w, s.before + 2 * i);
    }
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
        int64_t nnz;
        if (face_system_csr(P, B, s.pa, s.pb, s.dynamic, s.inv_mass, s.inv_inertia, s.n, s.t, s.ra, s.rb, s.index,
                            s.slide, m, &sp, &si, &sx, &nnz) != 0)
            goto out;
        for (int64_t i = 0; i < P; i++) { /* rhs = -velocity at each unknown's equation */
            if (s.index[2 * i] >= 0)
                s.rhs[s.index[2 * i]] = -s.before[2 * i];
            if (s.index[2 * i + 1] >= 0)
                s.rhs[s.index[2 * i + 1]] = -s.before[2 * i + 1];
        }
        int solved = face_dual_solve(m, sp, si, sx, s.rhs, ridge, refinements, optimality, s.x);
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
        const int32_t rows = 3 * n_dyn;
        jp = malloc(((size_t)rows + 1) * sizeof(int32_t));
        ji = malloc(((size_t)12 * P + 1) * sizeof(int32_t));
        jd = malloc(((size_t)12 * P + 1) * sizeof(double));
        order = malloc(((size_t)rows + 1) * sizeof(int32_t));
        inverse = malloc(((size_t)rows + 1) * sizeof(int32_t));
        if (jp == NULL || ji == NULL || jd == NULL || order == NULL || inverse == NULL)
            goto out;
        jacobian_transpose_csr(P, s.pa, s.pb, s.row, s.n, s.t, s.ra, s.rb, rows, jp, ji, jd);
        if (body_order_min_degree(P, s.pa, s.pb, s.row, n_dyn, order) != 0)
            goto out;
        for (int32_t q = n_dyn - 1; q >= 0; q--) /* each body's three rows, in its order */
            for (int d = 2; d >= 0; d--)
                order[3 * q + d] = 3 * order[q] + d;
        int factored = gram_factor(rows, (int32_t)(2 * P), jp, ji, jd, order, 1e-9, inverse, &factor);
        if (factored != 0)
            goto out;
        memcpy(s.rhs, impulses, (size_t)P * 2 * sizeof(double)); /* c, the solve's answer */
        used = admission_rounds_run(rows, 2 * P, jp, ji, jd, &factor, inverse, s.rhs, mu, s.keep, 100.0, rounds, 1e-5,
                                    until, impulses);
        if (used < 0)
            goto out;
    }
    /* faces.face_residual: the velocity left where the labels ask for none (the normal where a
     * point presses, the tangent where it sticks) and the closing velocity where a point lets
     * go, over the norm of every point's velocity before any impulse. */
    scratch = malloc(((size_t)3 * B + 1) * sizeof(double));
    if (scratch == NULL)
        goto out;
    velocities_after_impulses(bodies, points, P, B, s.vx, s.vy, s.w, s.inv_mass, s.inv_inertia, impulses, scratch,
                              scratch + B, scratch + 2 * B, s.after);
    double left = 0.0, scale = 0.0;
    for (int64_t i = 0; i < P; i++) { /* in face_residual's order: pressing normals, sticking tangents, open */
        if (s.face[i] != OPEN)
            left += s.after[2 * i] * s.after[2 * i];
        scale += s.before[2 * i] * s.before[2 * i] + s.before[2 * i + 1] * s.before[2 * i + 1];
    }
    for (int64_t i = 0; i < P; i++)
        if (s.face[i] == STICKS)
            left += s.after[2 * i + 1] * s.after[2 * i + 1];
    for (int64_t i = 0; i < P; i++)
        if (s.face[i] == OPEN && s.after[2 * i] < 0.0)
            left += s.after[2 * i] * s.after[2 * i];
    residual = scale > 0.0 ? sqrt(left) / sqrt(scale) : 0.0;
    outcome = ROUTE_SERVED;
out:
    t2 = monotonic_seconds();
    free_step(&s);
    spchol_free(&factor);
    free(sp), free(si), free(sx), free(jp), free(ji), free(jd), free(order), free(inverse), free(scratch);
    Py_END_ALLOW_THREADS
    if (outcome < 0)
        PyErr_NoMemory();
    else
        result = Py_BuildValue("(iddd l)", outcome, residual, (outcome == ROUTE_SERVED ? t1 : t2) - t0,
                               outcome == ROUTE_SERVED ? t2 - t1 : 0.0, used);
done:
    for (int k = 0; k < 6; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"solve_and_admit", solve_and_admit, METH_VARARGS,
     "The face route after its classifier: labels, solve, admission, residual (see the C source)."},
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
