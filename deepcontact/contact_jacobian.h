/* J^T of a step's contact points as CSR: R = 3 D rows, three for each dynamic body (x, y,
 * rotation), and 2 P columns, the normal and tangent direction of each point. A point's
 * direction d pushes its body B by +d and its body A by -d: on B's rows (d_x, d_y, rb x d), on
 * A's the negatives. A point between two parts of one body sums both. Each row's columns come
 * out in increasing order. Shared by deepcontact/_kinematics.c (kinematics.contact_jacobian_
 * sparse, the admission's J^T) and deepcontact/_route.c. In SciPy (a COO matrix made CSR) it
 * took about 0.17 ms at the thesis world's median step, most of it SciPy's checks and
 * conversions.
 */

#ifndef DEEPCONTACT_CONTACT_JACOBIAN_H
#define DEEPCONTACT_CONTACT_JACOBIAN_H

#include <stdint.h>
#include <string.h>

/* pa, pb (P,) body indices, checked; row (B,) each body's dynamic row or -1, below rows / 3;
 * n, t, ra, rb (2 P,) (x, y per point); rows = 3 D; out: indptr (rows + 1,), indices and data
 * of at least 12 P each. Returns the number of entries. */
static int64_t jacobian_transpose_csr(int64_t n_points, const int64_t *pa, const int64_t *pb, const int32_t *row,
                                      const double *n, const double *t, const double *ra, const double *rb,
                                      int64_t rows, int32_t *indptr, int32_t *indices, double *data)
{
    /* Entries a row: each of its body's points, two directions (one body counted once per point). */
    memset(indptr, 0, (size_t)(rows + 1) * sizeof(int32_t));
    for (int64_t i = 0; i < n_points; i++) {
        int32_t ra_row = row[pa[i]], rb_row = row[pb[i]];
        if (rb_row >= 0)
            for (int k = 0; k < 3; k++)
                indptr[3 * rb_row + k + 1] += 2;
        if (ra_row >= 0 && ra_row != rb_row)
            for (int k = 0; k < 3; k++)
                indptr[3 * ra_row + k + 1] += 2;
    }
    for (int64_t r = 0; r < rows; r++)
        indptr[r + 1] += indptr[r];
    int64_t nnz = rows ? indptr[rows] : 0;
    /* Filled point by point, so each row's columns increase; indptr[r] walks to row r's end. */
    for (int64_t i = 0; i < n_points; i++) {
        const double *dirs[2] = {&n[2 * i], &t[2 * i]};
        int32_t ra_row = row[pa[i]], rb_row = row[pb[i]];
        for (int k = 0; k < 2; k++) {
            const double *d = dirs[k];
            double on_b[3] = {0.0, 0.0, 0.0}, on_a[3] = {0.0, 0.0, 0.0};
            if (rb_row >= 0) {
                on_b[0] = d[0];
                on_b[1] = d[1];
                on_b[2] = rb[2 * i] * d[1] - rb[2 * i + 1] * d[0];
            }
            if (ra_row >= 0) {
                on_a[0] = -d[0];
                on_a[1] = -d[1];
                on_a[2] = -(ra[2 * i] * d[1] - ra[2 * i + 1] * d[0]);
            }
            if (rb_row >= 0 && ra_row == rb_row) { /* both sides on one body: one entry, summed */
                for (int q = 0; q < 3; q++) {
                    int32_t at = indptr[3 * rb_row + q]++;
                    indices[at] = (int32_t)(2 * i + k);
                    data[at] = on_b[q] + on_a[q];
                }
                continue;
            }
            if (rb_row >= 0)
                for (int q = 0; q < 3; q++) {
                    int32_t at = indptr[3 * rb_row + q]++;
                    indices[at] = (int32_t)(2 * i + k);
                    data[at] = on_b[q];
                }
            if (ra_row >= 0)
                for (int q = 0; q < 3; q++) {
                    int32_t at = indptr[3 * ra_row + q]++;
                    indices[at] = (int32_t)(2 * i + k);
                    data[at] = on_a[q];
                }
        }
    }
    for (int64_t r = rows; r > 0; r--) /* each indptr[r] now holds row r's end: shift back */
        indptr[r] = indptr[r - 1];
    indptr[0] = 0;
    return nnz;
}

#endif
