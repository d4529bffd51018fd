/* The admission into the friction cones, compiled (deepcontact.admission documents the
 * problem): ADMM between the affine set J^T x = J^T c (the bodies' motion kept) and the cones,
 * each round
 *     x = same_motion((c + rho (z - s)) / (1 + rho)),  x^ = relax x + (1 - relax) z,
 *     z' = cones(x^ + s),  s += x^ - z',
 * stopping once |x - z'| and |z' - z| are under `tolerance` at every entry, where
 * same_motion(y) = y - J (G^-1 (J^T (y - c))) and G = J^T J plus a ridge, factored once per
 * step by sparse Cholesky in a minimum degree order of the bodies. Shared by
 * deepcontact/_admission.c (admission.nearest_admissible) and deepcontact/_route.c. Every
 * function here runs without the GIL and allocates with malloc.
 */

#ifndef DEEPCONTACT_ADMISSION_KERNELS_H
#define DEEPCONTACT_ADMISSION_KERNELS_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sparse_cholesky.h"

/* The rounds read the clock every this many rounds, against `until`. */
#define UNTIL_EVERY 8

static double monotonic_seconds(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* The nearest impulses inside each point's cone (admission.project_to_cones), times keep (0 at
 * the points held open). v, out (2 P,); mu, keep (P,). */
static void project_cones(const double *v, const double *mu, const double *keep, int64_t n_points, double *out)
{
    for (int64_t i = 0; i < n_points; i++) {
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

/* sum over p in [begin, end) of vals[p] * x[idx[p]], in four running sums: a round's products are
 * short sparse dot products whose one running sum waited on each add in turn. */
static inline double gather_dot(const double *vals, const int32_t *idx, const double *x, int32_t begin, int32_t end)
{
    double a0 = 0.0, a1 = 0.0, a2 = 0.0, a3 = 0.0;
    int32_t p = begin;
    for (; p + 4 <= end; p += 4) {
        a0 += vals[p] * x[idx[p]];
        a1 += vals[p + 1] * x[idx[p + 1]];
        a2 += vals[p + 2] * x[idx[p + 2]];
        a3 += vals[p + 3] * x[idx[p + 3]];
    }
    for (; p < end; p++)
        a0 += vals[p] * x[idx[p]];
    return (a0 + a1) + (a2 + a3);
}

/* A minimum degree order of the dynamic bodies: the graph joins two bodies where a point
 * touches both (G couples their rows there). pa, pb (P,) body indices, checked; row (B,) each
 * body's dynamic row or -1, below n_dyn; order (n_dyn,) out. Returns 0, or -1 (memory). */
static int body_order_min_degree(int64_t n_points, const int64_t *pa, const int64_t *pb, const int32_t *row,
                                 int32_t n_dyn, int32_t *order)
{
    int32_t *start = calloc((size_t)n_dyn + 2, sizeof(int32_t));
    int32_t *fill = calloc((size_t)n_dyn + 1, sizeof(int32_t));
    int32_t *adj = malloc(((size_t)2 * n_points + 1) * sizeof(int32_t));
    int status = -1;
    if (start == NULL || fill == NULL || adj == NULL)
        goto out;
    /* Adjacency lists, a pair once per point that joins them (repeats only make a list longer). */
    for (int64_t i = 0; i < n_points; i++) {
        int32_t u = row[pa[i]], v = row[pb[i]];
        if (u >= 0 && v >= 0 && u != v) {
            start[u + 1]++;
            start[v + 1]++;
        }
    }
    for (int32_t k = 0; k < n_dyn; k++)
        start[k + 1] += start[k];
    for (int64_t i = 0; i < n_points; i++) {
        int32_t u = row[pa[i]], v = row[pb[i]];
        if (u >= 0 && v >= 0 && u != v) {
            adj[start[u] + fill[u]++] = v;
            adj[start[v] + fill[v]++] = u;
        }
    }
    status = spchol_min_degree(n_dyn, start, adj, order);
out:
    free(start), free(fill), free(adj);
    return status;
}

/* G = J^T J summed from J^T's rows (CSR jp, ji, jd: rows x cols), its rows and columns in the
 * order `order` (a permutation, new position -> row; inverse (rows,) out: row -> position),
 * factored: P G P^T = C C^T with `ridge` times G's largest diagonal entry added, a pivot that
 * rounding leaves below that taken as it (G is singular where a body's points cannot push it
 * every way; what the ridge adds there J takes away again). factor out. Returns 0, -1
 * (memory) or 1 (a pivot). */
static int gram_factor(int32_t rows, int32_t cols, const int32_t *jp, const int32_t *ji, const double *jd,
                       const int32_t *order, double ridge, int32_t *inverse, spchol_factor_t *factor)
{
    int32_t *cp = NULL, *ci = NULL, *gp = NULL, *gi = NULL, *up = NULL, *ui = NULL;
    double *cx = NULL, *gx = NULL, *ux = NULL;
    int status = -1;
    factor->n = rows;
    factor->Lp = factor->Li = NULL;
    factor->Lx = NULL;
    const int32_t nnz = rows ? jp[rows] : 0;
    cp = calloc((size_t)cols + 2, sizeof(int32_t));
    ci = malloc(((size_t)nnz + 1) * sizeof(int32_t));
    cx = malloc(((size_t)nnz + 1) * sizeof(double));
    if (cp == NULL || ci == NULL || cx == NULL)
        goto out;
    spchol_transpose(rows, cols, jp, ji, jd, cp, ci, cx);
    double trace;
    if (spchol_gram(rows, jp, ji, jd, cp, ci, cx, &gp, &gi, &gx, &trace) != 0)
        goto out;
    double top = 0.0;
    for (int32_t i = 0; i < rows; i++)
        for (int32_t q = gp[i]; q < gp[i + 1]; q++)
            if (gi[q] == i && gx[q] > top)
                top = gx[q];
    const double added = ridge * (top > 0.0 ? top : 1e-300);
    up = malloc(((size_t)rows + 1) * sizeof(int32_t));
    ui = malloc(((size_t)gp[rows] + 1) * sizeof(int32_t));
    ux = malloc(((size_t)gp[rows] + 1) * sizeof(double));
    if (up == NULL || ui == NULL || ux == NULL
        || spchol_permute_upper(rows, gp, gi, gx, order, inverse, up, ui, ux) != 0)
        goto out;
    status = spchol_factor(rows, up, ui, ux, added, added, factor);
out:
    free(cp), free(ci), free(cx), free(gp), free(gi), free(gx), free(up), free(ui), free(ux);
    return status;
}

/* The rounds (the header says what they compute). jt as CSR (jp (rows + 1,), ji, jd: rows =
 * 3 D, n2 = 2 P columns); factor C of P G P^T (each column's diagonal first, positive);
 * position (rows,): row -> its place in the factor's order; c (2 P,); mu, keep (P,); rho,
 * iterations, tolerance; relax: the over-relaxation (1: plain ADMM; between 1 and 2 the
 * affine step is pushed past its point, which converges in fewer rounds where ADMM crawls along
 * the cones, as it does at rho = 100); until: CLOCK_MONOTONIC seconds after which no round starts
 * (0: none; read every UNTIL_EVERY rounds); z (2 P,) out. carry (P, 4) or NULL: each point's
 * (z, s) to begin from, read on entry where its row is finite (elsewhere z = cones(c), s = 0)
 * and the last round's (z, s) written back: the state a stream's next step begins from, where
 * the same point's problem has moved little and its cut rounds go on where these stopped.
 * Returns the rounds run, or -1 (memory). */
static long admission_rounds_run(int32_t rows, int64_t n2, const int32_t *jp, const int32_t *ji, const double *jd,
                                 const spchol_factor_t *factor, const int32_t *position, const double *c,
                                 const double *mu, const double *keep, double rho, long iterations, double tolerance,
                                 double relax, double until, double *z, double *carry)
{
    const int64_t n_points = n2 / 2;
    const int32_t *lp = factor->Lp, *li = factor->Li;
    const double *lx = factor->Lx;
    /* Per call, once: J by rows (J^T's columns), its row indices moved to the factor's order,
     * and the factor by rows (for the forward solve) with its diagonal inverted, so that every
     * product of a round gathers (no scattered writes) and no permutation is walked. */
    const int64_t jnz = rows ? jp[rows] : 0, lnz = rows ? lp[rows] : 0;
    double *work = calloc((size_t)(4 * n2 + 2 * rows + jnz + lnz + 2), sizeof(double));
    int32_t *index = calloc((size_t)(n2 + 2 + jnz + rows + 2 + lnz + 1), sizeof(int32_t));
    if (work == NULL || index == NULL) {
        free(work), free(index);
        return -1;
    }
    double *x = work, *s = x + n2, *y = s + n2, *zp = y + n2, *g = zp + n2, *inv_diag = g + rows;
    double *jcx = inv_diag + rows, *rx = jcx + jnz;
    int32_t *jcp = index, *jci = jcp + n2 + 2, *rp = jci + jnz, *ri = rp + rows + 2;
    for (int64_t k = 0; k < jnz; k++) /* J^T's CSR to CSC: J by rows */
        jcp[ji[k] + 2]++;
    for (int64_t k = 0; k < n2; k++)
        jcp[k + 2] += jcp[k + 1];
    for (int32_t r = 0; r < rows; r++)
        for (int32_t k = jp[r]; k < jp[r + 1]; k++) {
            int32_t at = jcp[ji[k] + 1]++;
            jci[at] = position[r];
            jcx[at] = jd[k];
        }
    for (int32_t j = 0; j < rows; j++) { /* the factor's off-diagonal entries by rows */
        inv_diag[j] = 1.0 / lx[lp[j]];
        for (int32_t p = lp[j] + 1; p < lp[j + 1]; p++)
            rp[li[p] + 2]++;
    }
    for (int32_t r = 0; r < rows; r++)
        rp[r + 2] += rp[r + 1];
    for (int32_t j = 0; j < rows; j++)
        for (int32_t p = lp[j] + 1; p < lp[j + 1]; p++) {
            int32_t at = rp[li[p] + 1]++;
            ri[at] = j;
            rx[at] = lx[p];
        }
    const double blend = 1.0 / (1.0 + rho);
    long round = 0;
    project_cones(c, mu, keep, n_points, z);
    if (carry != NULL)
        for (int64_t i = 0; i < n_points; i++) {
            const double *from = carry + 4 * i;
            if (isfinite(from[0]) && isfinite(from[1]) && isfinite(from[2]) && isfinite(from[3])) {
                z[2 * i] = from[0] * keep[i], z[2 * i + 1] = from[1] * keep[i];
                s[2 * i] = from[2], s[2 * i + 1] = from[3];
            }
        }
    while (round < iterations) {
        if (until > 0 && round > 0 && round % UNTIL_EVERY == 0 && monotonic_seconds() >= until)
            break;
        round++;
        for (int64_t k = 0; k < n2; k++) {
            y[k] = (c[k] + rho * (z[k] - s[k])) * blend;
            x[k] = y[k] - c[k]; /* x holds y - c until the projection below */
        }
        if (rows) {
            for (int32_t r = 0; r < rows; r++) /* g = P J^T (y - c), in the factor's order */
                g[position[r]] = gather_dot(jd, ji, x, jp[r], jp[r + 1]);
            for (int32_t i = 0; i < rows; i++) /* C g' = g, C's rows gathered */
                g[i] = (g[i] - gather_dot(rx, ri, g, rp[i], rp[i + 1])) * inv_diag[i];
            for (int32_t j = rows - 1; j >= 0; j--) /* C^T h = g', C's columns gathered */
                g[j] = (g[j] - gather_dot(lx, li, g, lp[j] + 1, lp[j + 1])) * inv_diag[j];
            for (int64_t k = 0; k < n2; k++) /* x = y - J h */
                x[k] = y[k] - gather_dot(jcx, jci, g, jcp[k], jcp[k + 1]);
        } else {
            memcpy(x, y, (size_t)n2 * sizeof(double));
        }
        memcpy(zp, z, (size_t)n2 * sizeof(double));
        /* x^ = relax x + (1 - relax) z: with relax 1 exactly x, the same numbers as plain ADMM. */
        for (int64_t k = 0; k < n2; k++)
            y[k] = relax * x[k] + (1.0 - relax) * zp[k] + s[k];
        project_cones(y, mu, keep, n_points, z);
        double change = 0.0;
        for (int64_t k = 0; k < n2; k++) {
            double gap = x[k] - z[k], moved = z[k] - zp[k];
            s[k] += relax * x[k] + (1.0 - relax) * zp[k] - z[k];
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
    if (carry != NULL)
        for (int64_t i = 0; i < n_points; i++) {
            double *to = carry + 4 * i;
            to[0] = z[2 * i], to[1] = z[2 * i + 1], to[2] = s[2 * i], to[3] = s[2 * i + 1];
        }
    free(work), free(index);
    return round;
}

#endif
