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

#include "sparse_cholesky.h"

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
    Py_ssize_t *start = NULL;
    double *push = NULL, *term_v = NULL, *out_v = NULL;
    int64_t *owner = NULL;
    int32_t *term_r = NULL, *term_c = NULL, *row_start = NULL, *sorted = NULL, *marker = NULL, *slot = NULL;
    int32_t *out_p = NULL, *out_c = NULL;
    Py_ssize_t nnz = 0;
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
    const unsigned char *dynamic = b[2].buf;
    const double *inv_mass = b[3].buf, *inv_inertia = b[4].buf, *n = b[5].buf, *t = b[6].buf, *ra = b[7].buf,
                 *rb = b[8].buf, *slide = b[10].buf;
    for (Py_ssize_t i = 0; i < n_points; i++)
        if (pa[i] < 0 || pa[i] >= n_bodies || pb[i] < 0 || pb[i] >= n_bodies || index[2 * i] < -1
            || index[2 * i] >= m || index[2 * i + 1] < -1 || index[2 * i + 1] >= m) {
            PyErr_SetString(PyExc_ValueError, "_faces.face_system_sum: a body or an index out of range");
            goto done;
        }
    int out_of_memory = 1;
    Py_BEGIN_ALLOW_THREADS
    start = calloc((size_t)(n_bodies + 2), sizeof(Py_ssize_t));
    push = malloc((size_t)(2 * n_points + 1) * 6 * sizeof(double));
    owner = malloc((size_t)(2 * n_points + 1) * sizeof(int64_t));
    row_start = calloc((size_t)(m + 2), sizeof(int32_t));
    marker = malloc((size_t)(m + 1) * sizeof(int32_t));
    slot = malloc((size_t)(m + 1) * sizeof(int32_t));
    out_p = malloc((size_t)(m + 1) * sizeof(int32_t));
    if (start == NULL || push == NULL || owner == NULL || row_start == NULL || marker == NULL || slot == NULL
        || out_p == NULL)
        goto out;
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
    /* start[k + 1] now ends body k's pushes, start[k] begins them. The terms, at most four a
     * pair of pushes, in the order the sum takes them. */
    Py_ssize_t room = 0;
    for (Py_ssize_t k = 0; k < n_bodies; k++)
        room += 4 * (start[k + 1] - start[k]) * (start[k + 1] - start[k]);
    if (room > INT32_MAX)
        goto out;
    term_r = malloc((size_t)(room + 1) * sizeof(int32_t));
    term_c = malloc((size_t)(room + 1) * sizeof(int32_t));
    term_v = malloc((size_t)(room + 1) * sizeof(double));
    sorted = malloc((size_t)(room + 1) * sizeof(int32_t));
    if (term_r == NULL || term_c == NULL || term_v == NULL || sorted == NULL)
        goto out;
    Py_ssize_t terms = 0;
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
                    if (pressing >= 0) {
                        term_r[terms] = (int32_t)row;
                        term_c[terms] = (int32_t)pressing;
                        term_v[terms++] = along_n + slide[j] * along_t;
                    }
                    if (sticking >= 0) {
                        term_r[terms] = (int32_t)row;
                        term_c[terms] = (int32_t)sticking;
                        term_v[terms++] = along_t;
                    }
                }
            }
        }
    }
    /* The terms by row (a stable counting sort), then each row's repeats summed in their order. */
    for (Py_ssize_t q = 0; q < terms; q++)
        row_start[term_r[q] + 2]++;
    for (Py_ssize_t r = 0; r < m; r++)
        row_start[r + 2] += row_start[r + 1];
    for (Py_ssize_t q = 0; q < terms; q++)
        sorted[row_start[term_r[q] + 1]++] = (int32_t)q;
    for (Py_ssize_t c = 0; c < m; c++)
        marker[c] = -1;
    out_p[0] = 0;
    for (Py_ssize_t r = 0; r < m; r++) { /* row_start[r] .. row_start[r + 1]: row r's terms */
        for (int32_t q = row_start[r]; q < row_start[r + 1]; q++) {
            int32_t c = term_c[sorted[q]];
            if (marker[c] != (int32_t)r) {
                marker[c] = (int32_t)r;
                nnz++;
            }
        }
        out_p[r + 1] = (int32_t)nnz;
    }
    out_c = malloc((size_t)(nnz + 1) * sizeof(int32_t));
    out_v = malloc((size_t)(nnz + 1) * sizeof(double));
    if (out_c == NULL || out_v == NULL)
        goto out;
    for (Py_ssize_t c = 0; c < m; c++)
        marker[c] = -1;
    for (Py_ssize_t r = 0; r < m; r++) {
        int32_t at = out_p[r];
        for (int32_t q = row_start[r]; q < row_start[r + 1]; q++) {
            int32_t c = term_c[sorted[q]];
            if (marker[c] != (int32_t)r) { /* a new column: starts at 0.0, as a zeroed array does */
                marker[c] = (int32_t)r;
                slot[c] = at;
                out_c[at] = c;
                out_v[at++] = 0.0;
            }
            out_v[slot[c]] += term_v[sorted[q]];
        }
    }
    out_of_memory = 0;
out:
    Py_END_ALLOW_THREADS
    if (out_of_memory)
        PyErr_NoMemory();
    else
        result = Py_BuildValue("(y#y#y#)", (const char *)out_p, (Py_ssize_t)((m + 1) * sizeof(int32_t)),
                               (const char *)out_c, (Py_ssize_t)(nnz * sizeof(int32_t)), (const char *)out_v,
                               (Py_ssize_t)(nnz * sizeof(double)));
done:
    free(start);
    free(push);
    free(owner);
    free(term_r);
    free(term_c);
    free(term_v);
    free(sorted);
    free(row_start);
    free(marker);
    free(slot);
    free(out_p);
    free(out_c);
    free(out_v);
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
    int32_t *cp = NULL, *ci = NULL, *gp = NULL, *gi = NULL, *order = NULL, *inverse = NULL;
    int32_t *up = NULL, *ui = NULL;
    double *cx = NULL, *gx = NULL, *ux = NULL, *work = NULL;
    spchol_factor_t factor = {0, NULL, NULL, NULL};
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
    int status = -1;
    Py_BEGIN_ALLOW_THREADS
    {
        /* S by columns too (CSC: cp, ci, cx), then G = S S^T. */
        cp = calloc((size_t)(m + 2), sizeof(int32_t));
        ci = malloc((size_t)(nnz + 1) * sizeof(int32_t));
        cx = malloc((size_t)(nnz + 1) * sizeof(double));
        work = malloc((size_t)(4 * m + 1) * sizeof(double));
        if (cp == NULL || ci == NULL || cx == NULL || work == NULL)
            goto out;
        spchol_transpose((int32_t)m, (int32_t)m, sp, si, sx, cp, ci, cx);
        double trace;
        if (spchol_gram((int32_t)m, sp, si, sx, cp, ci, cx, &gp, &gi, &gx, &trace) != 0)
            goto out;
        const int32_t at = gp[m];
        double scale = trace / (double)m;
        if (!(scale > 0)) { /* S = 0: every x solves it, 0 the least */
            memset(x, 0, (size_t)m * sizeof(double));
            status = 0;
            goto out;
        }
        order = malloc((size_t)(m + 1) * sizeof(int32_t));
        inverse = malloc((size_t)(m + 1) * sizeof(int32_t));
        up = malloc((size_t)(m + 1) * sizeof(int32_t));
        ui = malloc((size_t)(at + 1) * sizeof(int32_t));
        ux = malloc((size_t)(at + 1) * sizeof(double));
        if (order == NULL || inverse == NULL || up == NULL || ui == NULL || ux == NULL
            || spchol_rcm((int32_t)m, gp, gi, order) != 0
            || spchol_permute_upper((int32_t)m, gp, gi, gx, order, inverse, up, ui, ux) != 0)
            goto out;
        int factored = spchol_factor((int32_t)m, up, ui, ux, ridge * scale, 0.0, &factor);
        if (factored != 0) {
            status = factored > 0 ? 1 : -1;
            goto out;
        }
        /* y = G^-1 b, refined against S S^T (not the ridged G); y is kept in the new order. */
        double *y = work, *r = work + m, *u = work + 2 * m, *v = work + 3 * m;
        for (Py_ssize_t k = 0; k < m; k++)
            y[inverse[k]] = rhs[k];
        spchol_solve(&factor, y);
        for (int round = 0; round < refinements; round++) {
            for (Py_ssize_t c = 0; c < m; c++) { /* u = S^T y */
                double s_ = 0.0;
                for (int32_t q = cp[c]; q < cp[c + 1]; q++)
                    s_ += cx[q] * y[inverse[ci[q]]];
                u[c] = s_;
            }
            for (Py_ssize_t i = 0; i < m; i++) { /* r = b - S u, in the new order */
                double s_ = 0.0;
                for (int32_t p = sp[i]; p < sp[i + 1]; p++)
                    s_ += sx[p] * u[si[p]];
                r[inverse[i]] = rhs[i] - s_;
            }
            spchol_solve(&factor, r);
            for (Py_ssize_t k = 0; k < m; k++)
                y[k] += r[k];
        }
        for (Py_ssize_t c = 0; c < m; c++) { /* x = S^T y */
            double s_ = 0.0;
            for (int32_t q = cp[c]; q < cp[c + 1]; q++)
                s_ += cx[q] * y[inverse[ci[q]]];
            x[c] = s_;
        }
        /* The answer's test: |S^T (S x - b)| against |S^T b|. */
        for (Py_ssize_t i = 0; i < m; i++) {
            double s_ = 0.0;
            for (int32_t p = sp[i]; p < sp[i + 1]; p++)
                s_ += sx[p] * x[si[p]];
            v[i] = s_ - rhs[i];
        }
        double gradient = 0.0, reach = 0.0;
        for (Py_ssize_t c = 0; c < m; c++) {
            double g_ = 0.0, h_ = 0.0;
            for (int32_t q = cp[c]; q < cp[c + 1]; q++) {
                g_ += cx[q] * v[ci[q]];
                h_ += cx[q] * rhs[ci[q]];
            }
            gradient += g_ * g_;
            reach += h_ * h_;
        }
        status = sqrt(gradient) <= optimality * sqrt(reach) ? 0 : 2;
    }
out:
    Py_END_ALLOW_THREADS
    if (status < 0)
        PyErr_NoMemory();
    else
        result = PyLong_FromLong(status);
done:
    spchol_free(&factor);
    free(cp), free(ci), free(cx), free(gp), free(gi), free(gx);
    free(order), free(inverse), free(up), free(ui), free(ux), free(work);
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
