/* Compiled core of deepcontact.faces: the linear system of a step solved on a face of its
 * limits (face_system's sum over the pairs of points that share a body, as CSR), its dual
 * solve on a sparse Cholesky factor (minimum_norm_solve), and the dense S S^T of the dense
 * path that backs it.
 *
 * deepcontact/faces.py owns the system and documents it; this is its arithmetic, where
 * NumPy's fancy indexing and dense products cost about a millisecond a step.
 * tests/deepcontact/test_faces.py checks them against the dense NumPy products and the
 * pseudo-inverse.
 * -ffp-contract=off (setup.py), as for every kernel here.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "face_kernels.h"

/* face_system's sum (deepcontact.faces documents the system): every ordered pair of a
 * dynamic body's pushes (i, j) adds the relative velocity along direction d at i's point that a
 * unit impulse along e at j's point causes through that body, g_i[d] . W g_j[e] (W: the body's
 * inverse mass, mass, inertia), to the equation of i's point along d and the unknowns of j's
 * point: its normal column (plus slide times its tangent one) where it presses, its tangent
 * column where it sticks. NumPy built the same sum from a few thousand pairs with fancy indexing
 * and a bincount, about a millisecond at 160 points. The system is about 3 % full, so it comes
 * out as CSR: each entry the sum of its terms in the order the pairs give them (bodies in
 * order, then their pushes), the same numbers a dense array summed in place holds.
 *
 * Arguments: a and b int64 (P,) body rows of each point, dynamic uint8 (B,), inv_mass and
 * inv_inertia float64 (B,), n, t, ra, rb float64 (2 P,) (x, y per point), index int64 (2 P,):
 * each point's equation row and unknown column by direction (normal 2 i, tangent 2 i + 1), -1
 * where it has none, all below m; slide float64 (P,); m. Returns (indptr, indices, data) as
 * bytes: int32 (m + 1,), int32 and float64 (nnz,), each row's columns in the order first met. */
static PyObject *face_system_sum(PyObject *self, PyObject *args)
{
    Py_buffer b[11];
    Py_ssize_t m;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*y*y*n", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7],
                          &b[8], &b[9], &b[10], &m))
        return NULL;
    const int n_bufs = 11;
    PyObject *result = NULL;
    const Py_ssize_t n_points = b[0].len / (Py_ssize_t)sizeof(int64_t), n_bodies = b[2].len;
    const Py_ssize_t vec = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (b[0].len != n_points * (Py_ssize_t)sizeof(int64_t) || b[1].len != b[0].len
        || b[3].len != n_bodies * (Py_ssize_t)sizeof(double) || b[4].len != b[3].len || b[5].len != vec
        || b[6].len != vec || b[7].len != vec || b[8].len != vec || b[9].len != 2 * b[0].len
        || b[10].len != n_points * (Py_ssize_t)sizeof(double) || m < 0 || m > INT32_MAX / 2) {
        PyErr_SetString(PyExc_ValueError, "_faces.face_system_sum: arrays of the wrong size");
        goto done;
    }
    const int64_t *pa = b[0].buf, *pb = b[1].buf, *index = b[9].buf;
    for (Py_ssize_t i = 0; i < n_points; i++)
        if (pa[i] < 0 || pa[i] >= n_bodies || pb[i] < 0 || pb[i] >= n_bodies || index[2 * i] < -1
            || index[2 * i] >= m || index[2 * i + 1] < -1 || index[2 * i + 1] >= m) {
            PyErr_SetString(PyExc_ValueError, "_faces.face_system_sum: a body or an index out of range");
            goto done;
        }
    int32_t *out_p = NULL, *out_c = NULL;
    double *out_v = NULL;
    int64_t nnz = 0;
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = face_system_csr(n_points, n_bodies, pa, pb, b[2].buf, b[3].buf, b[4].buf, b[5].buf, b[6].buf, b[7].buf,
                             b[8].buf, index, b[10].buf, m, &out_p, &out_c, &out_v, &nnz);
    Py_END_ALLOW_THREADS
    if (status != 0)
        PyErr_NoMemory();
    else
        result = Py_BuildValue("(y#y#y#)", (const char *)out_p, (Py_ssize_t)((m + 1) * sizeof(int32_t)),
                               (const char *)out_c, (Py_ssize_t)(nnz * sizeof(int32_t)), (const char *)out_v,
                               (Py_ssize_t)(nnz * sizeof(double)));
    free(out_p), free(out_c), free(out_v);
done:
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

/* minimum_norm_solve's S S^T for a face's system S (m, m), row-major and mostly zeros (a
 * point's equation couples it only to the points that share one of its bodies: about 3 % of
 * the entries at the thesis world's largest steps). Each column's nonzero rows are gathered
 * once and their outer product summed into the lower triangle of `gram` (row-major, zeroed,
 * out), which is what LAPACK's potrf (lower, Fortran order: the upper triangle here) reads;
 * the upper triangle is then mirrored so that the caller holds the whole matrix. BLAS's dense
 * product took about 0.9 ms at 300 unknowns, summing what is not zero a few tens of µs.
 *
 * Arguments: system float64 (m * m,), m, gram float64 (m * m,), out. */
static PyObject *sparse_gram(PyObject *self, PyObject *args)
{
    Py_buffer b[2];
    Py_ssize_t m;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*nw*", &b[0], &m, &b[1]))
        return NULL;
    PyObject *result = NULL;
    Py_ssize_t *rows = NULL;
    double *vals = NULL;
    if (m < 0 || b[0].len != m * m * (Py_ssize_t)sizeof(double) || b[1].len != b[0].len) {
        PyErr_SetString(PyExc_ValueError, "_faces.sparse_gram: arrays of the wrong size");
        goto done;
    }
    rows = PyMem_Malloc((size_t)(m ? m : 1) * sizeof(Py_ssize_t));
    vals = PyMem_Malloc((size_t)(m ? m : 1) * sizeof(double));
    if (rows == NULL || vals == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    const double *system = b[0].buf;
    double *gram = b[1].buf;
    Py_BEGIN_ALLOW_THREADS
    memset(gram, 0, (size_t)(m * m) * sizeof(double));
    for (Py_ssize_t j = 0; j < m; j++) {
        Py_ssize_t count = 0;
        for (Py_ssize_t i = 0; i < m; i++) {
            double v = system[i * m + j];
            if (v != 0.0) {
                rows[count] = i;
                vals[count++] = v;
            }
        }
        for (Py_ssize_t p = 0; p < count; p++) { /* rows ascend: q <= p is the lower triangle */
            double *row = gram + rows[p] * m;
            for (Py_ssize_t q = 0; q <= p; q++)
                row[rows[q]] += vals[p] * vals[q];
        }
    }
    for (Py_ssize_t i = 0; i < m; i++)
        for (Py_ssize_t k = 0; k < i; k++)
            gram[k * m + i] = gram[i * m + k];
    Py_END_ALLOW_THREADS
    result = Py_NewRef(Py_None);
done:
    PyMem_Free(rows);
    PyMem_Free(vals);
    for (int k = 0; k < 2; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

/* minimum_norm_solve's dual solve on S's nonzeros (deepcontact.faces documents it): S S^T
 * summed from S's columns, in a reverse Cuthill-McKee order (a minimum degree order holds about
 * a tenth fewer entries here and takes several times as long to find), factored by sparse Cholesky
 * with the ridge, y = (S S^T)^-1 b refined `refinements` times against S S^T itself, x = S^T y,
 * and the answer kept only where |S^T (S x - b)| <= optimality |S^T b|. The same steps as the
 * dense path in faces.py (LAPACK's dpotrf on S S^T), on a tenth to a fifth of its entries: a
 * face's S is about 3 % full and S S^T under 10 %.
 *
 * Arguments: S as CSR (indptr int32 (m + 1,), indices int32, data float64: face_system_sum's),
 * rhs float64 (m,), ridge (relative to S S^T's mean diagonal), refinements, optimality, x
 * float64 (m,) out. Returns 0 (x written), 1 (S S^T not positive definite to rounding: the
 * caller solves densely, with an LU) or 2 (x is not a least-squares answer: the system is far
 * from consistent). */
static PyObject *dual_solve(PyObject *self, PyObject *args)
{
    Py_buffer b[5];
    double ridge, optimality;
    int refinements;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*y*didw*", &b[0], &b[1], &b[2], &b[3], &ridge, &refinements, &optimality,
                          &b[4]))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t m = b[3].len / (Py_ssize_t)sizeof(double), nnz = b[1].len / (Py_ssize_t)sizeof(int32_t);
    if (b[3].len != m * (Py_ssize_t)sizeof(double) || b[0].len != (m + 1) * (Py_ssize_t)sizeof(int32_t)
        || b[2].len != nnz * (Py_ssize_t)sizeof(double) || b[4].len != b[3].len || refinements < 0
        || m > INT32_MAX / 4) {
        PyErr_SetString(PyExc_ValueError, "_faces.dual_solve: arrays of the wrong size");
        goto done;
    }
    const int32_t *sp = b[0].buf, *si = b[1].buf;
    const double *sx = b[2].buf, *rhs = b[3].buf;
    double *x = b[4].buf;
    if (sp[0] != 0 || sp[m] != nnz) {
        PyErr_SetString(PyExc_ValueError, "_faces.dual_solve: not a CSR matrix");
        goto done;
    }
    for (Py_ssize_t i = 0; i < m; i++)
        if (sp[i + 1] < sp[i]) {
            PyErr_SetString(PyExc_ValueError, "_faces.dual_solve: not a CSR matrix");
            goto done;
        }
    for (Py_ssize_t k = 0; k < nnz; k++)
        if (si[k] < 0 || si[k] >= m) {
            PyErr_SetString(PyExc_ValueError, "_faces.dual_solve: a column out of range");
            goto done;
        }
    int status;
    Py_BEGIN_ALLOW_THREADS
    status = face_dual_solve(m, sp, si, sx, rhs, ridge, refinements, optimality, x);
    Py_END_ALLOW_THREADS
    if (status < 0)
        PyErr_NoMemory();
    else
        result = PyLong_FromLong(status);
done:
    for (int k = 0; k < 5; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"face_system_sum", face_system_sum, METH_VARARGS,
     "face_system's sum over the pairs of a dynamic body's pushes (see the C source)."},
    {"sparse_gram", sparse_gram, METH_VARARGS, "S S^T of a mostly-zero square system (see the C source)."},
    {"dual_solve", dual_solve, METH_VARARGS,
     "minimum_norm_solve's dual solve by sparse Cholesky on S's nonzeros (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._faces",
    "Compiled core of deepcontact.faces (a face's system and its dual's gram).", -1, methods,
};

PyMODINIT_FUNC PyInit__faces(void)
{
    return PyModule_Create(&module);
}
