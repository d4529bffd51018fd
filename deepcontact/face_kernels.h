/* The face route's solve, compiled: a face's linear system summed over the pairs of points
 * that share a body, as CSR, and its minimum-norm solution through the dual on a sparse
 * Cholesky factor of S S^T, or in the bodies' space on factors of order 3 D (face_body_solve;
 * the compiled route's only). Shared by deepcontact/_faces.c (faces.face_system_sparse,
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

/* face_body_solve's ridge on K = W^1/2 A^T A W^1/2, relative to its mean diagonal. K's
 * eigenvalues are S's own (not S S^T's, their squares), so the cut lies at about the same share
 * of S's largest singular value as the dual's ridge (faces.DUAL_RIDGE, on squares) does: inside
 * the gap a face's system leaves between the directions it resolves (above about 1e-6 of the
 * largest) and rounding's (below 1e-12). On a pyramid of boxes 1e-12 to 1e-8 give the dual's
 * answer to 1e-13; 1e-13 begins to read rounding. */
#define FACE_BODY_RIDGE 1e-10

/* y = K^+ y (K's pseudo-inverse by the ridged factor f of P K P^T, refined `refinements` times
 * against K itself), in place, y in the factor's order. K whole (CSC kp, ki, kx) in the original
 * order; inverse: original -> position; r (n,) scratch. The ridge's (K + r I)^-1 keeps a vector
 * in K's range there, so a y in K's range comes out in it: the null space never enters. */
static void face_body_pinv(int32_t n, const spchol_factor_t *f, const int32_t *kp, const int32_t *ki, const double *kx,
                           const int32_t *inverse, int refinements, double *y, double *r, double *z)
{
    memcpy(z, y, (size_t)n * sizeof(double));
    spchol_solve(f, z);
    for (int round = 0; round < refinements; round++) {
        memcpy(r, y, (size_t)n * sizeof(double));
        for (int32_t c = 0; c < n; c++) { /* r = y - K z */
            const double zc = z[inverse[c]];
            for (int32_t q = kp[c]; q < kp[c + 1]; q++)
                r[inverse[ki[q]]] -= kx[q] * zc;
        }
        spchol_solve(f, r);
        for (int32_t k = 0; k < n; k++)
            z[k] += r[k];
    }
    memcpy(y, z, (size_t)n * sizeof(double));
}

/* A pivot of face_body_solve's factors below this share of their matrix's mean diagonal marks a
 * direction the face's rows or columns leave free (where points slide, the bodies' space answers
 * only where neither K nor G has one but those it has set apart: the bodies no unknown pushes,
 * and those one or two do along the directions their pushes leave). A face's system resolves
 * nothing below about 1e-6 of its largest singular value, and the ridge (FACE_BODY_RIDGE) leaves
 * a free direction's pivot at 1e-10. */
#define FACE_BODY_FREE 1e-8

/* L^T or R^T (rows, m) as CSR from J^T's entries (jt: jp, ji, jd): each on its column's unknown
 * (index; -1: none) times its row's W^1/2; with slide (P,) non-NULL, a tangent entry of a point
 * that slides also on its normal unknown, times slide (R^T: a sliding point's column is its
 * normal plus slide times its tangent). ap (rows + 1,), ai and ax (2 nnz of J^T) out. */
static void face_body_rows(int32_t rows, const int32_t *jp, const int32_t *ji, const double *jd, const double *weight,
                           const int64_t *index, const double *slide, int32_t *ap, int32_t *ai, double *ax)
{
    int32_t at = 0;
    ap[0] = 0;
    for (int32_t r = 0; r < rows; r++) {
        for (int32_t p = jp[r]; p < jp[r + 1]; p++) {
            const int32_t col = ji[p];
            if (index[col] >= 0) {
                ai[at] = (int32_t)index[col];
                ax[at++] = jd[p] * weight[r];
            }
            if (slide != NULL && (col & 1) && slide[col / 2] != 0.0 && index[col - 1] >= 0) {
                ai[at] = (int32_t)index[col - 1];
                ax[at++] = slide[col / 2] * jd[p] * weight[r];
            }
        }
        ap[r + 1] = at;
    }
}

/* One of face_body_solve's two body-space matrices, built and factored: the gram M = A A^T of
 * A (rows, m) given by rows (ap, ai, ax) and by columns (cp, ci, cx), whole (CSC, *mp, *mi,
 * *mx out, malloc'd), and P M P^T + ridge * mean diagonal = C C^T in `order` (inverse out), f
 * out. *free_out: whether a pivot of a row A does not leave empty lies below FACE_BODY_FREE of
 * the mean diagonal (*scale_out). Returns 0, -1
 * (memory), 1 (a pivot not positive) or 3 (M = 0). */
static int face_body_factor(int32_t rows, const int32_t *ap, const int32_t *ai, const double *ax, const int32_t *cp,
                            const int32_t *ci, const double *cx, const int32_t *order, double ridge, int32_t *inverse,
                            int32_t **mp, int32_t **mi, double **mx, spchol_factor_t *f, int *free_out,
                            double *scale_out)
{
    double trace;
    if (spchol_gram(rows, ap, ai, ax, cp, ci, cx, mp, mi, mx, &trace) != 0)
        return -1;
    const double scale = rows ? trace / (double)rows : 0.0;
    *scale_out = scale;
    if (!(scale > 0))
        return 3;
    const int32_t entries = (*mp)[rows];
    int32_t *up = malloc(((size_t)rows + 1) * sizeof(int32_t));
    int32_t *ui = malloc(((size_t)entries + 1) * sizeof(int32_t));
    double *ux = malloc(((size_t)entries + 1) * sizeof(double));
    int status = -1;
    if (up != NULL && ui != NULL && ux != NULL && spchol_permute_upper(rows, *mp, *mi, *mx, order, inverse, up, ui, ux) == 0)
        status = spchol_factor(rows, up, ui, ux, ridge * scale, 0.0, f);
    free(up), free(ui), free(ux);
    *free_out = 0;
    if (status == 0)
        for (int32_t k = 0; k < rows && !*free_out; k++) {
            const double pivot = f->Lx[f->Lp[k]];
            /* A row A leaves empty (a body no unknown pushes, falling free) is free in K and G
             * both, and answered 0 by both: only the others count. */
            *free_out = ap[order[k] + 1] > ap[order[k]] && pivot * pivot < FACE_BODY_FREE * scale;
        }
    return status;
}

/* The directions a body's own pushes leave free, where one or two unknowns push it: the 3-vectors
 * (x, y, rotation, scaled by W^1/2) ortho-normal to its rows of L^T (their k-th entries on the
 * body's three rows are one unknown's: contact_jacobian.h writes a point's rows together).
 * ap, ax: L^T as CSR; q: the body's first row; out (6,): up to two vectors. Returns how many:
 * two where one unknown pushes (or two along one line), one where two do, 0 where nothing does. */
static int face_body_free_directions(const int32_t *ap, const double *ax, int32_t q, double *out)
{
    const int32_t pushes = ap[q + 1] - ap[q];
    double l[2][3] = {{0.0, 0.0, 0.0}, {0.0, 0.0, 0.0}};
    for (int32_t k = 0; k < pushes && k < 2; k++)
        for (int d = 0; d < 3; d++)
            l[k][d] = ax[ap[q + d] + k];
    const double n0 = sqrt(l[0][0] * l[0][0] + l[0][1] * l[0][1] + l[0][2] * l[0][2]);
    const double n1 = sqrt(l[1][0] * l[1][0] + l[1][1] * l[1][1] + l[1][2] * l[1][2]);
    if (pushes == 2) {
        double c[3] = {l[0][1] * l[1][2] - l[0][2] * l[1][1], l[0][2] * l[1][0] - l[0][0] * l[1][2],
                       l[0][0] * l[1][1] - l[0][1] * l[1][0]};
        const double nc = sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]);
        if (nc > 1e-12 * n0 * n1) {
            for (int d = 0; d < 3; d++)
                out[d] = c[d] / nc;
            return 1;
        }
    }
    /* One line of pushes: the plane normal to it. */
    const double *a = n0 >= n1 ? l[0] : l[1];
    const double na = n0 >= n1 ? n0 : n1;
    if (!(na > 0.0))
        return 0;
    double e[3] = {a[0] / na, a[1] / na, a[2] / na}, axis[3] = {0.0, 0.0, 0.0};
    int least = 0; /* the axis least along e */
    for (int d = 1; d < 3; d++)
        if (fabs(e[d]) < fabs(e[least]))
            least = d;
    axis[least] = 1.0;
    double u[3] = {e[1] * axis[2] - e[2] * axis[1], e[2] * axis[0] - e[0] * axis[2], e[0] * axis[1] - e[1] * axis[0]};
    const double nu = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
    for (int d = 0; d < 3; d++)
        u[d] /= nu;
    out[0] = u[0], out[1] = u[1], out[2] = u[2];
    out[3] = e[1] * u[2] - e[2] * u[1], out[4] = e[2] * u[0] - e[0] * u[2], out[5] = e[0] * u[1] - e[1] * u[0];
    return 2;
}

/* A body's free directions out of its rows of R^T (R^T P, P = I - N N^T: its first `count`
 * entries on each of its three rows, one unknown's at a time), then each direction appended to
 * those rows as a column of its own (m + j), times sqrt(weight): L'^T or R'^T, whose gram is P M P
 * + weight N N^T. ap, ai, ax: CSR with room for 3 entries more a direction (moved here);
 * directions: `free` (F,) body first rows and `dirs` (3 F,); project: whether to project first. */
static void face_body_ridge_columns(int32_t rows, int32_t *ap, int32_t *ai, double *ax, int32_t n_free,
                                    const int32_t *free_rows, const double *dirs, int64_t m, double weight, int project)
{
    if (n_free == 0)
        return;
    if (project)
        for (int32_t j = 0; j < n_free;) { /* a body's directions are consecutive */
            const int32_t q = free_rows[j];
            int32_t end = j;
            while (end < n_free && free_rows[end] == q)
                end++;
            for (int32_t k = 0; k < ap[q + 1] - ap[q]; k++) {
                double v[3] = {ax[ap[q] + k], ax[ap[q + 1] + k], ax[ap[q + 2] + k]};
                for (int32_t t = j; t < end; t++) {
                    const double *n = dirs + 3 * t;
                    const double along = n[0] * v[0] + n[1] * v[1] + n[2] * v[2];
                    for (int d = 0; d < 3; d++)
                        v[d] -= along * n[d];
                }
                for (int d = 0; d < 3; d++)
                    ax[ap[q + d] + k] = v[d];
            }
            j = end;
        }
    /* Each row's new start: its old one plus the entries appended to the rows before it (each
     * direction adds one to each of its body's three rows). Moved from the last row back, so that
     * no entry is written over before it has moved. */
    const double root = sqrt(weight);
    int32_t before = 3 * n_free, j = n_free; /* appended before row r's end; directions not yet placed */
    for (int32_t r = rows - 1; r >= 0; r--) {
        const int32_t body = r - r % 3;
        int32_t first = j;
        while (first > 0 && free_rows[first - 1] == body)
            first--;
        const int32_t here = j - first; /* this body's directions: first .. j */
        before -= here;
        const int32_t begin = ap[r], end = ap[r + 1];
        for (int32_t p = end - 1; p >= begin; p--) {
            ai[p + before] = ai[p];
            ax[p + before] = ax[p];
        }
        for (int32_t t = 0; t < here; t++) {
            ai[end + before + t] = (int32_t)(m + first + t);
            ax[end + before + t] = root * dirs[3 * (first + t) + r % 3];
        }
        ap[r + 1] = end + before + here;
        if (r % 3 == 0)
            j = first;
    }
}

/* a . b over n entries, in four running sums (a dependent chain of additions is what bounds
 * face_body_shared_directions' and face_body_off_shared's dense products, not their arithmetic). */
static double face_dot(const double *a, const double *b, int32_t n)
{
    double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
    int32_t k = 0;
    for (; k + 4 <= n; k += 4) {
        s0 += a[k] * b[k];
        s1 += a[k + 1] * b[k + 1];
        s2 += a[k + 2] * b[k + 2];
        s3 += a[k + 3] * b[k + 3];
    }
    for (; k < n; k++)
        s0 += a[k] * b[k];
    return (s0 + s1) + (s2 + s3);
}

/* The most candidates for free directions several bodies share that face_body_solve reads off
 * K's factor: past it the step goes to the dual (each costs its share of one or two walks of K's
 * factor, a Gram-Schmidt step against the others and its share of a walk of G's). The zoo's pyramids have up to 47;
 * a pile of discs, whose sticking points leave pairs of discs turning against each other, up to
 * 90 and more, where the dual is the cheaper (face_body_solve looks for them only where the
 * face has more unknowns than its bodies have freedoms). */
#define FACE_BODY_MOST_SHARED 64
/* A pivot of K's factor below this share of its mean diagonal is a candidate. Not only the
 * pivots the ridge alone holds (below FACE_BODY_FREE): where free directions overlap, a
 * Cholesky factor may show one of them at a pivot of 1e-5 to 1e-4 (a pyramid of the zoo:
 * twenty free directions, nineteen pivots at the ridge and one at 3.4e-5), while the first
 * direction K resolves lies at 1e-3 of its mean eigenvalue and beyond. */
#define FACE_BODY_CANDIDATE 1e-3
/* A candidate, after its inverse iteration, is a free direction where K' takes it to below this
 * share of its mean diagonal (n^T K' n; rounding leaves 1e-16, a resolved one 1e-3 and more). */
#define FACE_BODY_NULL 1e-10

/* The directions K leaves free that no one body's pushes account for: a row of boxes sliding
 * together on their supports, held to one another by sticking points. With f the factor of
 * P K' P^T + ridge (K' = K with the bodies' own free directions given columns of their own,
 * face_body_ridge_columns), a free direction shows as a pivot the ridge alone holds: the Schur
 * complement there is zero to rounding, so L^-T e_k is a null vector of K' to the ridge's
 * accuracy (L L^T L^-T e_k = L e_k, whose only entry of size is the pivot, sqrt(ridge)). Each
 * pivot below FACE_BODY_CANDIDATE of K's mean diagonal `scale` on a row L does not leave empty
 * gives a candidate so, sharpened by inverse iteration with the same factor (once from a pivot
 * below FACE_BODY_FREE, twice from the others; each step shrinks its part off K's null space by
 * the ridge over K's least resolved eigenvalue, 1e-7 or less), taken off the bodies' own
 * directions (free_rows, dirs: n_free of them, K' holds them already) and made ortho-normal
 * (Gram-Schmidt, twice); one that rounding leaves dependent on those kept, or that K' holds
 * (FACE_BODY_NULL), is dropped. kp, ki, kx: K' whole (CSC, the rows' order); ap: L^T's rows
 * (CSR: a row L leaves empty is free in K and G both and answered 0, not counted); order
 * (position -> row); shared (FACE_BODY_MOST_SHARED rows,) out, one direction after another, in
 * the rows' own order; work (rows,). Returns how many were kept, -2 where there are more than
 * FACE_BODY_MOST_SHARED candidates, or -1 where memory ran out. */
static int face_body_shared_directions(int32_t rows, const spchol_factor_t *f, const int32_t *ap, const int32_t *order,
                                       const int32_t *kp, const int32_t *ki, const double *kx,
                                       double scale, int32_t n_free, const int32_t *free_rows, const double *dirs,
                                       double *shared, double *work)
{
    const int32_t *Lp = f->Lp, *Li = f->Li;
    const double *Lx = f->Lx;
    int32_t count = 0;
    unsigned char iterations[FACE_BODY_MOST_SHARED]; /* 1 from a pivot the ridge alone holds, else 2 */
    for (int32_t k = 0; k < rows; k++) /* counted first: past the most, nothing is computed */
        count += ap[order[k] + 1] > ap[order[k]] && Lx[Lp[k]] * Lx[Lp[k]] < FACE_BODY_CANDIDATE * scale;
    if (count > FACE_BODY_MOST_SHARED)
        return -2;
    count = 0;
    for (int32_t k = 0; k < rows; k++) {
        const double pivot = Lx[Lp[k]];
        if (!(ap[order[k] + 1] > ap[order[k]] && pivot * pivot < FACE_BODY_CANDIDATE * scale))
            continue;
        iterations[count] = pivot * pivot < FACE_BODY_FREE * scale ? 1 : 2;
        double *v = shared + (size_t)count++ * rows; /* in the factor's order until the end */
        memset(v, 0, (size_t)rows * sizeof(double));
        v[k] = 1.0;
        for (int32_t j = k; j >= 0; j--) { /* v = L^-T e_k: rows past k stay 0 */
            double acc = v[j];
            for (int32_t p = Lp[j] + 1; p < Lp[j + 1]; p++)
                acc -= Lx[p] * v[Li[p]];
            v[j] = acc / Lx[Lp[j]];
        }
    }
    /* The inverse iteration, every candidate still iterating at once (spchol_solve_many). */
    double *block = malloc((size_t)rows * (size_t)count * sizeof(double) + sizeof(double));
    if (block == NULL)
        return -1;
    for (int step = 0; step < 2; step++) {
        int32_t going = 0;
        for (int32_t t = 0; t < count; t++)
            going += iterations[t] > step;
        if (going == 0)
            break;
        for (int32_t t = 0, j = 0; t < count; t++) {
            if (iterations[t] <= step)
                continue;
            double *v = shared + (size_t)t * rows; /* normalized, then (K' + ridge)^-1 */
            const double norm = sqrt(face_dot(v, v, rows));
            for (int32_t k = 0; k < rows; k++)
                block[(size_t)k * going + j] = v[k] / norm;
            j++;
        }
        spchol_solve_many(f, block, going);
        for (int32_t t = 0, j = 0; t < count; t++) {
            if (iterations[t] <= step)
                continue;
            double *v = shared + (size_t)t * rows;
            for (int32_t k = 0; k < rows; k++)
                v[k] = block[(size_t)k * going + j];
            j++;
        }
    }
    free(block);
    for (int32_t t = 0; t < count; t++) {
        double *v = shared + (size_t)t * rows;
        const double norm = sqrt(face_dot(v, v, rows));
        for (int32_t k = 0; k < rows; k++)
            v[k] /= norm;
        memcpy(work, v, (size_t)rows * sizeof(double)); /* into the rows' own order */
        for (int32_t k = 0; k < rows; k++)
            v[order[k]] = work[k];
        for (int32_t j = 0; j < n_free; j++) { /* off the bodies' own (ortho-normal, a body's three rows) */
            const int32_t q = free_rows[j];
            const double *d = dirs + 3 * j;
            const double along = v[q] * d[0] + v[q + 1] * d[1] + v[q + 2] * d[2];
            for (int i = 0; i < 3; i++)
                v[q + i] -= along * d[i];
        }
    }
    int32_t kept = 0;
    for (int32_t t = 0; t < count; t++) {
        double *v = shared + (size_t)t * rows;
        const double before = face_dot(v, v, rows);
        for (int pass = 0; pass < 2; pass++)
            for (int32_t u = 0; u < kept; u++) {
                const double *e = shared + (size_t)u * rows;
                const double along = face_dot(e, v, rows);
                for (int32_t k = 0; k < rows; k++)
                    v[k] -= along * e[k];
            }
        double norm = face_dot(v, v, rows);
        if (!(norm > 1e-8 * before))
            continue; /* dependent on those kept */
        norm = sqrt(norm);
        for (int32_t k = 0; k < rows; k++)
            v[k] /= norm;
        double quotient = 0.0; /* v^T K' v: a direction K' holds is not free */
        for (int32_t c = 0; c < rows; c++) {
            double kv = 0.0;
            for (int32_t p = kp[c]; p < kp[c + 1]; p++)
                kv += kx[p] * v[ki[p]];
            quotient += kv * v[c];
        }
        if (!(quotient < FACE_BODY_NULL * scale))
            continue;
        double *into = shared + (size_t)kept++ * rows;
        memmove(into, v, (size_t)rows * sizeof(double));
    }
    return kept;
}

/* P G' P's answer on the range of P = I - N N^T, N (n_shared, ortho-normal) the free directions
 * of K that several bodies share (face_body_shared_directions): z with N^T z = 0 and P G' z = y
 * for y (rows,) on P's range, in the factor's order, in place. G' (R's gram with the bodies' own
 * free directions set apart) may itself leave some of N's directions free, so its ridged factor
 * f is used only inside the Schur complement that keeps the answer off N: z = w - H mu, w =
 * f^-1 y, H = f^-1 N, mu = (N^T H)^-1 N^T w. That is the exact answer for the ridged G' (which
 * is G' on P's range where G' is of full rank there), and `refinements` rounds against P G' P
 * itself (gp, gi, gx: G' whole, CSC, the rows' order) take off what the ridge and the cancelling
 * of H's large parts left. No N's columns join G' (each spans many bodies: its factor would
 * fill). inverse: row -> the factor's position. Returns 0, 1 (N^T H not positive definite) or
 * -1 (memory). */
static int face_body_off_shared(int32_t rows, const spchol_factor_t *f, const int32_t *gp, const int32_t *gi,
                                const double *gx, const int32_t *inverse, int refinements, int32_t n_shared,
                                const double *shared, double *z)
{
    const size_t n = (size_t)n_shared;
    double *nf = malloc(n * (size_t)rows * sizeof(double) + sizeof(double)); /* N in the factor's order */
    double *h = malloc(n * (size_t)rows * sizeof(double) + sizeof(double));
    double *gram = malloc(n * n * sizeof(double) + sizeof(double));
    double *mu = malloc((n + 1) * sizeof(double));
    double *y = malloc(((size_t)rows + 1) * sizeof(double));
    double *w = malloc(((size_t)rows + 1) * sizeof(double));
    double *g = malloc(((size_t)rows + 1) * sizeof(double));
    double *g_ = malloc(n * (size_t)rows * sizeof(double) + sizeof(double)); /* H's transpose */
    int status = -1;
    if (nf == NULL || h == NULL || gram == NULL || mu == NULL || y == NULL || w == NULL || g == NULL || g_ == NULL)
        goto done;
    for (size_t t = 0; t < n; t++) { /* H = f^-1 N, every column in one walk of f (h as (rows, n) first) */
        double *ft = nf + t * rows;
        const double *nt = shared + t * rows;
        for (int32_t q = 0; q < rows; q++)
            ft[inverse[q]] = nt[q];
        for (int32_t k = 0; k < rows; k++)
            h[(size_t)k * n + t] = ft[k];
    }
    spchol_solve_many(f, h, n_shared);
    for (int32_t k = 0; k < rows; k++) /* (n, rows), a direction's after another's: gram[] reads */
        for (size_t t = 0; t < n; t++)
            g_[t * rows + k] = h[(size_t)k * n + t];
    memcpy(h, g_, n * (size_t)rows * sizeof(double));
    for (size_t a = 0; a < n; a++) /* N^T H, symmetric, lower */
        for (size_t t = 0; t <= a; t++)
            gram[a * n + t] = face_dot(nf + a * rows, h + t * rows, rows);
    for (size_t j = 0; j < n; j++) { /* its Cholesky factor, in place */
        double d = gram[j * n + j];
        for (size_t k = 0; k < j; k++)
            d -= gram[j * n + k] * gram[j * n + k];
        if (!(d > 0.0)) {
            status = 1;
            goto done;
        }
        d = sqrt(d);
        gram[j * n + j] = d;
        for (size_t i = j + 1; i < n; i++) {
            double e = gram[i * n + j];
            for (size_t k = 0; k < j; k++)
                e -= gram[i * n + k] * gram[j * n + k];
            gram[i * n + j] = e / d;
        }
    }
    memcpy(y, z, (size_t)rows * sizeof(double));
    memset(z, 0, (size_t)rows * sizeof(double));
    memcpy(w, y, (size_t)rows * sizeof(double)); /* the residual, first y itself */
    for (int round = 0; round <= refinements; round++) {
        spchol_solve(f, w); /* w = f^-1 residual, then off N: w - H mu */
        for (size_t a = 0; a < n; a++)
            mu[a] = face_dot(nf + a * rows, w, rows);
        for (size_t i = 0; i < n; i++) {
            for (size_t k = 0; k < i; k++)
                mu[i] -= gram[i * n + k] * mu[k];
            mu[i] /= gram[i * n + i];
        }
        for (size_t i = n; i-- > 0;) {
            for (size_t k = i + 1; k < n; k++)
                mu[i] -= gram[k * n + i] * mu[k];
            mu[i] /= gram[i * n + i];
        }
        for (size_t t = 0; t < n; t++) {
            const double *ht = h + t * rows;
            for (int32_t k = 0; k < rows; k++)
                w[k] -= mu[t] * ht[k];
        }
        for (int32_t k = 0; k < rows; k++)
            z[k] += w[k];
        /* z = P z: where G' leaves a direction of N free, H's parts along it are the ridge's
         * inverse, and what their cancelling leaves would reach x through R */
        for (size_t a = 0; a < n; a++) {
            const double *na = nf + a * rows;
            const double along = face_dot(na, z, rows);
            for (int32_t k = 0; k < rows; k++)
                z[k] -= along * na[k];
        }
        if (round == refinements)
            break;
        memset(g, 0, (size_t)rows * sizeof(double)); /* the residual y - P G' z, z on P's range */
        for (int32_t c = 0; c < rows; c++) {
            const double zc = z[inverse[c]];
            for (int32_t p = gp[c]; p < gp[c + 1]; p++)
                g[inverse[gi[p]]] += gx[p] * zc;
        }
        for (size_t a = 0; a < n; a++) {
            const double *na = nf + a * rows;
            const double along = face_dot(na, g, rows);
            for (int32_t k = 0; k < rows; k++)
                g[k] -= along * na[k];
        }
        for (int32_t k = 0; k < rows; k++)
            w[k] = y[k] - g[k];
    }
    status = 0;
done:
    free(nf), free(h), free(gram), free(mu), free(y), free(w), free(g), free(g_);
    return status;
}

/* minimum_norm_solve's answer in the bodies' space. With A (m, 3 D) the face's rows of J (the
 * pressing points' normals, the sticking points' tangents), C its columns (A, but a sliding
 * point's normal plus slide times its tangent) and W the dynamic bodies' inverse masses and
 * inertias, a face's system is S = A W C^T = L R^T, L = A W^1/2, R = C W^1/2, and with K = L^T L
 * and G = R^T R (3 D, 3 D):
 *   - where no point slides, R = L and S's pseudo-inverse is L K^+ K^+ L^T, whatever K's rank;
 *   - where points slide, it is R G^-1 K^-1 L^T where K and G are both of full rank (L R^T a
 *     full-rank factorization), but for the rows of bodies no unknown pushes, empty in both,
 *     and the directions a body one or two unknowns push leaves free: with Q a basis of L's
 *     rows, S^+ = R Q (Q^T G Q)^-1 (Q^T K Q)^-1 Q^T L^T, those directions N taken off R's rows
 *     (L P = L, P = I - N N^T) and given columns of their own in both, so that K + c N N^T and
 *     P G P + c N N^T act as the inverses on P's range, where the solve's vectors lie
 *     (face_body_ridge_columns). The directions K leaves free besides (rows of boxes that stick
 *     to one another sliding together: no one body's pushes leave them) are read off K's
 *     factor (face_body_shared_directions), and R's side is kept off them by a Schur
 *     complement on G's factor rather than by columns of their own, each over many bodies
 *     (face_body_off_shared). Where G leaves a direction free that K does not, or more than
 *     FACE_BODY_MOST_SHARED are shared, the product is not the pseudo-inverse: declined (1)
 *     or failed the test below (2), for the dual.
 * The same x as the dual's S^T (S S^T)^+ b, from factors of order 3 D rather than m: on a
 * pyramid of boxes (800 points, m = 1,600 unknowns, 630 body rows) a small share of S S^T's,
 * whose graph joins every pair of points two bodies apart. jt: J^T as CSR (jp (rows + 1,), ji,
 * jd: rows = 3 D, 2 P columns; contact_jacobian.h); weight (rows,): each row's W^1/2
 * (1/sqrt(kg), 1/sqrt(kg m^2)); order (rows,): a fill-reducing order (position -> row); index
 * (2 P,): each column's unknown or -1, below m; slide (P,): each point's slide (+-mu where it
 * slides, else 0); rhs (m,); ridge relative to each matrix's mean diagonal (FACE_BODY_RIDGE);
 * refinements and optimality as face_dual_solve's; slide_in_bodies: 0 sends a step where points
 * slide to the dual at once (a card's slide_in_bodies: in a pile of discs, whose sliding points
 * leave turnings that only the pile's sticking points hold, K is nearly always left free); x
 * (m,) out. Returns 0 (x written), 1 (declined: a pivot not positive, a free direction of G where
 * points slide, or points slide and slide_in_bodies is 0), 2 (x is not a
 * least-squares answer: |S^T (S x - b)| > optimality |S^T b|) or -1 (memory). */
static int face_body_solve(int32_t rows, const int32_t *jp, const int32_t *ji, const double *jd, const double *weight,
                           const int32_t *order, const int64_t *index, const double *slide, int64_t n_points, int64_t m,
                           const double *rhs, double ridge, int refinements, double optimality, int slide_in_bodies,
                           double *x)
{
    int slides = 0;
    for (int64_t i = 0; i < n_points && !slides; i++)
        slides = slide[i] != 0.0 && index[2 * i] >= 0;
    if (slides && !slide_in_bodies)
        return 1;
    const int32_t nnz = rows ? jp[rows] : 0;
    const int sides = slides ? 2 : 1; /* L, and R where it differs */
    int32_t *ap[2] = {NULL, NULL}, *ai[2] = {NULL, NULL}, *cp[2] = {NULL, NULL}, *ci[2] = {NULL, NULL};
    int32_t *mp[2] = {NULL, NULL}, *mi[2] = {NULL, NULL}, *inverse = NULL, *free_rows = NULL;
    double *ax[2] = {NULL, NULL}, *cx[2] = {NULL, NULL}, *mx[2] = {NULL, NULL}, *work = NULL, *dirs = NULL;
    double *shared = NULL; /* where points slide: free directions of K several bodies share */
    int32_t n_shared = 0;
    spchol_factor_t f[2] = {{0, NULL, NULL, NULL}, {0, NULL, NULL, NULL}};
    int status = -1;
    int32_t n_free = 0; /* where points slide: the free directions of bodies one or two unknowns push */
    const int32_t most_free = 2 * (rows / 3);
    free_rows = malloc(((size_t)most_free + 1) * sizeof(int32_t));
    dirs = malloc(((size_t)3 * most_free + 1) * sizeof(double));
    inverse = malloc(((size_t)rows + 1) * sizeof(int32_t));
    if (free_rows == NULL || dirs == NULL || inverse == NULL)
        goto out;
    for (int k = 0; k < sides; k++) {
        const size_t room = (size_t)(k ? 2 : 1) * (size_t)nnz + 3 * (size_t)most_free + 1;
        ap[k] = malloc(((size_t)rows + 1) * sizeof(int32_t));
        ai[k] = malloc(room * sizeof(int32_t));
        ax[k] = malloc(room * sizeof(double));
        cp[k] = calloc((size_t)m + (size_t)most_free + 2, sizeof(int32_t));
        ci[k] = malloc(room * sizeof(int32_t));
        cx[k] = malloc(room * sizeof(double));
        if (ap[k] == NULL || ai[k] == NULL || ax[k] == NULL || cp[k] == NULL || ci[k] == NULL || cx[k] == NULL)
            goto out;
        face_body_rows(rows, jp, ji, jd, weight, index, k ? slide : NULL, ap[k], ai[k], ax[k]);
        if (slides && k == 0) {
            /* A body one or two unknowns push (a row of J^T holds an entry for each, zero or not)
             * is free in K along the directions its pushes leave: those are taken out of R's rows
             * and given a column of their own in both (face_body_ridge_columns), so that K and G
             * are of full rank on the rest, where L R^T is a full-rank factorization. */
            double scale = 0.0;
            for (int32_t p = 0; p < ap[0][rows]; p++)
                scale += ax[0][p] * ax[0][p];
            scale = rows ? scale / (double)rows : 0.0; /* K's mean diagonal */
            for (int32_t q = 0; q + 2 < rows; q += 3) {
                const int32_t pushes = ap[0][q + 1] - ap[0][q];
                if (pushes > 0 && pushes < 3) {
                    const int found = face_body_free_directions(ap[0], ax[0], q, dirs + 3 * n_free);
                    for (int t = 0; t < found; t++)
                        free_rows[n_free++] = q;
                }
            }
            face_body_ridge_columns(rows, ap[0], ai[0], ax[0], n_free, free_rows, dirs, m, scale, 0);
        } else if (k == 1) {
            double scale = 0.0;
            for (int32_t p = 0; p < ap[1][rows]; p++)
                scale += ax[1][p] * ax[1][p];
            scale = rows ? scale / (double)rows : 0.0; /* G's mean diagonal */
            face_body_ridge_columns(rows, ap[1], ai[1], ax[1], n_free, free_rows, dirs, m, scale, 1);
        }
        /* by columns (the free directions' after the unknowns): by its rows */
        spchol_transpose(rows, (int32_t)(m + n_free), ap[k], ai[k], ax[k], cp[k], ci[k], cx[k]);
        int free_direction = 0;
        double mean_diagonal = 0.0;
        int factored = face_body_factor(rows, ap[k], ai[k], ax[k], cp[k], ci[k], cx[k], order, ridge, inverse, &mp[k],
                                        &mi[k], &mx[k], &f[k], &free_direction, &mean_diagonal);
        if (factored == 3) { /* no unknown moves a body: S = 0, and 0 the least of its answers */
            memset(x, 0, (size_t)m * sizeof(double));
            status = 0;
            goto out;
        }
        if (factored != 0) {
            status = factored > 0 ? 1 : -1;
            goto out;
        }
        if (slides && free_direction && k == 0 && m > rows) {
            /* Free directions no one body's pushes leave (boxes sliding together): read off K's
             * factor; R's side is kept off them below (face_body_off_shared). K's side needs
             * nothing: its ridged solve keeps a vector in K's range (face_body_pinv). Only
             * where the face has more unknowns than its bodies have freedoms (a pile held at
             * two points a face, whose dual's S S^T joins every two points two bodies apart): a
             * pile of discs, held at about a point a pair, leaves dozens of such directions, and
             * its dual costs less than finding them. */
            shared = malloc((size_t)FACE_BODY_MOST_SHARED * (size_t)rows * sizeof(double) + sizeof(double));
            double *scratch = malloc(((size_t)rows + 1) * sizeof(double));
            if (shared == NULL || scratch == NULL) {
                free(scratch);
                goto out;
            }
            n_shared = face_body_shared_directions(rows, &f[0], ap[0], order, mp[0], mi[0], mx[0], mean_diagonal, n_free,
                                                   free_rows, dirs, shared, scratch);
            free(scratch);
            if (n_shared <= 0) {
                status = n_shared == -1 ? -1 : 1;
                goto out;
            }
        } else if (slides && free_direction && n_shared == 0) {
            /* G leaves a direction free. With shared directions set apart it may be one of
             * theirs, which face_body_off_shared keeps the answer off (the test at the end
             * tells); without, the product is not the pseudo-inverse. */
            status = 1;
            goto out;
        }
    }
    /* R's side: L's where no point slides. Vectors over the columns run to m + n_free, the free
     * directions' entries 0: b's and x's have none there. */
    const int r_ = sides - 1;
    const int64_t columns = m + n_free;
    work = calloc((size_t)4 * rows + 3 * (size_t)columns + 1, sizeof(double));
    if (work == NULL)
        goto out;
    double *y = work, *r = work + rows, *z = work + 2 * rows, *u = work + 3 * rows, *v = work + 4 * rows;
    double *b = v + columns, *xe = b + columns;
    memcpy(b, rhs, (size_t)m * sizeof(double));
    for (int32_t q = 0; q < rows; q++) { /* y = L^T b, in the factors' order (one order, one inverse) */
        double s_ = 0.0;
        for (int32_t p = ap[0][q]; p < ap[0][q + 1]; p++)
            s_ += ax[0][p] * b[ai[0][p]];
        y[inverse[q]] = s_;
    }
    face_body_pinv(rows, &f[0], mp[0], mi[0], mx[0], inverse, refinements, y, r, z);
    if (n_shared == 0)
        face_body_pinv(rows, &f[r_], mp[r_], mi[r_], mx[r_], inverse, refinements, y, r, z);
    else {
        const int off = face_body_off_shared(rows, &f[1], mp[1], mi[1], mx[1], inverse, refinements, n_shared,
                                             shared, y);
        if (off != 0) {
            status = off < 0 ? -1 : 1;
            goto out;
        }
    }
    for (int64_t c = 0; c < m; c++) { /* x = R y */
        double s_ = 0.0;
        for (int32_t q = cp[r_][c]; q < cp[r_][c + 1]; q++)
            s_ += cx[r_][q] * y[inverse[ci[r_][q]]];
        xe[c] = x[c] = s_;
    }
    /* The dual's test, with S = L R^T: |S^T (S x - b)| = |R L^T (L R^T x - b)| against |R L^T b|
     * (R's rows taken off the free directions change neither product: L P = L). */
    for (int32_t q = 0; q < rows; q++) { /* u = R^T x */
        double s_ = 0.0;
        for (int32_t p = ap[r_][q]; p < ap[r_][q + 1]; p++)
            s_ += ax[r_][p] * xe[ai[r_][p]];
        u[q] = s_;
    }
    for (int64_t c = 0; c < m; c++) { /* v = L u - b */
        double s_ = 0.0;
        for (int32_t q = cp[0][c]; q < cp[0][c + 1]; q++)
            s_ += cx[0][q] * u[ci[0][q]];
        v[c] = s_ - rhs[c];
    }
    double norms[2] = {0.0, 0.0};
    const double *of[2] = {v, b};
    for (int k = 0; k < 2; k++) { /* |R L^T t| for t = v, then b */
        for (int32_t q = 0; q < rows; q++) {
            double s_ = 0.0;
            for (int32_t p = ap[0][q]; p < ap[0][q + 1]; p++)
                s_ += ax[0][p] * of[k][ai[0][p]];
            u[q] = s_;
        }
        for (int64_t c = 0; c < m; c++) {
            double s_ = 0.0;
            for (int32_t q = cp[r_][c]; q < cp[r_][c + 1]; q++)
                s_ += cx[r_][q] * u[ci[r_][q]];
            norms[k] += s_ * s_;
        }
    }
    status = sqrt(norms[0]) <= optimality * sqrt(norms[1]) ? 0 : 2;
out:
    for (int k = 0; k < 2; k++) {
        spchol_free(&f[k]);
        free(ap[k]), free(ai[k]), free(ax[k]), free(cp[k]), free(ci[k]), free(cx[k]);
        free(mp[k]), free(mi[k]), free(mx[k]);
    }
    free(inverse), free(work), free(free_rows), free(dirs), free(shared);
    return status;
}

#endif
