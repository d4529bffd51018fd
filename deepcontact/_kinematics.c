/* Compiled core of deepcontact.kinematics: the contact points' relative velocities
 * and effective masses, read straight from the engine's records.
 *
 * deepcontact/kinematics.py owns the conventions and documents them; this is its
 * arithmetic. In NumPy the same quantities took about a hundred calls per step
 * (each a few microseconds on a few hundred points), the larger part of the
 * server's feature stage; here one call makes one pass over the bodies and two
 * over the points.
 *
 * Bit for bit what the NumPy implementation gave (tests/deepcontact/
 * test_kinematics.py keeps it as the reference): float32 fields are widened to
 * float64 before any arithmetic, every sum is taken in NumPy's order (the
 * warm start's impulses reach the bodies as np.bincount added them: every
 * point's share on body B first, in point order, then every share on body A),
 * and -ffp-contract=off (setup.py) keeps a*b+c from being fused. The models
 * were trained on these numbers, so serving them must not move a bit.
 *
 * Layout: `bodies` and `points` are C-contiguous arrays of BODY_DTYPE and
 * CONTACT_DTYPE (deepcontact/records.py); the field offsets below are checked
 * against those dtypes when kinematics.py imports this module. Outputs are
 * (P, 2) float64, written in place. Body indices are checked before use.
 *
 * Build: setup.py (`make setup` runs it through `pip install -e .`).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <time.h>

/* BODY_DTYPE (48 bytes) and CONTACT_DTYPE (64 bytes): byte offsets of the fields read. */
enum {
    BODY_SIZE = 48,
    BODY_TYPE = 4,
    BODY_POSITION = 8,
    BODY_VELOCITY = 20,
    BODY_ANGULAR_VELOCITY = 28,
    BODY_MASS = 32,
    BODY_INERTIA = 36,
    POINT_SIZE = 64,
    POINT_BODY_A = 8,
    POINT_BODY_B = 12,
    POINT_POINT = 16,
    POINT_NORMAL = 24,
    POINT_BUILTIN = 36,
};
enum { BODY_DYNAMIC = 2 };
enum { WARM_NONE = 0, WARM_BUILTIN = 1, WARM_GIVEN = 2 };

static inline double f32_at(const char *record, int offset)
{
    float x;
    memcpy(&x, record + offset, sizeof x);
    return (double)x;
}

static inline int32_t i32_at(const char *record, int offset)
{
    int32_t x;
    memcpy(&x, record + offset, sizeof x);
    return x;
}

/* 1/x where the body may take impulses and x > 0, else 0 (kinematics._inverse). */
static inline double inverse_of(double x, int ok)
{
    return (ok && x > 0.0) ? 1.0 / x : 0.0;
}

/* Per-body scratch, grown as needed, never shrunk: 8 float64 a body. */
static double *scratch = NULL;
static Py_ssize_t scratch_bodies = 0;

static double *body_scratch(Py_ssize_t n_bodies)
{
    if (n_bodies > scratch_bodies) {
        double *p = PyMem_Realloc(scratch, (size_t)n_bodies * 8 * sizeof(double));
        if (p == NULL) {
            PyErr_NoMemory();
            return NULL;
        }
        scratch = p;
        scratch_bodies = n_bodies;
    }
    return scratch;
}

/* One point's frame: the body rows, normal, tangent and lever arms (m). */
struct frame {
    Py_ssize_t a, b;
    double n0, n1, t0, t1, ra0, ra1, rb0, rb1;
};

static inline void frame_of(const char *point, const char *bodies, struct frame *f)
{
    f->a = i32_at(point, POINT_BODY_A);
    f->b = i32_at(point, POINT_BODY_B);
    const double p0 = f32_at(point, POINT_POINT), p1 = f32_at(point, POINT_POINT + 4);
    f->n0 = f32_at(point, POINT_NORMAL);
    f->n1 = f32_at(point, POINT_NORMAL + 4);
    f->t0 = f->n1;
    f->t1 = -f->n0;
    const char *ba = bodies + f->a * BODY_SIZE, *bb = bodies + f->b * BODY_SIZE;
    f->ra0 = p0 - f32_at(ba, BODY_POSITION);
    f->ra1 = p1 - f32_at(ba, BODY_POSITION + 4);
    f->rb0 = p0 - f32_at(bb, BODY_POSITION);
    f->rb1 = p1 - f32_at(bb, BODY_POSITION + 4);
}

/* Relative (normal, tangent) velocity at a point from the bodies' (vx, vy, w) rows. */
static inline void relative_velocity(const struct frame *f, const double *vx, const double *vy, const double *w,
                                     double *out)
{
    const double wa = w[f->a], wb = w[f->b];
    double rel0 = vx[f->b] - vx[f->a];
    double rel1 = vy[f->b] - vy[f->a];
    rel0 += wa * f->ra1 - wb * f->rb1;
    rel1 += wb * f->rb0 - wa * f->ra0;
    out[0] = rel0 * f->n0 + rel1 * f->n1;
    out[1] = rel0 * f->t0 + rel1 * f->t1;
}

/* point_kinematics(bodies, n_bodies, points, n_points, warm_mode, warm, dt, gx, gy,
 *                  velocities, warmed, masses) -> None
 *
 * bodies: n_bodies BODY_DTYPE records; points: n_points CONTACT_DTYPE records.
 * warm_mode: WARM_NONE, WARM_BUILTIN (the points' builtin field) or WARM_GIVEN
 *   (warm, (P, 2) float64 N s; otherwise pass an empty buffer).
 * dt (s), gx, gy (m/s^2): this step's gravity, added to dynamic bodies first when dt != 0.
 * velocities: (P, 2) float64 out, the relative velocity before any impulse, or an
 *   empty buffer for none; warmed: the same after the warm start (needs warm_mode
 *   != WARM_NONE), or empty; masses: (P, 2) float64 out, the effective masses, or empty.
 */
static PyObject *point_kinematics(PyObject *self, PyObject *args)
{
    Py_buffer bodies_buf, points_buf, warm_buf, vel_buf, warmed_buf, mass_buf;
    Py_ssize_t n_bodies, n_points;
    int warm_mode;
    double dt, gx, gy;
    if (!PyArg_ParseTuple(args, "y*ny*niy*dddw*w*w*", &bodies_buf, &n_bodies, &points_buf, &n_points, &warm_mode,
                          &warm_buf, &dt, &gx, &gy, &vel_buf, &warmed_buf, &mass_buf))
        return NULL;
    PyObject *result = NULL;
    const Py_ssize_t out_len = n_points * 2 * (Py_ssize_t)sizeof(double);
    if (bodies_buf.len != n_bodies * BODY_SIZE || points_buf.len != n_points * POINT_SIZE) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: bodies or points are not whole records");
        goto done;
    }
    if ((vel_buf.len && vel_buf.len != out_len) || (warmed_buf.len && warmed_buf.len != out_len) ||
        (mass_buf.len && mass_buf.len != out_len) || (warm_mode == WARM_GIVEN && warm_buf.len != out_len)) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: an impulse or output buffer is not (P, 2) float64");
        goto done;
    }
    if (warmed_buf.len && warm_mode == WARM_NONE) {
        PyErr_SetString(PyExc_ValueError, "_kinematics: warmed velocities need a warm start");
        goto done;
    }
    const char *bodies = bodies_buf.buf, *points = points_buf.buf;
    for (Py_ssize_t i = 0; i < n_points; i++) {
        const char *p = points + i * POINT_SIZE;
        const int32_t a = i32_at(p, POINT_BODY_A), b = i32_at(p, POINT_BODY_B);
        if (a < 0 || b < 0 || a >= n_bodies || b >= n_bodies) {
            PyErr_Format(PyExc_ValueError, "contact points name bodies outside 0..%zd", n_bodies - 1);
            goto done;
        }
    }
    double *s = body_scratch(n_bodies > 0 ? n_bodies : 1);
    if (s == NULL)
        goto done;
    /* Per body: velocity after gravity (vx, vy, w), inverse mass and inertia, and the
     * warm start's impulse summed on it (dvx, dvy, dw; then its velocity after). */
    double *vx = s, *vy = s + n_bodies, *w = s + 2 * n_bodies, *inv_m = s + 3 * n_bodies,
           *inv_i = s + 4 * n_bodies;
    for (Py_ssize_t k = 0; k < n_bodies; k++) {
        const char *body = bodies + k * BODY_SIZE;
        const int dynamic = i32_at(body, BODY_TYPE) == BODY_DYNAMIC;
        const double on = dynamic ? 1.0 : 0.0;
        vx[k] = f32_at(body, BODY_VELOCITY) * on;
        vy[k] = f32_at(body, BODY_VELOCITY + 4) * on;
        w[k] = f32_at(body, BODY_ANGULAR_VELOCITY) * on;
        if (dt != 0.0) {
            vx[k] += (dt * gx) * on;
            vy[k] += (dt * gy) * on;
        }
        inv_m[k] = inverse_of(f32_at(body, BODY_MASS), dynamic);
        inv_i[k] = inverse_of(f32_at(body, BODY_INERTIA), dynamic);
    }
    struct frame f;
    double *vel = vel_buf.len ? vel_buf.buf : NULL, *warmed = warmed_buf.len ? warmed_buf.buf : NULL,
           *mass = mass_buf.len ? mass_buf.buf : NULL;
    for (Py_ssize_t i = 0; i < n_points; i++) {
        if (!vel && !mass)
            break;
        frame_of(points + i * POINT_SIZE, bodies, &f);
        if (vel)
            relative_velocity(&f, vx, vy, w, vel + 2 * i);
        if (mass) {
            /* 1 / (1/m_A + 1/m_B + (r_A x d)^2 / I_A + (r_B x d)^2 / I_B), d = n then t. */
            const double d[2][2] = {{f.n0, f.n1}, {f.t0, f.t1}};
            for (int k = 0; k < 2; k++) {
                const double ca = f.ra0 * d[k][1] - f.ra1 * d[k][0];
                const double cb = f.rb0 * d[k][1] - f.rb1 * d[k][0];
                const double inv = inv_m[f.a] + inv_m[f.b] + inv_i[f.a] * (ca * ca) + inv_i[f.b] * (cb * cb);
                mass[2 * i + k] = inverse_of(inv, 1);
            }
        }
    }
    if (warmed) {
        /* The warm start's impulse summed on each body (N s, N m s), then its velocity after it. */
        double *dvx = s + 5 * n_bodies, *dvy = s + 6 * n_bodies, *dw = s + 7 * n_bodies;
        memset(dvx, 0, (size_t)n_bodies * 3 * sizeof(double));
        const double *given = warm_mode == WARM_GIVEN ? warm_buf.buf : NULL;
        for (int side = 0; side < 2; side++) { /* B's shares, then A's, as np.bincount(concat(b, a)) */
            for (Py_ssize_t i = 0; i < n_points; i++) {
                const char *p = points + i * POINT_SIZE;
                frame_of(p, bodies, &f);
                const double jn = given ? given[2 * i] : f32_at(p, POINT_BUILTIN);
                const double jt = given ? given[2 * i + 1] : f32_at(p, POINT_BUILTIN + 4);
                const double i0 = jn * f.n0 + jt * f.t0, i1 = jn * f.n1 + jt * f.t1;
                if (side == 0) {
                    dvx[f.b] += i0;
                    dvy[f.b] += i1;
                    dw[f.b] += f.rb0 * i1 - f.rb1 * i0;
                } else {
                    dvx[f.a] += -i0;
                    dvy[f.a] += -i1;
                    dw[f.a] += -(f.ra0 * i1 - f.ra1 * i0);
                }
            }
        }
        for (Py_ssize_t k = 0; k < n_bodies; k++) {
            dvx[k] = vx[k] + dvx[k] * inv_m[k];
            dvy[k] = vy[k] + dvy[k] * inv_m[k];
            dw[k] = w[k] + dw[k] * inv_i[k];
        }
        for (Py_ssize_t i = 0; i < n_points; i++) {
            frame_of(points + i * POINT_SIZE, bodies, &f);
            relative_velocity(&f, dvx, dvy, dw, warmed + 2 * i);
        }
    }
    result = Py_NewRef(Py_None);
done:
    PyBuffer_Release(&bodies_buf);
    PyBuffer_Release(&points_buf);
    PyBuffer_Release(&warm_buf);
    PyBuffer_Release(&vel_buf);
    PyBuffer_Release(&warmed_buf);
    PyBuffer_Release(&mass_buf);
    return result;
}

/* nearest_admissible's rounds (deepcontact.kinematics documents the problem): ADMM between
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
        PyErr_SetString(PyExc_ValueError, "_kinematics.admission_rounds: arrays of the wrong size or contents");
        goto done;
    }
    const int32_t *jp = b[0].buf, *ji = b[1].buf, *lp = b[3].buf, *li = b[4].buf, *up = b[6].buf, *ui = b[7].buf;
    const int32_t *perm_r = b[9].buf, *perm_c = b[10].buf;
    const double *jd = b[2].buf, *ld = b[5].buf, *ud = b[8].buf, *c = b[11].buf, *mu = b[12].buf, *keep = b[13].buf;
    double *z = b[14].buf;
    for (Py_ssize_t k = 0; k < rows; k++)
        if (perm_r[k] < 0 || perm_r[k] >= rows || perm_c[k] < 0 || perm_c[k] >= rows) {
            PyErr_SetString(PyExc_ValueError, "_kinematics.admission_rounds: a permutation out of range");
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

/* face_system's sum (deepcontact.kinematics documents the system): every ordered pair of a
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
        PyErr_SetString(PyExc_ValueError, "_kinematics.face_system_sum: arrays of the wrong size");
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
            PyErr_SetString(PyExc_ValueError, "_kinematics.face_system_sum: a body or an index out of range");
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
        PyErr_SetString(PyExc_ValueError, "_kinematics.sparse_gram: arrays of the wrong size");
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

/* nearest_admissible's factorization of G = J^T J + ridge I (kinematics.admission_factors) as
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
        PyErr_SetString(PyExc_ValueError, "_kinematics.envelope_cholesky: arrays of the wrong size or contents");
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
            PyErr_SetString(PyExc_ValueError, "_kinematics.envelope_cholesky: order is not a permutation");
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
    {"face_system_sum", face_system_sum, METH_VARARGS,
     "face_system's sum over the pairs of a dynamic body's pushes (see the C source)."},
    {"envelope_cholesky", envelope_cholesky, METH_VARARGS,
     "nearest_admissible's factorization, as admission_rounds takes it (see the C source)."},
    {"sparse_gram", sparse_gram, METH_VARARGS, "S S^T of a mostly-zero square system (see the C source)."},
    {"admission_rounds", admission_rounds, METH_VARARGS,
     "nearest_admissible's ADMM rounds on a factorized gram (see the C source)."},
    {"point_kinematics", point_kinematics, METH_VARARGS,
     "Relative velocities (before and after a warm start) and effective masses at contact points (see the C "
     "source)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "deepcontact._kinematics",
    "Compiled core of deepcontact.kinematics (contact velocities and effective masses).", -1, methods,
};

PyMODINIT_FUNC PyInit__kinematics(void)
{
    PyObject *mod = PyModule_Create(&module);
    if (mod == NULL)
        return NULL;
    const struct {
        const char *name;
        long value;
    } constants[] = {
        {"BODY_SIZE", BODY_SIZE},         {"BODY_TYPE", BODY_TYPE},
        {"BODY_POSITION", BODY_POSITION}, {"BODY_VELOCITY", BODY_VELOCITY},
        {"BODY_ANGULAR_VELOCITY", BODY_ANGULAR_VELOCITY},
        {"BODY_MASS", BODY_MASS},         {"BODY_INERTIA", BODY_INERTIA},
        {"POINT_SIZE", POINT_SIZE},       {"POINT_BODY_A", POINT_BODY_A},
        {"POINT_BODY_B", POINT_BODY_B},   {"POINT_POINT", POINT_POINT},
        {"POINT_NORMAL", POINT_NORMAL},   {"POINT_BUILTIN", POINT_BUILTIN},
        {"WARM_NONE", WARM_NONE},         {"WARM_BUILTIN", WARM_BUILTIN},
        {"WARM_GIVEN", WARM_GIVEN},
    };
    for (size_t k = 0; k < sizeof constants / sizeof constants[0]; k++) {
        if (PyModule_AddIntConstant(mod, constants[k].name, constants[k].value)) {
            Py_DECREF(mod);
            return NULL;
        }
    }
    return mod;
}
