/* Compiled core of deepcontact.faces: the linear system of a step solved on a face of its
 * limits (face_system's sum over the pairs of points that share a body) and the S S^T of
 * its dual solve (minimum_norm_solve).
 *
 * deepcontact/faces.py owns the system and documents it; this is its arithmetic, where
 * NumPy's fancy indexing and dense products cost about a millisecond a step.
 * tests/deepcontact/test_faces.py checks both against the dense NumPy products.
 * -ffp-contract=off (setup.py), as for every kernel here.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

/* face_system's sum (deepcontact.faces documents the system): every ordered pair of a
 * dynamic body's pushes (i, j) adds the relative velocity along direction d at i's point that a
 * unit impulse along e at j's point causes through that body, g_i[d] . W g_j[e] (W: the body's
 * inverse mass, mass, inertia), to the equation of i's point along d and the unknowns of j's
 * point: its normal column (plus slide times its tangent one) where it presses, its tangent
 * column where it sticks. NumPy built the same sum from a few thousand pairs with fancy indexing
 * and a bincount, about a millisecond at 160 points.
 *
 * Arguments: a and b int64 (P,) body rows of each point, dynamic uint8 (B,), inv_mass and
 * inv_inertia float64 (B,), n, t, ra, rb float64 (2 P,) (x, y per point), index int64 (2 P,):
 * each point's equation row and unknown column by direction (normal 2 i, tangent 2 i + 1), -1
 * where it has none, all below m; slide float64 (P,); m; system float64 (m * m,), zeroed, out
 * (row-major). */
static PyObject *face_system_sum(PyObject *self, PyObject *args)
{
    Py_buffer b[12];
    Py_ssize_t m;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*y*y*y*y*y*y*y*y*nw*", &b[0], &b[1], &b[2], &b[3], &b[4], &b[5], &b[6], &b[7],
                          &b[8], &b[9], &b[10], &m, &b[11]))
        return NULL;
    const int n_bufs = 12;
    PyObject *result = NULL;
    Py_ssize_t *start = NULL;
    double *push = NULL;
    int64_t *owner = NULL;
    const Py_ssize_t n_points = b[0].len / (Py_ssize_t)sizeof(int64_t), n_bodies = b[2].len;
    const Py_ssize_t vec = 2 * n_points * (Py_ssize_t)sizeof(double);
    if (b[0].len != n_points * (Py_ssize_t)sizeof(int64_t) || b[1].len != b[0].len
        || b[3].len != n_bodies * (Py_ssize_t)sizeof(double) || b[4].len != b[3].len || b[5].len != vec
        || b[6].len != vec || b[7].len != vec || b[8].len != vec || b[9].len != 2 * b[0].len
        || b[10].len != n_points * (Py_ssize_t)sizeof(double) || m < 0
        || b[11].len != m * m * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_ValueError, "_faces.face_system_sum: arrays of the wrong size");
        goto done;
    }
    const int64_t *pa = b[0].buf, *pb = b[1].buf, *index = b[9].buf;
    const unsigned char *dynamic = b[2].buf;
    const double *inv_mass = b[3].buf, *inv_inertia = b[4].buf, *n = b[5].buf, *t = b[6].buf, *ra = b[7].buf,
                 *rb = b[8].buf, *slide = b[10].buf;
    double *system = b[11].buf;
    for (Py_ssize_t i = 0; i < n_points; i++)
        if (pa[i] < 0 || pa[i] >= n_bodies || pb[i] < 0 || pb[i] >= n_bodies || index[2 * i] < -1
            || index[2 * i] >= m || index[2 * i + 1] < -1 || index[2 * i + 1] >= m) {
            PyErr_SetString(PyExc_ValueError, "_faces.face_system_sum: a body or an index out of range");
            goto done;
        }
    start = PyMem_Calloc((size_t)(n_bodies + 2), sizeof(Py_ssize_t));
    push = PyMem_Malloc((size_t)(2 * n_points + 1) * 6 * sizeof(double));
    owner = PyMem_Malloc((size_t)(2 * n_points + 1) * sizeof(int64_t));
    if (start == NULL || push == NULL || owner == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_BEGIN_ALLOW_THREADS
    /* The pushes grouped by body (a counting sort): start[k] .. start[k + 1] are body k's. */
    for (Py_ssize_t i = 0; i < n_points; i++) {
        if (dynamic[pb[i]])
            start[pb[i] + 2]++;
        if (dynamic[pa[i]])
            start[pa[i] + 2]++;
    }
    for (Py_ssize_t k = 0; k < n_bodies; k++)
        start[k + 2] += start[k + 1];
    for (Py_ssize_t i = 0; i < n_points; i++)
        for (int side = 0; side < 2; side++) { /* body b pushed along +n, body a along -n */
            const int64_t body = side == 0 ? pb[i] : pa[i];
            if (!dynamic[body])
                continue;
            const double sign = side == 0 ? 1.0 : -1.0, *r = side == 0 ? rb + 2 * i : ra + 2 * i;
            const Py_ssize_t at = start[body + 1]++;
            double *g = push + 6 * at; /* (normal, tangent) x (x, y, angular) */
            for (int d = 0; d < 2; d++) {
                const double *dir = (d == 0 ? n : t) + 2 * i;
                g[3 * d] = sign * dir[0];
                g[3 * d + 1] = sign * dir[1];
                g[3 * d + 2] = sign * (r[0] * dir[1] - r[1] * dir[0]);
            }
            owner[at] = i;
        }
    /* start[k + 1] now ends body k's pushes, start[k] begins them. */
    for (Py_ssize_t k = 0; k < n_bodies; k++) {
        const double w[3] = {inv_mass[k], inv_mass[k], inv_inertia[k]};
        for (Py_ssize_t p = start[k]; p < start[k + 1]; p++) {
            const double *gi = push + 6 * p;
            const int64_t i = owner[p];
            for (Py_ssize_t q = start[k]; q < start[k + 1]; q++) {
                const double *gj = push + 6 * q;
                const int64_t j = owner[q];
                const int64_t pressing = index[2 * j], sticking = index[2 * j + 1];
                for (int d = 0; d < 2; d++) {
                    const int64_t row = index[2 * i + d];
                    if (row < 0)
                        continue;
                    const double along_n = gi[3 * d] * w[0] * gj[0] + gi[3 * d + 1] * w[1] * gj[1]
                                           + gi[3 * d + 2] * w[2] * gj[2];
                    const double along_t = gi[3 * d] * w[0] * gj[3] + gi[3 * d + 1] * w[1] * gj[4]
                                           + gi[3 * d + 2] * w[2] * gj[5];
                    if (pressing >= 0)
                        system[row * m + pressing] += along_n + slide[j] * along_t;
                    if (sticking >= 0)
                        system[row * m + sticking] += along_t;
                }
            }
        }
    }
    Py_END_ALLOW_THREADS
    Py_INCREF(Py_None);
    result = Py_None;
done:
    PyMem_Free(start);
    PyMem_Free(push);
    PyMem_Free(owner);
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

static PyMethodDef methods[] = {
    {"face_system_sum", face_system_sum, METH_VARARGS,
     "face_system's sum over the pairs of a dynamic body's pushes (see the C source)."},
    {"sparse_gram", sparse_gram, METH_VARARGS, "S S^T of a mostly-zero square system (see the C source)."},
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
