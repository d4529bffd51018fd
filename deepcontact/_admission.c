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

/* nearest_admissible's rounds (deepcontact.admission documents the problem): ADMM between
 * the affine set J^T x = J^T c (the bodies' motion kept) and the friction cones, each round
 *     x = same_motion((c + rho (z - s)) / (1 + rho)),  z' = cones(x + s),  s += x - z',
 * stopping once |x - z'| and |z' - z| are under `tolerance` at every entry. same_motion(y)
 * is y - J (G^-1 (J^T (y - c))), G = J^T J plus its ridge, factorized once per step
 * (envelope_cholesky below; SuperLU's form, which it replaced): Pr G Pc = L U (L unit lower,
 * U upper, CSC). In NumPy each round was about twenty
 * calls on a few hundred numbers, about 0.1 ms; here it is a few sparse passes.
 *
 * Arguments: jt as CSR (indptr int32 (R + 1,), indices int32, data float64: R = 3 D rows,
 * 2 P columns), L and U as CSC (int32, int32, float64; R x R), perm_r and perm_c int32
 * (R,), c float64 (2 P,), mu and keep float64 (P,), rho, iterations, tolerance, until
 * (seconds of CLOCK_MONOTONIC, Python's time.monotonic(), after which no round starts; 0:
 * none; read every UNTIL_EVERY rounds) and z float64 (2 P,) out. R = 0: no dynamic body,
 * same_motion is the identity. Returns the rounds run. */
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
    Py_buffer b[16];
    Py_ssize_t rows;
    double rho, tolerance, until;
    long iterations;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*ny*y*y*y*y*y*y*y*y*y*y*dlddw*", &b[0], &b[1], &b[2], &rows, &b[3], &b[4],
                          &b[5], &b[6], &b[7], &b[8], &b[9], &b[10], &b[11], &b[12], &b[13], &rho, &iterations,
                          &tolerance, &until, &b[14]))
        return NULL;
    const int n_bufs = 15;
    PyObject *result = NULL;
    double *work = NULL;
    const Py_ssize_t n2 = b[11].len / (Py_ssize_t)sizeof(double), n_points = n2 / 2;
    if (b[11].len != n2 * (Py_ssize_t)sizeof(double) || n2 % 2 || b[12].len != n_points * (Py_ssize_t)sizeof(double)
        || b[13].len != b[12].len || b[14].len != b[11].len || rows < 0
        || !valid_sparse(&b[0], &b[1], &b[2], rows, n2)
        || (rows && (!valid_sparse(&b[3], &b[4], &b[5], rows, rows) || !valid_sparse(&b[6], &b[7], &b[8], rows, rows)
                     || b[9].len != rows * (Py_ssize_t)sizeof(int32_t) || b[10].len != b[9].len))) {
        PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *jp = b[0].buf, *ji = b[1].buf, *lp = b[3].buf, *li = b[4].buf, *up = b[6].buf, *ui = b[7].buf;
    const int32_t *perm_r = b[9].buf, *perm_c = b[10].buf;
    const double *jd = b[2].buf, *ld = b[5].buf, *ud = b[8].buf, *c = b[11].buf, *mu = b[12].buf, *keep = b[13].buf;
    double *z = b[14].buf;
    for (Py_ssize_t k = 0; k < rows; k++)
        if (perm_r[k] < 0 || perm_r[k] >= rows || perm_c[k] < 0 || perm_c[k] >= rows) {
            PyErr_SetString(PyExc_ValueError, "_admission.admission_rounds: a permutation out of range");
            goto done;
        }
    work = PyMem_Calloc((size_t)(4 * n2 + 3 * rows + 1), sizeof(double));
    if (work == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *x = work, *s = x + n2, *y = s + n2, *zp = y + n2, *g = zp + n2, *h = g + rows, *inv_diag = h + rows;
    long round = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < rows; j++) { /* U's diagonal, found once rather than every round */
        double diag = 0.0;
        for (int32_t k = up[j]; k < up[j + 1]; k++)
            if (ui[k] == j)
                diag = ud[k];
        inv_diag[j] = diag != 0.0 ? 1.0 / diag : 0.0;
    }
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
            for (Py_ssize_t r = 0; r < rows; r++) { /* g = Pr (J^T (y - c)) */
                double acc = 0.0;
                for (int32_t k = jp[r]; k < jp[r + 1]; k++)
                    acc += jd[k] * (y[ji[k]] - c[ji[k]]);
                g[perm_r[r]] = acc;
            }
            for (Py_ssize_t j = 0; j < rows; j++) /* L, unit lower: forward */
                for (int32_t k = lp[j]; k < lp[j + 1]; k++)
                    if (li[k] > j)
                        g[li[k]] -= ld[k] * g[j];
            for (Py_ssize_t j = rows - 1; j >= 0; j--) { /* U, upper: backward */
                g[j] *= inv_diag[j];
                for (int32_t k = up[j]; k < up[j + 1]; k++)
                    if (ui[k] < j)
                        g[ui[k]] -= ud[k] * g[j];
            }
            for (Py_ssize_t r = 0; r < rows; r++) /* h = Pc g: G^-1 (J^T (y - c)) */
                h[r] = g[perm_c[r]];
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

/* nearest_admissible's factorization of G = J^T J + ridge I (admission.admission_factors) as
 * a Cholesky factorization in an envelope: rows and columns in the order `order` (a reverse
 * Cuthill-McKee order of the bodies, computed by the caller), each row of the factor C stored
 * from its first nonzero to the diagonal (a row's first nonzero is where G's is: the fill of a
 * Cholesky factorization stays inside G's envelope). Written out as admission_rounds takes
 * SuperLU's factors: Pr G Pc = L U with L unit lower and U upper, both CSC, perm_r = perm_c =
 * the inverse of `order`; here L = C D^-1 (D: C's diagonal) and U = D C^T, so that a round's
 * two triangular solves are unchanged. SciPy's SuperLU took about 0.8 ms at the thesis world's
 * largest steps (300 rows), most of it in building and converting sparse matrices.
 *
 * Arguments: J^T's CSR arrays jp int32 (rows + 1,), ji int32, jd float64; rows; cols (J^T's
 * columns, 2 P); order int32 (rows,), a permutation; ridge (relative to G's largest diagonal
 * entry); out: lp, li, ld, up, ui, ud (int32 (rows + 1,), int32 and float64 of at least
 * rows (rows + 1) / 2 each) and inverse int32 (rows,). Returns the number of entries of each
 * factor. */
static PyObject *envelope_cholesky(PyObject *self, PyObject *args)
{
    Py_buffer b[11];
    Py_ssize_t rows, cols;
    double ridge;
    memset(b, 0, sizeof b);
    if (!PyArg_ParseTuple(args, "y*y*y*nny*dw*w*w*w*w*w*w*", &b[0], &b[1], &b[2], &rows, &cols, &b[3], &ridge, &b[4],
                          &b[5], &b[6], &b[7], &b[8], &b[9], &b[10]))
        return NULL;
    const int n_bufs = 11;
    PyObject *result = NULL;
    double *env = NULL, *col_vals = NULL;
    Py_ssize_t *offset = NULL;
    int32_t *first = NULL, *count = NULL, *col_rows = NULL;
    const Py_ssize_t room = rows * (rows + 1) / 2, i32 = (Py_ssize_t)sizeof(int32_t), f64 = (Py_ssize_t)sizeof(double);
    if (rows < 0 || cols < 0 || !valid_sparse(&b[0], &b[1], &b[2], rows, cols) || b[3].len != rows * i32
        || b[4].len != (rows + 1) * i32 || b[5].len < room * i32 || b[6].len < room * f64
        || b[7].len != (rows + 1) * i32 || b[8].len < room * i32 || b[9].len < room * f64 || b[10].len != rows * i32) {
        PyErr_SetString(PyExc_ValueError, "_admission.envelope_cholesky: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *jp = b[0].buf, *ji = b[1].buf, *order = b[3].buf;
    const double *jd = b[2].buf;
    int32_t *lp = b[4].buf, *li = b[5].buf, *up = b[7].buf, *ui = b[8].buf, *inverse = b[10].buf;
    double *ld = b[6].buf, *ud = b[9].buf;
    for (Py_ssize_t k = 0; k < rows; k++)
        inverse[k] = -1;
    for (Py_ssize_t k = 0; k < rows; k++) {
        if (order[k] < 0 || order[k] >= rows || inverse[order[k]] >= 0) {
            PyErr_SetString(PyExc_ValueError, "_admission.envelope_cholesky: order is not a permutation");
            goto done;
        }
        inverse[order[k]] = (int32_t)k;
    }
    const Py_ssize_t nnz = rows ? jp[rows] : 0;
    first = PyMem_Malloc((size_t)(rows + 1) * sizeof(int32_t));
    offset = PyMem_Malloc((size_t)(rows + 1) * sizeof(Py_ssize_t));
    count = PyMem_Calloc((size_t)(cols + 1), sizeof(int32_t));
    col_rows = PyMem_Malloc((size_t)(nnz + 1) * sizeof(int32_t));
    col_vals = PyMem_Malloc((size_t)(nnz + 1) * sizeof(double));
    if (first == NULL || offset == NULL || count == NULL || col_rows == NULL || col_vals == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    /* J^T by columns (each point direction's pushes on its bodies), rows in the new order. */
    for (Py_ssize_t k = 0; k < nnz; k++)
        count[ji[k] + 1]++;
    for (Py_ssize_t c = 0; c < cols; c++)
        count[c + 1] += count[c];
    for (Py_ssize_t r = 0; r < rows; r++)
        for (int32_t k = jp[r]; k < jp[r + 1]; k++) {
            int32_t at = count[ji[k]]++;
            col_rows[at] = inverse[r];
            col_vals[at] = jd[k];
        }
    /* count[c] is now column c's end, and its start the column before's. Each row's envelope
     * starts at the least row it shares a column with. */
    for (Py_ssize_t i = 0; i < rows; i++)
        first[i] = (int32_t)i;
    for (Py_ssize_t c = 0, start = 0; c < cols; start = count[c], c++) {
        int32_t least = (int32_t)rows;
        for (int32_t p = (int32_t)start; p < count[c]; p++)
            if (col_rows[p] < least)
                least = col_rows[p];
        for (int32_t p = (int32_t)start; p < count[c]; p++)
            if (least < first[col_rows[p]])
                first[col_rows[p]] = least;
    }
    offset[0] = 0;
    for (Py_ssize_t i = 0; i < rows; i++) /* row i holds columns first[i]..i from offset[i] - first[i] */
        offset[i + 1] = offset[i] + (i - first[i] + 1);
    env = PyMem_Calloc((size_t)(offset[rows] + 1), sizeof(double));
    if (env == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    Py_ssize_t entries = 0;
    Py_BEGIN_ALLOW_THREADS
#define AT(i, j) env[offset[i] + (j) - first[i]]
    for (Py_ssize_t c = 0, start = 0; c < cols; start = count[c], c++)
        for (int32_t p = (int32_t)start; p < count[c]; p++)
            for (int32_t q = (int32_t)start; q < count[c]; q++)
                if (col_rows[q] <= col_rows[p])
                    AT(col_rows[p], col_rows[q]) += col_vals[p] * col_vals[q];
    double top = 0.0;
    for (Py_ssize_t i = 0; i < rows; i++)
        if (AT(i, i) > top)
            top = AT(i, i);
    const double added = ridge * (top > 0.0 ? top : 1e-300);
    for (Py_ssize_t i = 0; i < rows; i++) {
        double *row = &AT(i, first[i]) - first[i]; /* row[j] for first[i] <= j <= i */
        row[i] += added;
        for (Py_ssize_t j = first[i]; j < i; j++) {
            const double *other = &AT(j, first[j]) - first[j];
            double acc = row[j];
            for (Py_ssize_t k = first[i] > first[j] ? first[i] : first[j]; k < j; k++)
                acc -= row[k] * other[k];
            row[j] = acc / other[j];
        }
        double diag = row[i];
        for (Py_ssize_t k = first[i]; k < i; k++)
            diag -= row[k] * row[k];
        row[i] = sqrt(diag > added ? diag : added); /* rounding below the ridge: the ridge */
    }
    /* U = D C^T: its column i is row i of C, each entry j times C's diagonal at j. */
    up[0] = 0;
    for (Py_ssize_t i = 0; i < rows; i++) {
        for (Py_ssize_t j = first[i]; j <= i; j++) {
            ui[entries] = (int32_t)j;
            ud[entries++] = AT(j, j) * AT(i, j);
        }
        up[i + 1] = (int32_t)entries;
    }
    /* L = C D^-1: its column j holds the rows i >= j whose envelope reaches back to j. */
    Py_ssize_t at = 0;
    lp[0] = 0;
    for (Py_ssize_t j = 0; j < rows; j++) {
        const double diag = AT(j, j);
        for (Py_ssize_t i = j; i < rows; i++)
            if (first[i] <= j) {
                li[at] = (int32_t)i;
                ld[at++] = i == j ? 1.0 : AT(i, j) / diag;
            }
        lp[j + 1] = (int32_t)at;
    }
#undef AT
    Py_END_ALLOW_THREADS
    result = PyLong_FromSsize_t(entries);
done:
    PyMem_Free(env);
    PyMem_Free(offset);
    PyMem_Free(first);
    PyMem_Free(count);
    PyMem_Free(col_rows);
    PyMem_Free(col_vals);
    for (int k = 0; k < n_bufs; k++)
        if (b[k].obj != NULL || b[k].buf != NULL)
            PyBuffer_Release(&b[k]);
    return result;
}

static PyMethodDef methods[] = {
    {"envelope_cholesky", envelope_cholesky, METH_VARARGS,
     "nearest_admissible's factorization, as admission_rounds takes it (see the C source)."},
    {"admission_rounds", admission_rounds, METH_VARARGS,
     "nearest_admissible's ADMM rounds on a factorized gram (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._admission",
    "Compiled core of deepcontact.admission (the admission rounds and their factorization).", -1, methods,
};

PyMODINIT_FUNC PyInit__admission(void)
{
    return PyModule_Create(&module);
}
