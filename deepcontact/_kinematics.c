/* Compiled core of deepcontact.kinematics: the contact points' relative velocities
 * and effective masses, read straight from the engine's records, and the contact
 * Jacobian's transpose as a sparse matrix (the admission's).
 *
 * deepcontact/kinematics.py owns the conventions and documents them; this is its
 * arithmetic. In NumPy the same quantities took about a hundred calls per step
 * (each a few microseconds on a few hundred points), the larger part of the
 * server's feature stage; here one call makes one pass over the bodies and two
 * over the points.
 *
 * Bit for bit what the NumPy implementation gave (tests/deepcontact/
 * test_kinematics.py keeps it as the reference): float32 fields are widened to
 * float64 before any arithmetic, every sum is taken in NumPy's order (the
 * warm start's impulses reach the bodies as np.bincount added them: every
 * point's share on body B first, in point order, then every share on body A),
 * and -ffp-contract=off (setup.py) keeps a*b+c from being fused. The models
 * were trained on these numbers, so serving them must not move a bit.
 *
 * Layout: `bodies` and `points` are C-contiguous arrays of BODY_DTYPE and
 * CONTACT_DTYPE (deepcontact/records.py); the field offsets below are checked
 * against those dtypes when kinematics.py imports this module. Outputs are
 * (P, 2) float64, written in place. Body indices are checked before use.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "contact_jacobian.h"
#include "contact_records.h"

enum { WARM_NONE = 0, WARM_BUILTIN = 1, WARM_GIVEN = 2 };

/* Per-body scratch, grown as needed, never shrunk: 8 float64 a body. */
static double *scratch = NULL;
static Py_ssize_t scratch_bodies = 0;

static double *body_scratch(Py_ssize_t n_bodies)
{
    if (n_bodies > scratch_bodies) {
        double *p = PyMem_Realloc(scratch, (size_t)n_bodies * 8 * sizeof(double));
        if (p == NULL) {
            PyErr_NoMemory();
            return NULL;
        }
        scratch = p;
        scratch_bodies = n_bodies;
    }
    return scratch;
}

/* point_kinematics(bodies, n_bodies, points, n_points, warm_mode, warm, dt, gx, gy,
 *                  velocities, warmed, masses) -> None
 *
 * bodies: n_bodies BODY_DTYPE records; points: n_points CONTACT_DTYPE records.
 * warm_mode: WARM_NONE, WARM_BUILTIN (the points' builtin field) or WARM_GIVEN
 *   (warm, (P, 2) float64 N s; otherwise pass an empty buffer).
 * dt (s), gx, gy (m/s^2): this step's gravity, added to dynamic bodies first when dt != 0.
 * velocities: (P, 2) float64 out, the relative velocity before any impulse, or an
 *   empty buffer for none; warmed: the same after the warm start (needs warm_mode
 *   != WARM_NONE), or empty; masses: (P, 2) float64 out, the effective masses, or empty.
 */
static PyObject *point_kinematics(PyObject *self, PyObject *args)
{
    Py_buffer bodies_buf, points_buf, warm_buf, vel_buf, warmed_buf, mass_buf;
    Py_ssize_t n_bodies, n_points;
    int warm_mode;
    double dt, gx, gy;
    if (!PyArg_ParseTuple(args, "y*ny*niy*dddw*w*w*", &bodies_buf, &n_bodies, &points_buf, &n_points, &warm_mode,
                          &warm_buf, &dt, &gx, &gy, &vel_buf, &warmed_buf, &mass_buf))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t out_len = n_points * 2 * (Py_ssize_t)sizeof(double);
    if (bodies_buf.len != n_bodies * BODY_SIZE || points_buf.len != n_points * POINT_SIZE) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: bodies or points are not whole records");
        goto done;
    }
    if ((vel_buf.len && vel_buf.len != out_len) || (warmed_buf.len && warmed_buf.len != out_len) ||
        (mass_buf.len && mass_buf.len != out_len) || (warm_mode == WARM_GIVEN && warm_buf.len != out_len)) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: an impulse or output buffer is not (P, 2) float64");
        goto done;
    }
    if (warmed_buf.len && warm_mode == WARM_NONE) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: warmed velocities need a warm start");
        goto done;
    }
    const char *bodies = bodies_buf.buf, *points = points_buf.buf;
    if (!points_in_range(points, n_points, n_bodies)) {
        PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
        goto done;
    }
    double *s = body_scratch(n_bodies > 0 ? n_bodies : 1);
    if (s == NULL)
        goto done;
    /* Per body: velocity after gravity (vx, vy, w), inverse mass and inertia, and the
     * warm start's impulse summed on it (dvx, dvy, dw; then its velocity after). */
    double *vx = s, *vy = s + n_bodies, *w = s + 2 * n_bodies, *inv_m = s + 3 * n_bodies,
           *inv_i = s + 4 * n_bodies;
    for (Py_ssize_t k = 0; k < n_bodies; k++) {
        const char *body = bodies + k * BODY_SIZE;
        const int dynamic = i32_at(body, BODY_TYPE) == BODY_DYNAMIC;
        const double on = dynamic ? 1.0 : 0.0;
        vx[k] = f32_at(body, BODY_VELOCITY) * on;
        vy[k] = f32_at(body, BODY_VELOCITY + 4) * on;
        w[k] = f32_at(body, BODY_ANGULAR_VELOCITY) * on;
        if (dt != 0.0) {
            vx[k] += (dt * gx) * on;
            vy[k] += (dt * gy) * on;
        }
        inv_m[k] = inverse_of(f32_at(body, BODY_MASS), dynamic);
        inv_i[k] = inverse_of(f32_at(body, BODY_INERTIA), dynamic);
    }
    struct frame f;
    double *vel = vel_buf.len ? vel_buf.buf : NULL, *warmed = warmed_buf.len ? warmed_buf.buf : NULL,
           *mass = mass_buf.len ? mass_buf.buf : NULL;
    for (Py_ssize_t i = 0; i < n_points; i++) {
        if (!vel && !mass)
            break;
        frame_of(points + i * POINT_SIZE, bodies, &f);
        if (vel)
            relative_velocity(&f, vx, vy, w, vel + 2 * i);
        if (mass) {
            /* 1 / (1/m_A + 1/m_B + (r_A x d)^2 / I_A + (r_B x d)^2 / I_B), d = n then t. */
            const double d[2][2] = {{f.n0, f.n1}, {f.t0, f.t1}};
            for (int k = 0; k < 2; k++) {
                const double ca = f.ra0 * d[k][1] - f.ra1 * d[k][0];
                const double cb = f.rb0 * d[k][1] - f.rb1 * d[k][0];
                const double inv = inv_m[f.a] + inv_m[f.b] + inv_i[f.a] * (ca * ca) + inv_i[f.b] * (cb * cb);
                mass[2 * i + k] = inverse_of(inv, 1);
            }
        }
    }
    if (warmed) /* the warm start's impulse summed on each body (N s, N m s), then the velocities after it */
        velocities_after_impulses(bodies, points, n_points, n_bodies, vx, vy, w, inv_m, inv_i,
                                  warm_mode == WARM_GIVEN ? warm_buf.buf : NULL, s + 5 * n_bodies, s + 6 * n_bodies,
                                  s + 7 * n_bodies, warmed);
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&bodies_buf);
    PyBuffer_Release(&points_buf);
    PyBuffer_Release(&warm_buf);
    PyBuffer_Release(&vel_buf);
    PyBuffer_Release(&warmed_buf);
    PyBuffer_Release(&mass_buf);
    return result;
}

/* jacobian_transpose(a, b, row, n, t, ra, rb, rows, indptr, indices, data) -> entries: J^T as
 * CSR (contact_jacobian.h says what it holds), checked and written in place.
 *
 * Arguments: a, b int64 (P,) body indices; row int32 (B,) each body's dynamic row or -1;
 * n, t, ra, rb float64 (P, 2); rows (3 D); out: indptr int32 (rows + 1,), indices int32 and
 * data float64 of at least 12 P each. Returns the number of entries. */
static PyObject *jacobian_transpose(PyObject *self, PyObject *args)
{
    Py_buffer b[10];
    Py_ssize_t rows;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*nw*w*w*", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &rows,
                          &b[7], &b[8], &b[9]))
        return NULL;
    const int n_bufs = 10;
    PyObject *result = NULL;
    const Py_ssize_t n_points = b[0].len / (Py_ssize_t)sizeof(int64_t), n_bodies = b[2].len / (Py_ssize_t)sizeof(int32_t);
    const Py_ssize_t vec = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (b[0].len != n_points * (Py_ssize_t)sizeof(int64_t) || b[1].len != b[0].len || rows < 0 || rows % 3
        || b[3].len != vec || b[4].len != vec || b[5].len != vec || b[6].len != vec
        || b[7].len != (rows + 1) * (Py_ssize_t)sizeof(int32_t) || b[8].len < 12 * n_points * (Py_ssize_t)sizeof(int32_t)
        || b[9].len < 12 * n_points * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "_admission.jacobian_transpose: arrays of the wrong size");
        goto done;
    }
    const int64_t *pa = b[0].buf, *pb = b[1].buf;
    const int32_t *row = b[2].buf;
    const double *n = b[3].buf, *t = b[4].buf, *ra = b[5].buf, *rb = b[6].buf;
    int32_t *indptr = b[7].buf, *indices = b[8].buf;
    double *data = b[9].buf;
    for (Py_ssize_t i = 0; i < n_points; i++)
        if (pa[i] < 0 || pa[i] >= n_bodies || pb[i] < 0 || pb[i] >= n_bodies
            || row[pa[i]] >= rows / 3 || row[pb[i]] >= rows / 3) {
            PyErr_SetString(PyExc_ValueError, "_admission.jacobian_transpose: a point names a body out of range");
            goto done;
        }
    Py_ssize_t nnz = jacobian_transpose_csr(n_points, pa, pb, row, n, t, ra, rb, rows, indptr, indices, data);
    result = PyLong_FromSsize_t(nnz);
done:
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"jacobian_transpose", jacobian_transpose, METH_VARARGS,
     "J^T of a step's contact points as CSR (see the C source)."},
    {"point_kinematics", point_kinematics, METH_VARARGS,
     "Relative velocities (before and after a warm start) and effective masses at contact points (see the C "
     "source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._kinematics",
    "Compiled core of deepcontact.kinematics (contact velocities, effective masses, the contact Jacobian).", -1, methods,
};

PyMODINIT_FUNC PyInit__kinematics(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL)
        return NULL;
    const struct {
        const char *name;
        long value;
    } constants[] = {
        {"BODY_SIZE", BODY_SIZE},         {"BODY_TYPE", BODY_TYPE},
        {"BODY_POSITION", BODY_POSITION}, {"BODY_VELOCITY", BODY_VELOCITY},
        {"BODY_ANGULAR_VELOCITY", BODY_ANGULAR_VELOCITY},
        {"BODY_MASS", BODY_MASS},         {"BODY_INERTIA", BODY_INERTIA},
        {"POINT_SIZE", POINT_SIZE},       {"POINT_BODY_A", POINT_BODY_A},
        {"POINT_BODY_B", POINT_BODY_B},   {"POINT_POINT", POINT_POINT},
        {"POINT_NORMAL", POINT_NORMAL},   {"POINT_BUILTIN", POINT_BUILTIN},
        {"WARM_NONE", WARM_NONE},         {"WARM_BUILTIN", WARM_BUILTIN},
        {"WARM_GIVEN", WARM_GIVEN},
    };
    for (size_t k = 0; k < sizeof constants / sizeof constants[0]; k++) {
        if (PyModule_AddIntConstant(mod, constants[k].name, constants[k].value)) {
            Py_DECREF(mod);
            return NULL;
        }
    }
    return mod;
}
