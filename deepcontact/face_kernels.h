/* The face route's solve, compiled: a face's linear system summed over the pairs of points
 * that share a body, as CSR, and its minimum-norm solution through the dual on a sparse
 * Cholesky factor of S S^T. Shared by deepcontact/_faces.c (faces.face_system_sparse,
 * faces.minimum_norm_solve) and deepcontact/_route.c (the whole route in one call); faces.py
 * documents the system and the solve. Every function here runs without the GIL and
 * allocates with malloc.
 */

#ifndef DEEPCONTACT_FACE_KERNELS_H
#define DEEPCONTACT_FACE_KERNELS_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "sparse_cholesky.h"

/* face_system's sum as CSR (deepcontact/_faces.c documents it; faces.face_system_sparse).
 * pa, pb (P,) body rows, checked; dynamic (B,); inv_mass, inv_inertia (B,); n, t, ra, rb
 * (2 P,); index (2 P,): each point's equation row and unknown column by direction, -1 where it
 * has none, below m; slide (P,); m. Out: *out_p (m + 1,), *out_c and *out_v (*nnz,), malloc'd
 * (free them). Returns 0, or -1 where memory ran out (nothing left allocated). */
static int face_system_csr(int64_t n_points, int64_t n_bodies, const int64_t *pa, const int64_t *pb,
                           const unsigned char *dynamic, const double *inv_mass, const double *inv_inertia,
                           const double *n, const double *t, const double *ra, const double *rb, const int64_t *index,
                           const double *slide, int64_t m, int32_t **out_p_, int32_t **out_c_, double **out_v_,
                           int64_t *nnz_)
{
    int64_t *start = NULL, *owner = NULL;
    double *push = NULL, *term_v = NULL, *out_v = NULL;
    int32_t *term_r = NULL, *term_c = NULL, *row_start = NULL, *sorted = NULL, *marker = NULL, *slot = NULL;
    int32_t *out_p = NULL, *out_c = NULL;
    int64_t nnz = 0;
    start = calloc((size_t)(n_bodies + 2), sizeof(int64_t));
    push = malloc((size_t)(2 * n_points + 1) * 6 * sizeof(double));
    owner = malloc((size_t)(2 * n_points + 1) * sizeof(int64_t));
    row_start = calloc((size_t)(m + 2), sizeof(int32_t));
    marker = malloc((size_t)(m + 1) * sizeof(int32_t));
    slot = malloc((size_t)(m + 1) * sizeof(int32_t));
    out_p = malloc((size_t)(m + 1) * sizeof(int32_t));
    if (start == NULL || push == NULL || owner == NULL || row_start == NULL || marker == NULL || slot == NULL
        || out_p == NULL)
        goto fail;
    /* The pushes grouped by body (a counting sort): start[k] .. start[k + 1] are body k's. */
    for (int64_t i = 0; i < n_points; i++) {
        if (dynamic[pb[i]])
            start[pb[i] + 2]++;
        if (dynamic[pa[i]])
            start[pa[i] + 2]++;
    }
    for (int64_t k = 0; k < n_bodies; k++)
        start[k + 2] += start[k + 1];
    for (int64_t i = 0; i < n_points; i++)
        for (int side = 0; side < 2; side++) { /* body b pushed along +n, body a along -n */
            const int64_t body = side == 0 ? pb[i] : pa[i];
            if (!dynamic[body])
                continue;
            const double sign = side == 0 ? 1.0 : -1.0, *r = side == 0 ? rb + 2 * i : ra + 2 * i;
            const int64_t at = start[body + 1]++;
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
    int64_t room = 0;
    for (int64_t k = 0; k < n_bodies; k++)
        room += 4 * (start[k + 1] - start[k]) * (start[k + 1] - start[k]);
    if (room > INT32_MAX)
        goto fail;
    term_r = malloc((size_t)(room + 1) * sizeof(int32_t));
    term_c = malloc((size_t)(room + 1) * sizeof(int32_t));
    term_v = malloc((size_t)(room + 1) * sizeof(double));
    sorted = malloc((size_t)(room + 1) * sizeof(int32_t));
    if (term_r == NULL || term_c == NULL || term_v == NULL || sorted == NULL)
        goto fail;
    int64_t terms = 0;
    for (int64_t k = 0; k < n_bodies; k++) {
        const double w[3] = {inv_mass[k], inv_mass[k], inv_inertia[k]};
        for (int64_t p = start[k]; p < start[k + 1]; p++) {
            const double *gi = push + 6 * p;
            const int64_t i = owner[p];
            for (int64_t q = start[k]; q < start[k + 1]; q++) {
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
    for (int64_t q = 0; q < terms; q++)
        row_start[term_r[q] + 2]++;
    for (int64_t r = 0; r < m; r++)
        row_start[r + 2] += row_start[r + 1];
    for (int64_t q = 0; q < terms; q++)
        sorted[row_start[term_r[q] + 1]++] = (int32_t)q;
    for (int64_t c = 0; c < m; c++)
        marker[c] = -1;
    out_p[0] = 0;
    for (int64_t r = 0; r < m; r++) { /* row_start[r] .. row_start[r + 1]: row r's terms */
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
        goto fail;
    for (int64_t c = 0; c < m; c++)
        marker[c] = -1;
    for (int64_t r = 0; r < m; r++) {
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
    free(start), free(push), free(owner), free(term_r), free(term_c), free(term_v), free(sorted), free(row_start);
    free(marker), free(slot);
    *out_p_ = out_p;
    *out_c_ = out_c;
    *out_v_ = out_v;
    *nnz_ = nnz;
    return 0;
fail:
    free(start), free(push), free(owner), free(term_r), free(term_c), free(term_v), free(sorted), free(row_start);
    free(marker), free(slot), free(out_p), free(out_c), free(out_v);
    return -1;
}

/* How many times face_dual_solve grows its ridge, and by how much each time, where the factor
 * meets a pivot below zero: see faces.DUAL_RIDGE. */
#define FACE_DUAL_RIDGE_TRIES 2
#define FACE_DUAL_RIDGE_GROWTH 100.0

/* minimum_norm_solve's dual solve on S's nonzeros (deepcontact/_faces.c documents it). S as
 * CSR (sp (m + 1,), si, sx; checked), rhs (m,), ridge (relative to S S^T's mean diagonal; grown
 * FACE_DUAL_RIDGE_GROWTH times, up to FACE_DUAL_RIDGE_TRIES times, while the factor meets a
 * pivot below zero), refinements, optimality, x (m,) out. Returns 0 (x written), 1 (S S^T not
 * positive definite to rounding at the largest ridge), 2 (x is not a least-squares answer) or
 * -1 (memory). */
static int face_dual_solve(int64_t m, const int32_t *sp, const int32_t *si, const double *sx, const double *rhs,
                           double ridge, int refinements, double optimality, double *x)
{
    const int64_t nnz = sp[m];
    int32_t *cp = NULL, *ci = NULL, *gp = NULL, *gi = NULL, *order = NULL, *inverse = NULL;
    int32_t *up = NULL, *ui = NULL;
    double *cx = NULL, *gx = NULL, *ux = NULL, *work = NULL;
    spchol_factor_t factor = {0, NULL, NULL, NULL};
    int status = -1;
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
    for (int tries = 0; factored > 0 && tries < FACE_DUAL_RIDGE_TRIES; tries++) {
        ridge *= FACE_DUAL_RIDGE_GROWTH;
        factored = spchol_factor((int32_t)m, up, ui, ux, ridge * scale, 0.0, &factor);
    }
    if (factored != 0) {
        status = factored > 0 ? 1 : -1;
        goto out;
    }
    /* y = G^-1 b, refined against S S^T (not the ridged G); y is kept in the new order. */
    double *y = work, *r = work + m, *u = work + 2 * m, *v = work + 3 * m;
    for (int64_t k = 0; k < m; k++)
        y[inverse[k]] = rhs[k];
    spchol_solve(&factor, y);
    for (int round = 0; round < refinements; round++) {
        for (int64_t c = 0; c < m; c++) { /* u = S^T y */
            double s_ = 0.0;
            for (int32_t q = cp[c]; q < cp[c + 1]; q++)
                s_ += cx[q] * y[inverse[ci[q]]];
            u[c] = s_;
        }
        for (int64_t i = 0; i < m; i++) { /* r = b - S u, in the new order */
            double s_ = 0.0;
            for (int32_t p = sp[i]; p < sp[i + 1]; p++)
                s_ += sx[p] * u[si[p]];
            r[inverse[i]] = rhs[i] - s_;
        }
        spchol_solve(&factor, r);
        for (int64_t k = 0; k < m; k++)
            y[k] += r[k];
    }
    for (int64_t c = 0; c < m; c++) { /* x = S^T y */
        double s_ = 0.0;
        for (int32_t q = cp[c]; q < cp[c + 1]; q++)
            s_ += cx[q] * y[inverse[ci[q]]];
        x[c] = s_;
    }
    /* The answer's test: |S^T (S x - b)| against |S^T b|. */
    for (int64_t i = 0; i < m; i++) {
        double s_ = 0.0;
        for (int32_t p = sp[i]; p < sp[i + 1]; p++)
            s_ += sx[p] * x[si[p]];
        v[i] = s_ - rhs[i];
    }
    double gradient = 0.0, reach = 0.0;
    for (int64_t c = 0; c < m; c++) {
        double g_ = 0.0, h_ = 0.0;
        for (int32_t q = cp[c]; q < cp[c + 1]; q++) {
            g_ += cx[q] * v[ci[q]];
            h_ += cx[q] * rhs[ci[q]];
        }
        gradient += g_ * g_;
        reach += h_ * h_;
    }
    status = sqrt(gradient) <= optimality * sqrt(reach) ? 0 : 2;
out:
    spchol_free(&factor);
    free(cp), free(ci), free(cx), free(gp), free(gi), free(gx);
    free(order), free(inverse), free(up), free(ui), free(ux), free(work);
    return status;
}

#endif
