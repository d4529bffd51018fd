/* Compiled core of deepcontact.transfer: SPH stencil weights, P2G splat, SPH G2P gather.
 *
 * deepcontact/transfer.py owns the geometry, validation and reports; these
 * three loops are the part whose cost was mostly NumPy's per-call overhead
 * (about 30 calls per step on a few hundred particles), and whose NumPy
 * temporaries ORT's inference had pushed out of cache by the next step.
 * Here one call does each, over plain C arrays, in one pass.
 *
 * Layout: stencil entries are particle-major, (M, S) -- particle p's S
 * entries are contiguous, so the entries of particles [a, b) are the rows
 * a..b of the arrays (a TransferPlan of the contact points is a view).
 * Sums are accumulated in float64 and rounded to float32 once, at the end,
 * as the NumPy implementation did.
 *
 * Arguments are buffers (NumPy arrays, C-contiguous) checked only for their
 * sizes; dtypes are the caller's job (transfer.py creates every array it
 * passes). Every node index is checked against the grid before it is used,
 * so a wrong index raises IndexError instead of writing out of bounds.
 *
 * The GIL is held throughout: the calls are short, and the float64 scratch
 * buffers below are shared.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 * Compiled with -ffp-contract=off so that a*b+c is never fused: the
 * weights are then the same as NumPy's, operation for operation.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

enum { KERNEL_POLY6 = 0, KERNEL_SPIKY = 1, KERNEL_GAUSSIAN = 2 };

/* Grown as needed, never shrunk: a grid's worth of float64. */
static double *scratch = NULL;
static Py_ssize_t scratch_len = 0;

static double *scratch_zeroed(Py_ssize_t n)
{
    if (n > scratch_len) {
        double *p = PyMem_Realloc(scratch, (size_t)n * sizeof(double));
        if (p == NULL) {
            PyErr_NoMemory();
            return NULL;
        }
        scratch = p;
        scratch_len = n;
    }
    memset(scratch, 0, (size_t)n * sizeof(double));
    return scratch;
}

static int check_size(const Py_buffer *b, Py_ssize_t items, Py_ssize_t itemsize, const char *name)
{
    if (b->len != items * itemsize) {
        PyErr_Format(PyExc_ValueError, "_transfer: %s holds %zd bytes, expected %zd", name, b->len,
                     items * itemsize);
        return -1;
    }
    return 0;
}

/* Kernel shape as a function of m = 1 - (r/h)^2, up to the kernel's constant
 * factor (it cancels in the normalization); 0 out of range (m <= 0), and the
 * Gaussian is truncated there:
 *   poly6     m^3                          (h^2 - r^2)^3
 *   spiky     (1 - sqrt(1 - m))^3          (h - r)^3
 *   gaussian  exp(-4.5 (1 - m))            exp(-r^2 / (2 sigma^2)), sigma = h/3 */
static inline double shape_of_m(double m, int kernel)
{
    double w;
    switch (kernel) {
    case KERNEL_SPIKY: {
        double q2 = 1.0 - m;
        double q = sqrt(q2 > 0.0 ? q2 : 0.0);
        double d = 1.0 - q;
        d = d > 0.0 ? d : 0.0;
        w = d * d;
        return w * d;
    }
    case KERNEL_GAUSSIAN:
        if (m < 0.0)
            return 0.0;
        return exp((m - 1.0) * 4.5);
    default: /* poly6 */
        m = m > 0.0 ? m : 0.0;
        w = m * m;
        return w * m;
    }
}

/* shape(m, kernel, out): out[i] = shape_of_m(m[i]); m, out float64 of the same size.
 * The kernels' one implementation, for transfer.kernel_shape as for the weights below. */
static PyObject *shape(PyObject *self, PyObject *args)
{
    Py_buffer m, out;
    int kernel;
    if (!PyArg_ParseTuple(args, "y*iw*", &m, &kernel, &out))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t n = m.len / (Py_ssize_t)sizeof(double);
    if (check_size(&m, n, sizeof(double), "m") || check_size(&out, n, sizeof(double), "out"))
        goto done;
    const double *src = m.buf;
    double *dst = out.buf;
    for (Py_ssize_t i = 0; i < n; i++)
        dst[i] = shape_of_m(src[i], kernel);
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&m);
    PyBuffer_Release(&out);
    return result;
}

/* entries(pos, world_offset, o_h, flat_off, params, kernel, bounds, nodes, weights, lost, divisor) -> outside
 *
 * pos (M, 2) float64 m; world_offset None or (M,) int32 added to the node
 * indices (world b of a batch starts at b * cells); o_h (2, K) float64
 * window offsets in units of h, x then y; flat_off (K*K,) int32, entry
 * (ky, kx) at ky*K + kx; params (origin_x, origin_y, inv_dx, scale, lo_x,
 * lo_y, hi_x, hi_y, nx); kernel POLY6, SPIKY or GAUSSIAN; bounds (x_min,
 * y_min, x_max, y_max) m, the region where particles are accepted.  Writes
 * nodes (M, S) int32, weights (M, S) float64 (unnormalized, 0 out of
 * range), lost (M,) bool (no node in range) and divisor (M,) float64 (the
 * weight total; 1 where lost).  Returns how many particles are not finite
 * or outside the bounds.
 */
static PyObject *entries(PyObject *self, PyObject *args)
{
    Py_buffer pos, o_h, flat_off, nodes, weights, lost, divisor, woff = {0};
    PyObject *woff_obj;
    double ox, oy, inv_dx, scale, lo_x, lo_y, hi_x, hi_y;
    int nx, kernel;
    double in_lo_x, in_lo_y, in_hi_x, in_hi_y;
    if (!PyArg_ParseTuple(args, "y*Oy*y*(ddddddddi)i(dddd)w*w*w*w*", &pos, &woff_obj, &o_h, &flat_off, &ox, &oy,
                          &inv_dx, &scale, &lo_x, &lo_y, &hi_x, &hi_y, &nx, &kernel, &in_lo_x, &in_lo_y, &in_hi_x,
                          &in_hi_y, &nodes, &weights, &lost, &divisor))
        return NULL;
    PyObject *result = NULL;
    int has_woff = woff_obj != Py_None;
    if (has_woff && PyObject_GetBuffer(woff_obj, &woff, PyBUF_SIMPLE) < 0)
        goto done;
    const Py_ssize_t m = pos.len / (2 * (Py_ssize_t)sizeof(double));
    const Py_ssize_t k = o_h.len / (2 * (Py_ssize_t)sizeof(double));
    const Py_ssize_t s = k * k;
    if (check_size(&pos, 2 * m, sizeof(double), "pos") || check_size(&flat_off, s, sizeof(int32_t), "flat_off") ||
        check_size(&nodes, m * s, sizeof(int32_t), "nodes") ||
        check_size(&weights, m * s, sizeof(double), "weights") || check_size(&lost, m, 1, "lost") ||
        check_size(&divisor, m, sizeof(double), "divisor") ||
        (has_woff && check_size(&woff, m, sizeof(int32_t), "world_offset")))
        goto done;
    if (k > 64) {
        PyErr_SetString(PyExc_ValueError, "_transfer: stencil wider than 64 nodes");
        goto done;
    }
    const double *p = pos.buf, *ohx = o_h.buf, *ohy = ohx + k;
    const int32_t *off = flat_off.buf, *wo = has_woff ? woff.buf : NULL;
    int32_t *out_nodes = nodes.buf;
    double *out_w = weights.buf, *out_div = divisor.buf;
    uint8_t *out_lost = lost.buf;
    double tx[64], ty[64];
    Py_ssize_t outside = 0;
    for (Py_ssize_t i = 0; i < m; i++) {
        /* Not finite or beyond the accepted region: counted, so that the caller
         * can take its careful path; the weights stay finite (0 for NaN). */
        outside += !(p[2 * i] >= in_lo_x && p[2 * i] <= in_hi_x && p[2 * i + 1] >= in_lo_y &&
                     p[2 * i + 1] <= in_hi_y);
        /* Node units, anchored at the nearest node moved inwards so that the
         * window stays on the grid; then the offset from the anchor in units of h. */
        double ux = (p[2 * i] - ox) * inv_dx, uy = (p[2 * i + 1] - oy) * inv_dx;
        double ax = nearbyint(ux), ay = nearbyint(uy);
        ax = ax > lo_x ? ax : lo_x;
        ax = ax < hi_x ? ax : hi_x;
        ay = ay > lo_y ? ay : lo_y;
        ay = ay < hi_y ? ay : hi_y;
        ux = (ux - ax) * scale;
        uy = (uy - ay) * scale;
        /* t = 1/2 - (distance along the axis / h)^2, so t_y + t_x = 1 - (r/h)^2 = m. */
        for (Py_ssize_t j = 0; j < k; j++) {
            double d = ohx[j] - ux;
            tx[j] = 0.5 - d * d;
            d = ohy[j] - uy;
            ty[j] = 0.5 - d * d;
        }
        int32_t base = (int32_t)ax + (int32_t)ay * nx + (wo ? wo[i] : 0);
        int32_t *n_i = out_nodes + i * s;
        double *w_i = out_w + i * s;
        double total = 0.0;
        for (Py_ssize_t jy = 0; jy < k; jy++) {
            for (Py_ssize_t jx = 0; jx < k; jx++) {
                Py_ssize_t e = jy * k + jx;
                double w = shape_of_m(ty[jy] + tx[jx], kernel);
                n_i[e] = base + off[e];
                w_i[e] = w;
                total += w;
            }
        }
        out_lost[i] = total <= 0.0;
        out_div[i] = total <= 0.0 ? total + 1.0 : total; /* lost: all weights 0, any divisor will do */
    }
    result = PyLong_FromSsize_t(outside);
done:
    if (has_woff && woff.obj)
        PyBuffer_Release(&woff);
    PyBuffer_Release(&pos);
    PyBuffer_Release(&o_h);
    PyBuffer_Release(&flat_off);
    PyBuffer_Release(&nodes);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&lost);
    PyBuffer_Release(&divisor);
    return result;
}

/* -1 with IndexError if some node index is not in [0, rows). */
static int check_nodes(const int32_t *n, Py_ssize_t count, Py_ssize_t rows)
{
    uint32_t bad = 0; /* no branch in the loop, so that it vectorizes */
    for (Py_ssize_t e = 0; e < count; e++)
        bad |= (uint32_t)n[e] >= (uint32_t)rows;
    if (!bad)
        return 0;
    for (Py_ssize_t e = 0; e < count; e++)
        if ((uint32_t)n[e] >= (uint32_t)rows) {
            PyErr_Format(PyExc_IndexError, "_transfer: node index %d outside the grid's %zd nodes", (int)n[e], rows);
            break;
        }
    return -1;
}

/* Channels are processed in blocks of up to BLOCK, so that a particle's
 * values (splat) or sums (gather) sit in a small local array. */
#define BLOCK 16

/* splat(nodes, weights, divisor, values, rows, out) -> finite
 *
 * P2G: out[node, c] = sum over entries (p, node) of weights[p, s] *
 * values[p, c] / divisor[p].  nodes, weights (M, S); divisor (M,) float64;
 * values (M, C) float64; out (rows, C) float32, overwritten.  Returns
 * whether every value was finite (if not, out holds garbage).
 */
static PyObject *splat(PyObject *self, PyObject *args)
{
    Py_buffer nodes, weights, divisor, values, out;
    Py_ssize_t rows;
    if (!PyArg_ParseTuple(args, "y*y*y*y*nw*", &nodes, &weights, &divisor, &values, &rows, &out))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t m = divisor.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t s = m ? weights.len / ((Py_ssize_t)sizeof(double) * m) : 0;
    const Py_ssize_t c = rows ? out.len / ((Py_ssize_t)sizeof(float) * rows) : 0;
    if (check_size(&weights, m * s, sizeof(double), "weights") || check_size(&nodes, m * s, sizeof(int32_t), "nodes") ||
        check_size(&values, m * c, sizeof(double), "values") || check_size(&out, rows * c, sizeof(float), "out"))
        goto done;
    const int32_t *n = nodes.buf;
    if (check_nodes(n, m * s, rows))
        goto done;
    double *acc = scratch_zeroed(rows * c);
    if (acc == NULL)
        goto done;
    const double *w = weights.buf, *div = divisor.buf, *v = values.buf;
    double vs[BLOCK];
    int finite = 1; /* NaN fails every comparison */
    for (Py_ssize_t i = 0; i < m * c; i++)
        finite &= fabs(v[i]) <= DBL_MAX;
    for (Py_ssize_t i = 0; i < m; i++) {
        for (Py_ssize_t j0 = 0; j0 < c; j0 += BLOCK) {
            const Py_ssize_t cb = c - j0 < BLOCK ? c - j0 : BLOCK;
            for (Py_ssize_t j = 0; j < cb; j++)
                vs[j] = v[i * c + j0 + j] / div[i];
            /* Entries out of range have weight 0 and add +0: cheaper than a branch the CPU cannot predict. */
            for (Py_ssize_t e = i * s; e < (i + 1) * s; e++) {
                double *a = acc + (Py_ssize_t)n[e] * c + j0;
                const double we = w[e];
                for (Py_ssize_t j = 0; j < cb; j++)
                    a[j] += we * vs[j];
            }
        }
    }
    float *o = out.buf;
    for (Py_ssize_t j = 0; j < rows * c; j++)
        o[j] = (float)acc[j];
    result = PyBool_FromLong(finite);
done:
    PyBuffer_Release(&nodes);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&divisor);
    PyBuffer_Release(&values);
    PyBuffer_Release(&out);
    return result;
}

/* gather(nodes, weights, grid, grid_is_float64, out, node_w, grid_copy) -> finite
 *
 * SPH G2P (thesis Algorithm 2): each node's weights are normalized to sum to
 * one over the particles in its range, then out[p, c] = sum over p's
 * entries of normalized weight * grid[node, c].  nodes, weights (M, S);
 * grid (rows, C) float32 or float64; out (M, C) float32, overwritten.
 * node_w (rows,) float64 receives each node's weight total (0: no particle
 * in range) and grid_copy (the grid's size) a copy of the grid: what the
 * report needs to say what was lost, if anyone asks.  Returns False (and
 * does nothing else) if the grid holds a value that is not finite.
 */
static PyObject *gather(PyObject *self, PyObject *args)
{
    Py_buffer nodes, weights, grid, out, node_w_buf, grid_copy;
    int grid_f64;
    if (!PyArg_ParseTuple(args, "y*y*y*pw*w*w*", &nodes, &weights, &grid, &grid_f64, &out, &node_w_buf, &grid_copy))
        return NULL;
    PyObject *result = NULL;
    double *wn = NULL;
    const Py_ssize_t gsize = grid_f64 ? sizeof(double) : sizeof(float);
    const Py_ssize_t rows = node_w_buf.len / (Py_ssize_t)sizeof(double);
    const Py_ssize_t c = rows ? grid.len / (gsize * rows) : 0;
    const Py_ssize_t m = c ? out.len / ((Py_ssize_t)sizeof(float) * c) : 0;
    const Py_ssize_t s = m ? weights.len / ((Py_ssize_t)sizeof(double) * m) : 0;
    if (check_size(&grid, rows * c, gsize, "grid") || check_size(&grid_copy, rows * c, gsize, "grid_copy") ||
        check_size(&out, m * c, sizeof(float), "out") || check_size(&weights, m * s, sizeof(double), "weights") ||
        check_size(&nodes, m * s, sizeof(int32_t), "nodes"))
        goto done;
    const int32_t *n = nodes.buf;
    if (check_nodes(n, m * s, rows))
        goto done;
    {
        int finite = 1; /* NaN fails every comparison */
        if (grid_f64)
            for (Py_ssize_t i = 0; i < rows * c; i++)
                finite &= fabs(((const double *)grid.buf)[i]) <= DBL_MAX;
        else
            for (Py_ssize_t i = 0; i < rows * c; i++)
                finite &= fabsf(((const float *)grid.buf)[i]) <= FLT_MAX;
        if (!finite) {
            result = Py_False;
            Py_INCREF(result);
            goto done;
        }
    }
    memcpy(grid_copy.buf, grid.buf, (size_t)grid.len);
    wn = PyMem_Malloc((size_t)(m * s > 0 ? m * s : 1) * sizeof(double));
    if (wn == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    double *node_w = node_w_buf.buf;
    memset(node_w, 0, (size_t)rows * sizeof(double));
    const double *w = weights.buf;
    for (Py_ssize_t e = 0; e < m * s; e++)
        node_w[n[e]] += w[e];
    /* Each weight over its node's total.  A node nobody reaches has total 0,
     * and so have all its entries' weights: 1 added to their divisor keeps
     * them 0.  Divisors first, then one division loop the compiler vectorizes. */
    for (Py_ssize_t e = 0; e < m * s; e++)
        wn[e] = node_w[n[e]] + (w[e] == 0.0);
    for (Py_ssize_t e = 0; e < m * s; e++)
        wn[e] = w[e] / wn[e];
    /* Four channels at a time, each in its own accumulator: the sums over a
     * particle's entries are dependency chains, and four run side by side. */
    const float *g32 = grid.buf;
    const double *g64 = grid.buf;
    float *o = out.buf;
    for (Py_ssize_t i = 0; i < m; i++) {
        const int32_t *n_i = n + i * s;
        const double *wn_i = wn + i * s;
        for (Py_ssize_t j0 = 0; j0 < c; j0 += 4) {
            const Py_ssize_t cb = c - j0 < 4 ? c - j0 : 4;
            double acc[4] = {0.0, 0.0, 0.0, 0.0};
            if (grid_f64)
                for (Py_ssize_t e = 0; e < s; e++) {
                    const double *g = g64 + (Py_ssize_t)n_i[e] * c + j0;
                    for (Py_ssize_t j = 0; j < cb; j++)
                        acc[j] += wn_i[e] * g[j];
                }
            else if (cb == 2) /* the impulse grids: (normal, tangent) */
                for (Py_ssize_t e = 0; e < s; e++) {
                    const float *g = g32 + (Py_ssize_t)n_i[e] * c + j0;
                    acc[0] += wn_i[e] * (double)g[0];
                    acc[1] += wn_i[e] * (double)g[1];
                }
            else
                for (Py_ssize_t e = 0; e < s; e++) {
                    const float *g = g32 + (Py_ssize_t)n_i[e] * c + j0;
                    for (Py_ssize_t j = 0; j < cb; j++)
                        acc[j] += wn_i[e] * (double)g[j];
                }
            for (Py_ssize_t j = 0; j < cb; j++)
                o[i * c + j0 + j] = (float)acc[j];
        }
    }
    result = Py_True;
    Py_INCREF(result);
done:
    PyMem_Free(wn);
    PyBuffer_Release(&nodes);
    PyBuffer_Release(&weights);
    PyBuffer_Release(&grid);
    PyBuffer_Release(&out);
    PyBuffer_Release(&node_w_buf);
    PyBuffer_Release(&grid_copy);
    return result;
}

static PyMethodDef methods[] = {
    {"shape", shape, METH_VARARGS, "Kernel shape as a function of m = 1 - (r/h)^2 (see the C source)."},
    {"entries", entries, METH_VARARGS, "Stencil entries of particles: nodes, weights, lost, divisor (see the C source)."},
    {"splat", splat, METH_VARARGS, "P2G of per-particle values through stencil entries (see the C source)."},
    {"gather", gather, METH_VARARGS, "SPH G2P of grid values through stencil entries (see the C source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._transfer",
    "Compiled core of deepcontact.transfer (stencil weights, P2G splat, SPH G2P gather).", -1, methods,
};

PyMODINIT_FUNC PyInit__transfer(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL)
        return NULL;
    if (PyModule_AddIntConstant(mod, "POLY6", KERNEL_POLY6) || PyModule_AddIntConstant(mod, "SPIKY", KERNEL_SPIKY) ||
        PyModule_AddIntConstant(mod, "GAUSSIAN", KERNEL_GAUSSIAN)) {
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
