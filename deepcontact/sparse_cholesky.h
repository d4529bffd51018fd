/* A sparse Cholesky factorization and what it needs: a fill-reducing order (reverse
 * Cuthill-McKee), the elimination tree, the factor's pattern and numbers, and solves with it.
 * Shared by deepcontact/_faces.c (the face solve's dual, S S^T) and deepcontact/_admission.c
 * (the admission's G = J^T J): both matrices come from a pile's contacts, a few per cent full,
 * and their factors, in a reverse Cuthill-McKee order, hold a tenth to a fifth of a dense
 * factor's entries (a thesis step of 170 points: S S^T of order 274, 5,400 entries against
 * 37,700), so factoring and solving cost a small share of LAPACK's dense work.
 *
 * The factorization is up-looking: row k of L solves L[0:k, 0:k] l = A[0:k, k], the pattern
 * of l read off the elimination tree (the rows whose columns row k's entries reach), so L's
 * columns fill in row order and each column holds its diagonal first. Matrices are CSC,
 * int32 indices, float64 values; every function here is static and allocates nothing the
 * caller does not free (spchol_free). Functions return 0 on success, -1 where memory ran out,
 * and spchol_factor 1 where a pivot is not positive (the matrix is not positive definite to
 * rounding: the caller solves another way).
 */

#ifndef DEEPCONTACT_SPARSE_CHOLESKY_H
#define DEEPCONTACT_SPARSE_CHOLESKY_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* A reverse Cuthill-McKee order of the graph on n nodes with adjacency lists adj[adjp[u] ..
 * adjp[u + 1]) (each edge in both lists; repeats and self loops allowed): each connected part
 * walked breadth first from one of its nodes of least degree, a node's unvisited neighbours in
 * order of increasing degree (ties by index), the whole reversed. order (n,) out: new position
 * -> node. Returns 0, or -1 where memory ran out. */
static int spchol_rcm(int32_t n, const int32_t *adjp, const int32_t *adj, int32_t *order)
{
    int32_t *degree = calloc((size_t)n + 1, sizeof(int32_t));
    int32_t *mark = calloc((size_t)n + 1, sizeof(int32_t));
    char *seen = calloc((size_t)n + 1, 1);
    if (degree == NULL || mark == NULL || seen == NULL) {
        free(degree);
        free(mark);
        free(seen);
        return -1;
    }
    for (int32_t u = 0; u < n; u++) { /* distinct neighbours, not itself */
        int32_t d = 0;
        for (int32_t k = adjp[u]; k < adjp[u + 1]; k++) {
            int32_t v = adj[k];
            if (v != u && mark[v] != u + 1) {
                mark[v] = u + 1;
                d++;
            }
        }
        degree[u] = d;
    }
    int32_t placed = 0;
    while (placed < n) {
        int32_t root = -1;
        for (int32_t u = 0; u < n; u++)
            if (!seen[u] && (root < 0 || degree[u] < degree[root]))
                root = u;
        seen[root] = 1;
        int32_t head = placed;
        order[placed++] = root;
        while (head < placed) {
            int32_t u = order[head++], first = placed;
            for (int32_t k = adjp[u]; k < adjp[u + 1]; k++)
                if (!seen[adj[k]]) {
                    seen[adj[k]] = 1;
                    order[placed++] = adj[k];
                }
            for (int32_t x = first + 1; x < placed; x++) { /* by degree, then index */
                int32_t v = order[x], y = x;
                while (y > first && (degree[order[y - 1]] > degree[v]
                                     || (degree[order[y - 1]] == degree[v] && order[y - 1] > v))) {
                    order[y] = order[y - 1];
                    y--;
                }
                order[y] = v;
            }
        }
    }
    for (int32_t k = 0; k < n / 2; k++) {
        int32_t swap = order[k];
        order[k] = order[n - 1 - k];
        order[n - 1 - k] = swap;
    }
    free(degree);
    free(mark);
    free(seen);
    return 0;
}

/* A A^T (n x n, whole, CSC: Gp (n + 1,), Gi, Gx, malloc'd here) of A (n x c) given by rows
 * (CSR: Ap, Ai, Ax) and by columns (CSC: Bp, Bi, Bx): column i of the product sums, over A's
 * entries (i, k), A[:, k] A[i, k]. *trace out: its diagonal's sum. Returns 0, or -1 where
 * memory ran out (nothing left allocated). */
static int spchol_gram(int32_t n, const int32_t *Ap, const int32_t *Ai, const double *Ax, const int32_t *Bp,
                       const int32_t *Bi, const double *Bx, int32_t **Gp, int32_t **Gi, double **Gx, double *trace)
{
    int64_t room = 0;
    for (int32_t i = 0; i < n; i++)
        for (int32_t p = Ap[i]; p < Ap[i + 1]; p++)
            room += Bp[Ai[p] + 1] - Bp[Ai[p]];
    int32_t *marker = malloc(((size_t)n + 1) * sizeof(int32_t));
    double *acc = calloc((size_t)n + 1, sizeof(double));
    *Gp = malloc(((size_t)n + 1) * sizeof(int32_t));
    *Gi = room < INT32_MAX ? malloc(((size_t)room + 1) * sizeof(int32_t)) : NULL;
    *Gx = room < INT32_MAX ? malloc(((size_t)room + 1) * sizeof(double)) : NULL;
    if (marker == NULL || acc == NULL || *Gp == NULL || *Gi == NULL || *Gx == NULL) {
        free(marker);
        free(acc);
        free(*Gp);
        free(*Gi);
        free(*Gx);
        *Gp = *Gi = NULL;
        *Gx = NULL;
        return -1;
    }
    for (int32_t i = 0; i < n; i++)
        marker[i] = -1;
    *trace = 0.0;
    (*Gp)[0] = 0;
    int32_t at = 0;
    for (int32_t i = 0; i < n; i++) {
        int32_t begin = at;
        for (int32_t p = Ap[i]; p < Ap[i + 1]; p++) {
            int32_t c = Ai[p];
            for (int32_t q = Bp[c]; q < Bp[c + 1]; q++) {
                int32_t j = Bi[q];
                if (marker[j] != i) {
                    marker[j] = i;
                    (*Gi)[at++] = j;
                    acc[j] = 0.0;
                }
                acc[j] += Bx[q] * Ax[p];
            }
        }
        for (int32_t q = begin; q < at; q++)
            (*Gx)[q] = acc[(*Gi)[q]];
        (*Gp)[i + 1] = at;
        if (marker[i] == i)
            *trace += acc[i];
    }
    free(marker);
    free(acc);
    return 0;
}

/* A's columns (CSC: Bp (c + 1,), Bi, Bx, of entry count Ap[n]) from its rows (CSR: Ap, Ai,
 * Ax), rows ascending within each column. Bp must hold c + 2 zeros on entry. */
static void spchol_transpose(int32_t n, int32_t c, const int32_t *Ap, const int32_t *Ai, const double *Ax,
                             int32_t *Bp, int32_t *Bi, double *Bx)
{
    for (int32_t p = 0; p < Ap[n]; p++)
        Bp[Ai[p] + 2]++;
    for (int32_t j = 0; j < c; j++)
        Bp[j + 2] += Bp[j + 1];
    for (int32_t i = 0; i < n; i++)
        for (int32_t p = Ap[i]; p < Ap[i + 1]; p++) {
            int32_t at = Bp[Ai[p] + 1]++;
            Bi[at] = i;
            Bx[at] = Ax[p];
        }
}

/* A minimum degree order of the graph on n nodes with adjacency lists adj[adjp[u] .. adjp[u +
 * 1]) (each edge in both lists; repeats and self loops allowed): the node of least degree in
 * the graph left is eliminated next, its neighbours joined to one another (the fill its
 * elimination makes), ties to the node that reached that degree last. On a pile's body graph
 * (the admission's G = J^T J) its Cholesky factor holds about a third fewer entries than in a
 * reverse Cuthill-McKee order (3,000 against 4,300 at a thesis step of 170 points); on the
 * denser S S^T of the face solve a tenth fewer, for several times the ordering's time. The
 * graph is kept as one bitset a node, so each elimination costs its degree times n / 64 words.
 * order (n,) out: position -> node. Returns 0, or -1 where memory ran out. */
static int spchol_min_degree(int32_t n, const int32_t *adjp, const int32_t *adj, int32_t *order)
{
    const int32_t words = (n + 63) / 64;
    uint64_t *bits = calloc((size_t)n * (size_t)(words ? words : 1) + 1, sizeof(uint64_t));
    int32_t *degree = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *head = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *next = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *prev = malloc(((size_t)n + 1) * sizeof(int32_t));
    if (bits == NULL || degree == NULL || head == NULL || next == NULL || prev == NULL) {
        free(bits), free(degree), free(head), free(next), free(prev);
        return -1;
    }
#define ROW(u) (bits + (size_t)(u) * (size_t)words)
    for (int32_t u = 0; u < n; u++)
        for (int32_t k = adjp[u]; k < adjp[u + 1]; k++)
            if (adj[k] != u)
                ROW(u)[adj[k] >> 6] |= (uint64_t)1 << (adj[k] & 63);
    for (int32_t d = 0; d <= n; d++)
        head[d] = -1;
    /* Each node on the list of its degree (doubly linked, pushed at the head). */
#define UNLINK(u)                                                                                  \
    do {                                                                                           \
        if (prev[u] >= 0)                                                                          \
            next[prev[u]] = next[u];                                                               \
        else                                                                                       \
            head[degree[u]] = next[u];                                                             \
        if (next[u] >= 0)                                                                          \
            prev[next[u]] = prev[u];                                                               \
    } while (0)
#define LINK(u)                                                                                    \
    do {                                                                                           \
        prev[u] = -1;                                                                              \
        next[u] = head[degree[u]];                                                                 \
        if (next[u] >= 0)                                                                          \
            prev[next[u]] = u;                                                                     \
        head[degree[u]] = u;                                                                       \
    } while (0)
    for (int32_t u = n - 1; u >= 0; u--) {
        int32_t d = 0;
        for (int32_t w = 0; w < words; w++)
            d += __builtin_popcountll(ROW(u)[w]);
        degree[u] = d;
        LINK(u);
    }
    int32_t least = 0;
    for (int32_t placed = 0; placed < n; placed++) {
        while (head[least] < 0)
            least++;
        const int32_t v = head[least];
        UNLINK(v);
        order[placed] = v;
        const uint64_t *nb = ROW(v);
        for (int32_t w = 0; w < words; w++)
            for (uint64_t word = nb[w]; word; word &= word - 1) {
                const int32_t u = w * 64 + __builtin_ctzll(word);
                uint64_t *row = ROW(u);
                int32_t d = 0;
                for (int32_t x = 0; x < words; x++) {
                    row[x] |= nb[x];
                    if (x == (u >> 6))
                        row[x] &= ~((uint64_t)1 << (u & 63));
                    if (x == (v >> 6))
                        row[x] &= ~((uint64_t)1 << (v & 63));
                    d += __builtin_popcountll(row[x]);
                }
                UNLINK(u);
                degree[u] = d;
                LINK(u);
                if (d < least)
                    least = d;
            }
    }
#undef LINK
#undef UNLINK
#undef ROW
    free(bits), free(degree), free(head), free(next), free(prev);
    return 0;
}

/* A factor L (n x n, lower, CSC: Lp (n + 1,), Li, Lx; each column's diagonal first). */
typedef struct {
    int32_t n;
    int32_t *Lp, *Li;
    double *Lx;
} spchol_factor_t;

static void spchol_free(spchol_factor_t *f)
{
    free(f->Lp);
    free(f->Li);
    free(f->Lx);
    f->Lp = f->Li = NULL;
    f->Lx = NULL;
}

/* The upper triangle (with the diagonal) of P A P^T as CSC, P the permutation `order` (new
 * position -> old index), from A given whole (both triangles, CSC; unsorted rows and repeats
 * summed later by the factorization's scatter). inverse (n,) out: old index -> new position.
 * Cp (n + 1,), Ci, Cx (A's entry count) out. Returns 0, or -1 where memory ran out. */
static int spchol_permute_upper(int32_t n, const int32_t *Ap, const int32_t *Ai, const double *Ax,
                                const int32_t *order, int32_t *inverse, int32_t *Cp, int32_t *Ci, double *Cx)
{
    int32_t *fill = malloc(((size_t)n + 1) * sizeof(int32_t));
    if (fill == NULL)
        return -1;
    for (int32_t k = 0; k < n; k++)
        inverse[order[k]] = k;
    memset(Cp, 0, ((size_t)n + 1) * sizeof(int32_t));
    for (int32_t j = 0; j < n; j++) /* entry (i, j) of A is (inverse i, inverse j) of C: kept where row <= column */
        for (int32_t p = Ap[j]; p < Ap[j + 1]; p++) {
            int32_t r = inverse[Ai[p]], c = inverse[j];
            if (r <= c)
                Cp[c + 1]++;
        }
    for (int32_t k = 0; k < n; k++)
        Cp[k + 1] += Cp[k];
    memcpy(fill, Cp, (size_t)n * sizeof(int32_t));
    for (int32_t j = 0; j < n; j++)
        for (int32_t p = Ap[j]; p < Ap[j + 1]; p++) {
            int32_t r = inverse[Ai[p]], c = inverse[j];
            if (r <= c) {
                Ci[fill[c]] = r;
                Cx[fill[c]++] = Ax[p];
            }
        }
    free(fill);
    return 0;
}

/* L L^T = C, C symmetric given by its upper triangle (CSC, Cp, Ci, Cx; repeats summed), with
 * `ridge` added to every diagonal entry. floor > 0: a pivot that rounding leaves below it is
 * taken as it (a matrix singular but for its ridge, whose null space the caller's products
 * remove again); floor 0: such a pivot fails. f out (spchol_free it). Returns 0, -1 (memory),
 * or 1 where a pivot is not positive. */
static int spchol_factor(int32_t n, const int32_t *Cp, const int32_t *Ci, const double *Cx, double ridge,
                         double floor, spchol_factor_t *f)
{
    f->n = n;
    f->Lp = NULL;
    f->Li = NULL;
    f->Lx = NULL;
    int status = -1;
    int32_t *parent = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *ancestor = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *mark = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *stack = malloc(((size_t)n + 1) * sizeof(int32_t));
    int32_t *count = calloc((size_t)n + 1, sizeof(int32_t));
    int32_t *next = malloc(((size_t)n + 1) * sizeof(int32_t));
    double *x = calloc((size_t)n + 1, sizeof(double));
    if (parent == NULL || ancestor == NULL || mark == NULL || stack == NULL || count == NULL || next == NULL
        || x == NULL)
        goto done;
    /* The elimination tree: k becomes the parent of the root of each subtree that an entry
     * (i, k), i < k, reaches (ancestor[] shortens the walks). */
    for (int32_t k = 0; k < n; k++) {
        parent[k] = -1;
        ancestor[k] = -1;
        for (int32_t p = Cp[k]; p < Cp[k + 1]; p++) {
            int32_t i = Ci[p];
            while (i != -1 && i < k) {
                int32_t up = ancestor[i];
                ancestor[i] = k;
                if (up == -1) {
                    parent[i] = k;
                    break;
                }
                i = up;
            }
        }
    }
    /* Row k's pattern, twice: first to count each column's entries, then to fill them. */
#define ROW_PATTERN(k, top)                                                                        \
    do {                                                                                           \
        top = n;                                                                                   \
        mark[k] = k;                                                                               \
        for (int32_t p_ = Cp[k]; p_ < Cp[k + 1]; p_++) {                                           \
            int32_t i_ = Ci[p_], len_ = 0;                                                         \
            if (i_ >= k)                                                                           \
                continue;                                                                          \
            for (; mark[i_] != k; i_ = parent[i_]) { /* up the tree to a node already marked */    \
                stack[len_++] = i_;                                                                \
                mark[i_] = k;                                                                      \
            }                                                                                      \
            while (len_ > 0) /* kept so that a column comes after the columns it needs */          \
                stack[--top] = stack[--len_];                                                      \
        }                                                                                          \
    } while (0)
    for (int32_t k = 0; k < n; k++)
        mark[k] = -1;
    for (int32_t k = 0; k < n; k++) {
        int32_t top;
        ROW_PATTERN(k, top);
        for (int32_t q = top; q < n; q++)
            count[stack[q]]++;
        count[k]++; /* the diagonal */
    }
    f->Lp = malloc(((size_t)n + 1) * sizeof(int32_t));
    if (f->Lp == NULL)
        goto done;
    f->Lp[0] = 0;
    for (int32_t k = 0; k < n; k++)
        f->Lp[k + 1] = f->Lp[k] + count[k];
    const int32_t entries = f->Lp[n];
    f->Li = malloc(((size_t)entries + 1) * sizeof(int32_t));
    f->Lx = malloc(((size_t)entries + 1) * sizeof(double));
    if (f->Li == NULL || f->Lx == NULL)
        goto done;
    for (int32_t k = 0; k < n; k++) {
        mark[k] = -1;
        next[k] = f->Lp[k];
    }
    status = 1;
    for (int32_t k = 0; k < n; k++) {
        int32_t top;
        ROW_PATTERN(k, top);
        double d = ridge;
        for (int32_t p = Cp[k]; p < Cp[k + 1]; p++) { /* x = C[0:k+1, k], scattered */
            if (Ci[p] < k)
                x[Ci[p]] += Cx[p];
            else if (Ci[p] == k)
                d += Cx[p];
        }
        for (int32_t q = top; q < n; q++) { /* row k of L, column by column */
            int32_t j = stack[q];
            double lkj = x[j] / f->Lx[f->Lp[j]];
            x[j] = 0.0;
            for (int32_t p = f->Lp[j] + 1; p < next[j]; p++)
                x[f->Li[p]] -= f->Lx[p] * lkj;
            d -= lkj * lkj;
            f->Li[next[j]] = k;
            f->Lx[next[j]++] = lkj;
        }
        if (floor > 0.0 && !(d >= floor))
            d = floor;
        if (!(d > 0.0))
            goto done;
        f->Li[next[k]] = k;
        f->Lx[next[k]++] = sqrt(d);
    }
#undef ROW_PATTERN
    status = 0;
done:
    if (status != 0)
        spchol_free(f);
    free(parent);
    free(ancestor);
    free(mark);
    free(stack);
    free(count);
    free(next);
    free(x);
    return status;
}

/* y = (L L^T)^-1 y, in place (n,). */
static void spchol_solve(const spchol_factor_t *f, double *y)
{
    const int32_t *Lp = f->Lp, *Li = f->Li;
    const double *Lx = f->Lx;
    for (int32_t j = 0; j < f->n; j++) {
        y[j] /= Lx[Lp[j]];
        for (int32_t p = Lp[j] + 1; p < Lp[j + 1]; p++)
            y[Li[p]] -= Lx[p] * y[j];
    }
    for (int32_t j = f->n - 1; j >= 0; j--) {
        double acc = y[j];
        for (int32_t p = Lp[j] + 1; p < Lp[j + 1]; p++)
            acc -= Lx[p] * y[Li[p]];
        y[j] = acc / Lx[Lp[j]];
    }
}

/* Y = (L L^T)^-1 Y for k right-hand sides at once, in place, Y (n, k) row-major (a row's k values
 * together): one walk over L's entries for all k, each entry's update a contiguous run of k,
 * where k solves one by one walk L k times. */
static void spchol_solve_many(const spchol_factor_t *f, double *y, int32_t k)
{
    const int32_t *Lp = f->Lp, *Li = f->Li;
    const double *Lx = f->Lx;
    for (int32_t j = 0; j < f->n; j++) {
        double *yj = y + (size_t)j * k;
        const double d = Lx[Lp[j]];
        for (int32_t t = 0; t < k; t++)
            yj[t] /= d;
        for (int32_t p = Lp[j] + 1; p < Lp[j + 1]; p++) {
            const double l = Lx[p];
            double *yi = y + (size_t)Li[p] * k;
            for (int32_t t = 0; t < k; t++)
                yi[t] -= l * yj[t];
        }
    }
    for (int32_t j = f->n - 1; j >= 0; j--) {
        double *yj = y + (size_t)j * k;
        for (int32_t p = Lp[j] + 1; p < Lp[j + 1]; p++) {
            const double l = Lx[p];
            const double *yi = y + (size_t)Li[p] * k;
            for (int32_t t = 0; t < k; t++)
                yj[t] -= l * yi[t];
        }
        const double d = Lx[Lp[j]];
        for (int32_t t = 0; t < k; t++)
            yj[t] /= d;
    }
}

#endif
