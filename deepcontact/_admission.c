/* Compiled core of deepcontact.admission: nearest_admissible's rounds (ADMM between the
 * bodies' motion kept and the friction cones) and the factorization they run on.
 *
 * deepcontact/admission.py owns the problem and documents it; this is its arithmetic. In
 * NumPy each round was about twenty calls on a few hundred numbers (about 0.1 ms); here it is
 * a few sparse passes, and the factorization skips SciPy's building and converting of sparse
 * matrices. tests/deepcontact/test_admission.py keeps the NumPy rounds as the reference.
 * -ffp-contract=off (setup.py), as for every kernel here: no a*b+c fused, so the numbers do
 * not depend on the compiler's defaults.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

#include "sparse_cholesky.h"

/* nearest_admissible's rounds (deepcontact.admission documents the problem): ADMM between
 * the affine set J^T x = J^T c (the bodies' motion kept) and the friction cones, each round
 *     x = same_motion((c + rho (z - s)) / (1 + rho)),  z' = cones(x + s),  s += x - z',
 * stopping once |x - z'| and |z' - z| are under `tolerance` at every entry. same_motion(y)
 * is y - J (G^-1 (J^T (y - c))), G = J^T J plus its ridge, factorized once per step
 * (gram_cholesky below): P G P^T = C C^T, C lower. In NumPy each round was about twenty
 * calls on a few hundred numbers, about 0.1 ms; here it is a few sparse passes.
 *
 * Arguments: jt as CSR (indptr int32 (R + 1,), indices int32, data float64: R = 3 D rows,
 * 2 P columns), C as CSC (Lp int32 (R + 1,), Li int32, Lx float64; each column's diagonal
 * first), position int32 (R,) (row -> its place in the factor's order), c float64 (2 P,), mu
 * and keep float64 (P,), rho, iterations, tolerance, until (seconds of CLOCK_MONOTONIC,
 * Python's time.monotonic(), after which no round starts; 0: none; read every UNTIL_EVERY
 * rounds) and z float64 (2 P,) out. R = 0: no dynamic body, same_motion is the identity.
 * Returns the rounds run. */
#define UNTIL_EVERY 8

static double monotonic_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static int valid_sparse(const Py_buffer *ptr, const Py_buffer *idx, const Py_buffer *val, Py_ssize_t major,
                        Py_ssize_t minor)
{
    if (ptr->len != (major + 1) * (Py_ssize_t)sizeof(int32_t))
        return 0;
    const int32_t *p = ptr->buf, *i = idx->buf;
    if (p[0] != 0)
        return 0;
    for (Py_ssize_t k = 0; k < major; k++)
        if (p[k + 1] < p[k])
            return 0;
    Py_ssize_t nnz = p[major];
    if (idx->len != nnz * (Py_ssize_t)sizeof(int32_t) || val->len != nnz * (Py_ssize_t)sizeof(double))
        return 0;
    for (Py_ssize_t k = 0; k < nnz; k++)
        if (i[k] < 0 || i[k] >= minor)
            return 0;
    return 1;
}

static void project_cones(const double *v, const double *mu, const double *keep, Py_ssize_t n_points, double *out)
{
    for (Py_ssize_t i = 0; i < n_points; i++) {
        double n = v[2 * i], t = v[2 * i + 1], m = mu[i];
        double at = t < 0 ? -t : t;
        if (at <= m * n) {
            out[2 * i] = n * keep[i];
            out[2 * i + 1] = t * keep[i];
        } else {
            double along = n + m * at;
            along = (along > 0 ? along : 0.0) / (1.0 + m * m);
            double sign = t > 0 ? 1.0 : (t < 0 ? -1.0 : 0.0);
            out[2 * i] = along * keep[i];
            out[2 * i + 1] = sign * m * along * keep[i];
        }
    }
}

static PyObject *admission_rounds(PyObject *self, PyObject *args)
{
    Py_buffer b[12];
    Py_ssize_t rows;
    double rho, tolerance, until;
    long iterations;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*ny*y*y*y*y*y*y*dlddw*", &b[0], &b[1], &b[2], &rows, &b[3], &b[4], &b[5],
                          &b[6], &b[7], &b[8], &b[9], &rho, &iterations, &tolerance, &until, &b[10]))
        return NULL;
    const int n_bufs = 11;
    PyObject *result = NULL;
    double *work = NULL;
    const Py_ssize_t n2 = b[7].len / (Py_ssize_t)sizeof(double), n_points = n2 / 2;
    if (b[7].len != n2 * (Py_ssize_t)sizeof(double) || n2 % 2 || b[8].len != n_points * (Py_ssize_t)sizeof(double)
        || b[9].len != b[8].len || b[10].len != b[7].len || rows < 0
        || !valid_sparse(&b[0], &b[1], &b[2], rows, n2)
        || (rows && (!valid_sparse(&b[3], &b[4], &b[5], rows, rows)
                     || b[6].len != rows * (Py_ssize_t)sizeof(int32_t)))) {
        PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *jp = b[0].buf, *ji = b[1].buf, *lp = b[3].buf, *li = b[4].buf, *position = b[6].buf;
    const double *jd = b[2].buf, *lx = b[5].buf, *c = b[7].buf, *mu = b[8].buf, *keep = b[9].buf;
    double *z = b[10].buf;
    for (Py_ssize_t k = 0; k < rows; k++)
        if (position[k] < 0 || position[k] >= rows || li[lp[k]] != k || !(lx[lp[k]] > 0.0)) {
            PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: a position out of range, or a factor "
                                              "whose columns do not start at a positive diagonal");
            goto done;
        }
    work = PyMem_Calloc((size_t)(4 * n2 + 2 * rows + 1), sizeof(double));
    if (work == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *x = work, *s = x + n2, *y = s + n2, *zp = y + n2, *g = zp + n2, *h = g + rows;
    long round = 0;
    const spchol_factor_t factor = {(int32_t)rows, (int32_t *)lp, (int32_t *)li, (double *)lx};
    Py_BEGIN_ALLOW_THREADS
    project_cones(c, mu, keep, n_points, z);
    while (round < iterations) {
        if (until > 0 && round > 0 && round % UNTIL_EVERY == 0 && monotonic_seconds() >= until)
            break;
        round++;
        for (Py_ssize_t k = 0; k < n2; k++) {
            y[k] = (c[k] + rho * (z[k] - s[k])) / (1.0 + rho);
            x[k] = y[k];
        }
        if (rows) {
            for (Py_ssize_t r = 0; r < rows; r++) { /* g = P (J^T (y - c)) */
                double acc = 0.0;
                for (int32_t k = jp[r]; k < jp[r + 1]; k++)
                    acc += jd[k] * (y[ji[k]] - c[ji[k]]);
                g[position[r]] = acc;
            }
            spchol_solve(&factor, g); /* (C C^T)^-1 */
            for (Py_ssize_t r = 0; r < rows; r++) /* h = P^T g: G^-1 (J^T (y - c)) */
                h[r] = g[position[r]];
            for (Py_ssize_t r = 0; r < rows; r++) /* x = y - J h */
                for (int32_t k = jp[r]; k < jp[r + 1]; k++)
                    x[ji[k]] -= jd[k] * h[r];
        }
        memcpy(zp, z, (size_t)n2 * sizeof(double));
        for (Py_ssize_t k = 0; k < n2; k++)
            y[k] = x[k] + s[k];
        project_cones(y, mu, keep, n_points, z);
        double change = 0.0;
        for (Py_ssize_t k = 0; k < n2; k++) {
            double gap = x[k] - z[k], moved = z[k] - zp[k];
            s[k] += gap;
            gap = gap < 0 ? -gap : gap;
            moved = moved < 0 ? -moved : moved;
            if (gap > change)
                change = gap;
            if (moved > change)
                change = moved;
        }
        if (change < tolerance)
            break;
    }
    Py_END_ALLOW_THREADS
    result = PyLong_FromLong(round);
done:
    PyMem_Free(work);
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

/* nearest_admissible's factorization of G = J^T J + ridge I (admission.admission_factors): G
 * summed from J^T's rows, its rows and columns in the order `order` (a minimum degree order of
 * the bodies, body_order below), factored by sparse Cholesky (sparse_cholesky.h). A
 * pivot that rounding leaves below the ridge is the ridge: G is singular where a body's points
 * cannot push it every way, and what the ridge adds in those directions J takes away again.
 * An envelope (skyline) Cholesky in the same order held about twice the entries, each walked
 * twice a round; SciPy's SuperLU before it took about 0.8 ms at the thesis world's largest steps.
 *
 * Arguments: J^T's CSR arrays jp int32 (rows + 1,), ji int32, jd float64; rows; cols (J^T's
 * columns, 2 P); order int32 (rows,), a permutation (new position -> row); ridge (relative to
 * G's largest diagonal entry). Returns (Lp, Li, Lx) as bytes: the factor C (C C^T = the
 * ordered G), lower, CSC, int32 (rows + 1,), int32 and float64, each column's diagonal first. */
static PyObject *gram_cholesky(PyObject *self, PyObject *args)
{
    Py_buffer b[4];
    Py_ssize_t rows, cols;
    double ridge;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*nny*d", &b[0], &b[1], &b[2], &rows, &cols, &b[3], &ridge))
        return NULL;
    const int n_bufs = 4;
    PyObject *result = NULL;
    int32_t *cp = NULL, *ci = NULL, *gp = NULL, *gi = NULL, *up = NULL, *ui = NULL, *inverse = NULL;
    double *cx = NULL, *gx = NULL, *ux = NULL;
    spchol_factor_t factor = {0, NULL, NULL, NULL};
    const Py_ssize_t i32 = (Py_ssize_t)sizeof(int32_t);
    if (rows < 0 || cols < 0 || rows > INT32_MAX / 4 || cols > INT32_MAX / 4
        || !valid_sparse(&b[0], &b[1], &b[2], rows, cols) || b[3].len != rows * i32) {
        PyErr_SetString(PyExc_ValueError, "_admission.gram_cholesky: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *jp = b[0].buf, *ji = b[1].buf, *order = b[3].buf;
    const double *jd = b[2].buf;
    inverse = malloc(((size_t)rows + 1) * sizeof(int32_t));
    if (inverse == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t k = 0; k < rows; k++)
        inverse[k] = -1;
    for (Py_ssize_t k = 0; k < rows; k++) {
        if (order[k] < 0 || order[k] >= rows || inverse[order[k]] >= 0) {
            PyErr_SetString(PyExc_ValueError, "_admission.gram_cholesky: order is not a permutation");
            goto done;
        }
        inverse[order[k]] = (int32_t)k;
    }
    int status = -1;
    Py_BEGIN_ALLOW_THREADS
    {
        const int32_t nnz = rows ? jp[rows] : 0;
        cp = calloc((size_t)cols + 2, sizeof(int32_t));
        ci = malloc(((size_t)nnz + 1) * sizeof(int32_t));
        cx = malloc(((size_t)nnz + 1) * sizeof(double));
        if (cp == NULL || ci == NULL || cx == NULL)
            goto out;
        spchol_transpose((int32_t)rows, (int32_t)cols, jp, ji, jd, cp, ci, cx);
        double trace;
        if (spchol_gram((int32_t)rows, jp, ji, jd, cp, ci, cx, &gp, &gi, &gx, &trace) != 0)
            goto out;
        double top = 0.0;
        for (Py_ssize_t i = 0; i < rows; i++)
            for (int32_t q = gp[i]; q < gp[i + 1]; q++)
                if (gi[q] == i && gx[q] > top)
                    top = gx[q];
        const double added = ridge * (top > 0.0 ? top : 1e-300);
        up = malloc(((size_t)rows + 1) * sizeof(int32_t));
        ui = malloc(((size_t)gp[rows] + 1) * sizeof(int32_t));
        ux = malloc(((size_t)gp[rows] + 1) * sizeof(double));
        if (up == NULL || ui == NULL || ux == NULL
            || spchol_permute_upper((int32_t)rows, gp, gi, gx, order, inverse, up, ui, ux) != 0)
            goto out;
        status = spchol_factor((int32_t)rows, up, ui, ux, added, added, &factor);
    }
out:
    Py_END_ALLOW_THREADS
    if (status != 0) {
        PyErr_SetString(status < 0 ? PyExc_MemoryError : PyExc_ArithmeticError,
                        status < 0 ? "_admission.gram_cholesky: out of memory" : "_admission.gram_cholesky: a pivot");
        goto done;
    }
    const Py_ssize_t entries = rows ? factor.Lp[rows] : 0;
    if (rows == 0) {
        int32_t zero = 0;
        result = Py_BuildValue("(y#y#y#)", (const char *)&zero, i32, "", (Py_ssize_t)0, "", (Py_ssize_t)0);
    } else {
        result = Py_BuildValue("(y#y#y#)", (const char *)factor.Lp, (rows + 1) * i32, (const char *)factor.Li,
                               entries * i32, (const char *)factor.Lx, entries * (Py_ssize_t)sizeof(double));
    }
done:
    spchol_free(&factor);
    free(cp), free(ci), free(cx), free(gp), free(gi), free(gx), free(up), free(ui), free(ux), free(inverse);
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

/* A minimum degree order of the dynamic bodies (admission.admission_factors; sparse_cholesky.h's
 * spchol_min_degree): the graph joins two bodies where a point touches both, and G = J^T J
 * couples their rows there, so its Cholesky factor, which the admission's rounds walk twice,
 * stays sparse. SciPy's reverse Cuthill-McKee, with the sparse graph it needs built first, took
 * about 0.15 ms at the thesis world's median step, and its factor held a fifth to a third more
 * entries.
 *
 * Arguments: a, b int64 (P,) body indices; row int32 (B,) each body's dynamic row or -1;
 * n_dynamic; out: order int64 (n_dynamic,). */
static PyObject *body_order(PyObject *self, PyObject *args)
{
    Py_buffer b[4];
    Py_ssize_t n_dyn;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*nw*", &b[0], &b[1], &b[2], &n_dyn, &b[3]))
        return NULL;
    const int n_bufs = 4;
    PyObject *result = NULL;
    int32_t *start = NULL, *adj = NULL, *fill = NULL, *order32 = NULL;
    const Py_ssize_t n_points = b[0].len / (Py_ssize_t)sizeof(int64_t), n_bodies = b[2].len / (Py_ssize_t)sizeof(int32_t);
    if (b[0].len != n_points * (Py_ssize_t)sizeof(int64_t) || b[1].len != b[0].len || n_dyn < 0
        || n_dyn > INT32_MAX / 2 || b[3].len != n_dyn * (Py_ssize_t)sizeof(int64_t)) {
        PyErr_SetString(PyExc_ValueError, "_admission.body_order: arrays of the wrong size");
        goto done;
    }
    const int64_t *pa = b[0].buf, *pb = b[1].buf;
    const int32_t *row = b[2].buf;
    int64_t *order = b[3].buf;
    for (Py_ssize_t i = 0; i < n_points; i++)
        if (pa[i] < 0 || pa[i] >= n_bodies || pb[i] < 0 || pb[i] >= n_bodies || row[pa[i]] >= n_dyn
            || row[pb[i]] >= n_dyn) {
            PyErr_SetString(PyExc_ValueError, "_admission.body_order: a point names a body out of range");
            goto done;
        }
    start = calloc((size_t)n_dyn + 2, sizeof(int32_t));
    fill = calloc((size_t)n_dyn + 1, sizeof(int32_t));
    adj = malloc(((size_t)2 * n_points + 1) * sizeof(int32_t));
    order32 = malloc(((size_t)n_dyn + 1) * sizeof(int32_t));
    if (start == NULL || fill == NULL || adj == NULL || order32 == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    /* Adjacency lists, a pair once per point that joins them (repeats only make a list longer). */
    for (Py_ssize_t i = 0; i < n_points; i++) {
        int32_t u = row[pa[i]], v = row[pb[i]];
        if (u >= 0 && v >= 0 && u != v) {
            start[u + 1]++;
            start[v + 1]++;
        }
    }
    for (Py_ssize_t k = 0; k < n_dyn; k++)
        start[k + 1] += start[k];
    for (Py_ssize_t i = 0; i < n_points; i++) {
        int32_t u = row[pa[i]], v = row[pb[i]];
        if (u >= 0 && v >= 0 && u != v) {
            adj[start[u] + fill[u]++] = v;
            adj[start[v] + fill[v]++] = u;
        }
    }
    if (spchol_min_degree((int32_t)n_dyn, start, adj, order32) != 0) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t k = 0; k < n_dyn; k++)
        order[k] = order32[k];
    result = Py_NewRef(Py_None);
done:
    free(start), free(fill), free(adj), free(order32);
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"body_order", body_order, METH_VARARGS,
     "A minimum degree order of the dynamic bodies (see the C source)."},
    {"gram_cholesky", gram_cholesky, METH_VARARGS,
     "nearest_admissible's factorization, as admission_rounds takes it (see the C source)."},
    {"admission_rounds", admission_rounds, METH_VARARGS,
     "nearest_admissible's ADMM rounds on a factorized gram (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._admission",
    "Compiled core of deepcontact.admission (the admission rounds, their factorization and its order).", -1, methods,
};

PyMODINIT_FUNC PyInit__admission(void)
{
    return PyModule_Create(&module);
}
