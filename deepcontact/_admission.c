/* Compiled core of deepcontact.admission: nearest_admissible's rounds (ADMM between the
 * bodies' motion kept and the friction cones), the factorization they run on and its order.
 *
 * deepcontact/admission.py owns the problem and documents it; deepcontact/admission_kernels.h
 * holds the arithmetic, which deepcontact/_route.c shares; this module checks Python's arrays
 * and calls it. In NumPy each round was about twenty calls on a few hundred numbers (about
 * 0.1 ms); here it is a few sparse passes, and the factorization skips SciPy's building and
 * converting of sparse matrices. tests/deepcontact/test_admission.py keeps the NumPy rounds as
 * the reference. -ffp-contract=off (setup.py), as for every kernel here: no a*b+c fused, so
 * the numbers do not depend on the compiler's defaults.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "admission_kernels.h"

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

static void release(Py_buffer *b, int n)
{
    for (int k = 0; k < n; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
}

/* admission_rounds(jp, ji, jd, rows, Lp, Li, Lx, position, c, mu, keep, rho, iterations,
 *                  tolerance, relax, until, z) -> rounds run
 *
 * jt as CSR (indptr int32 (R + 1,), indices int32, data float64: R = 3 D rows, 2 P columns),
 * C as CSC (Lp int32 (R + 1,), Li int32, Lx float64; each column's diagonal first),
 * position int32 (R,) (row -> its place in the factor's order), c float64 (2 P,), mu and keep
 * float64 (P,), rho, iterations, tolerance, relax (the over-relaxation, admission_kernels.h),
 * until (seconds of CLOCK_MONOTONIC, Python's time.monotonic(), after which no round starts; 0:
 * none) and z float64 (2 P,) out. R = 0: no dynamic body, same_motion is the identity. */
static PyObject *admission_rounds(PyObject *self, PyObject *args)
{
    Py_buffer b[11];
    Py_ssize_t rows;
    double rho, tolerance, relax, until;
    long iterations;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*ny*y*y*y*y*y*y*dldddw*", &b[0], &b[1], &b[2], &rows, &b[3], &b[4], &b[5],
                          &b[6], &b[7], &b[8], &b[9], &rho, &iterations, &tolerance, &relax, &until, &b[10]))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n2 = b[7].len / (Py_ssize_t)sizeof(double), n_points = n2 / 2;
    if (b[7].len != n2 * (Py_ssize_t)sizeof(double) || n2 % 2 || b[8].len != n_points * (Py_ssize_t)sizeof(double)
        || b[9].len != b[8].len || b[10].len != b[7].len || !(relax > 0.0 && relax < 2.0) || rows < 0 || rows > INT32_MAX / 4
        || !valid_sparse(&b[0], &b[1], &b[2], rows, n2)
        || (rows && (!valid_sparse(&b[3], &b[4], &b[5], rows, rows)
                     || b[6].len != rows * (Py_ssize_t)sizeof(int32_t)))) {
        PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *lp = b[3].buf, *li = b[4].buf, *position = b[6].buf;
    const double *lx = b[5].buf;
    for (Py_ssize_t k = 0; k < rows; k++)
        if (position[k] < 0 || position[k] >= rows || li[lp[k]] != k || !(lx[lp[k]] > 0.0)) {
            PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: a position out of range, or a factor "
                                              "whose columns do not start at a positive diagonal");
            goto done;
        }
    const spchol_factor_t factor = {(int32_t)rows, (int32_t *)lp, (int32_t *)li, (double *)lx};
    long rounds;
    Py_BEGIN_ALLOW_THREADS
    rounds = admission_rounds_run((int32_t)rows, n2, b[0].buf, b[1].buf, b[2].buf, &factor, position, b[7].buf,
                                  b[8].buf, b[9].buf, rho, iterations, tolerance, relax, until, b[10].buf, NULL);
    Py_END_ALLOW_THREADS
    if (rounds < 0)
        PyErr_NoMemory();
    else
        result = PyLong_FromLong(rounds);
done:
    release(b, 11);
    return result;
}

/* gram_cholesky(jp, ji, jd, rows, cols, order, ridge) -> (Lp, Li, Lx) as bytes
 *
 * nearest_admissible's factorization of G = J^T J + ridge I (admission.admission_factors;
 * admission_kernels.h's gram_factor): J^T's CSR arrays (int32 (rows + 1,), int32, float64);
 * rows; cols (J^T's columns, 2 P); order int32 (rows,), a permutation (new position -> row);
 * ridge (relative to G's largest diagonal entry). The factor C (C C^T = the ordered G) is
 * lower, CSC, int32 (rows + 1,), int32 and float64, each column's diagonal first. An envelope
 * (skyline) Cholesky in a reverse Cuthill-McKee order held about 2.6 times the entries at the
 * thesis world's largest steps, each walked twice a round; SciPy's SuperLU before it took
 * about 0.8 ms there. */
static PyObject *gram_cholesky(PyObject *self, PyObject *args)
{
    Py_buffer b[4];
    Py_ssize_t rows, cols;
    double ridge;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*nny*d", &b[0], &b[1], &b[2], &rows, &cols, &b[3], &ridge))
        return NULL;
    PyObject *result = NULL;
    int32_t *inverse = NULL;
    spchol_factor_t factor = {0, NULL, NULL, NULL};
    const Py_ssize_t i32 = (Py_ssize_t)sizeof(int32_t);
    if (rows < 0 || cols < 0 || rows > INT32_MAX / 4 || cols > INT32_MAX / 4
        || !valid_sparse(&b[0], &b[1], &b[2], rows, cols) || b[3].len != rows * i32) {
        PyErr_SetString(PyExc_ValueError, "_admission.gram_cholesky: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *order = b[3].buf;
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
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = gram_factor((int32_t)rows, (int32_t)cols, b[0].buf, b[1].buf, b[2].buf, order, ridge, inverse, &factor);
    Py_END_ALLOW_THREADS
    if (status != 0) {
        PyErr_SetString(status < 0 ? PyExc_MemoryError : PyExc_ArithmeticError,
                        status < 0 ? "_admission.gram_cholesky: out of memory" : "_admission.gram_cholesky: a pivot");
        goto done;
    }
    const Py_ssize_t entries = factor.Lp[rows];
    result = Py_BuildValue("(y#y#y#)", (const char *)factor.Lp, (rows + 1) * i32, (const char *)factor.Li,
                           entries * i32, (const char *)factor.Lx, entries * (Py_ssize_t)sizeof(double));
done:
    spchol_free(&factor);
    free(inverse);
    release(b, 4);
    return result;
}

/* body_order(a, b, row, n_dynamic, order) -> None
 *
 * A minimum degree order of the dynamic bodies (admission_kernels.h's body_order_min_degree):
 * the graph joins two bodies where a point touches both, and G = J^T J couples their rows
 * there, so its Cholesky factor, which the admission's rounds walk twice, stays sparse.
 * SciPy's reverse Cuthill-McKee, with the sparse graph it needs built first, took about
 * 0.15 ms at the thesis world's median step, and its factor held a fifth to a third more
 * entries. a, b int64 (P,) body indices; row int32 (B,) each body's dynamic row or -1;
 * n_dynamic; order int64 (n_dynamic,) out. */
static PyObject *body_order(PyObject *self, PyObject *args)
{
    Py_buffer b[4];
    Py_ssize_t n_dyn;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*nw*", &b[0], &b[1], &b[2], &n_dyn, &b[3]))
        return NULL;
    PyObject *result = NULL;
    int32_t *order32 = NULL;
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
    order32 = malloc(((size_t)n_dyn + 1) * sizeof(int32_t));
    if (order32 == NULL || body_order_min_degree(n_points, pa, pb, row, (int32_t)n_dyn, order32) != 0) {
        PyErr_NoMemory();
        goto done;
    }
    for (Py_ssize_t k = 0; k < n_dyn; k++)
        order[k] = order32[k];
    result = Py_NewRef(Py_None);
done:
    free(order32);
    release(b, 4);
    return result;
}

static PyMethodDef methods[] = {
    {"gram_cholesky", gram_cholesky, METH_VARARGS,
     "nearest_admissible's factorization, as admission_rounds takes it (see the C source)."},
    {"body_order", body_order, METH_VARARGS, "A minimum degree order of the dynamic bodies (see the C source)."},
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
