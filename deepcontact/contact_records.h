/* The engine's records as the compiled kernels read them: BODY_DTYPE (48 bytes) and
 * CONTACT_DTYPE (64 bytes) of deepcontact/records.py, field by byte offset, and a contact
 * point's frame and relative velocity. deepcontact.kinematics checks the offsets against the
 * dtypes when it imports its compiled module. Shared by deepcontact/_kinematics.c and
 * deepcontact/_route.c; float32 fields are widened to float64 before any arithmetic.
 */

#ifndef DEEPCONTACT_CONTACT_RECORDS_H
#define DEEPCONTACT_CONTACT_RECORDS_H

#include <stdint.h>
#include <string.h>

enum {
    BODY_SIZE = 48,
    BODY_TYPE = 4,
    BODY_POSITION = 8,
    BODY_VELOCITY = 20,
    BODY_ANGULAR_VELOCITY = 28,
    BODY_MASS = 32,
    BODY_INERTIA = 36,
    POINT_SIZE = 64,
    POINT_KEY = 0,
    POINT_BODY_A = 8,
    POINT_BODY_B = 12,
    POINT_POINT = 16,
    POINT_NORMAL = 24,
    POINT_BUILTIN = 36,
};
enum { BODY_STATIC = 0, BODY_DYNAMIC = 2 };  /* Box2D's b2BodyType; 1 is kinematic */

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

/* One point's frame: the body rows, normal, tangent (n rotated by -90 degrees) and lever
 * arms (m), as kinematics.contact_frame computes them. */
struct frame {
    int64_t a, b;
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

/* The relative velocities after impulses act, (P, 2) out (kinematics.velocities_before_and_after):
 * given (2 P,) N s, or NULL for each point's builtin field; vx, vy, w (B,) the velocities before
 * them; inv_m, inv_i (B,). Every point's share on body B is summed first, in point order, then
 * every share on A, and each body's sum divided by its mass last: np.bincount's order, so the
 * numbers are NumPy's to the bit. dvx, dvy, dw (B,) are scratch, left holding the bodies'
 * velocities after. */
static void velocities_after_impulses(const char *bodies, const char *points, int64_t n_points, int64_t n_bodies,
                                      const double *vx, const double *vy, const double *w, const double *inv_m,
                                      const double *inv_i, const double *given, double *dvx, double *dvy, double *dw,
                                      double *out)
{
    struct frame f;
    memset(dvx, 0, (size_t)n_bodies * sizeof(double));
    memset(dvy, 0, (size_t)n_bodies * sizeof(double));
    memset(dw, 0, (size_t)n_bodies * sizeof(double));
    for (int side = 0; side < 2; side++) { /* B's shares, then A's, as np.bincount(concat(b, a)) */
        for (int64_t i = 0; i < n_points; i++) {
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
    for (int64_t k = 0; k < n_bodies; k++) {
        dvx[k] = vx[k] + dvx[k] * inv_m[k];
        dvy[k] = vy[k] + dvy[k] * inv_m[k];
        dw[k] = w[k] + dw[k] * inv_i[k];
    }
    for (int64_t i = 0; i < n_points; i++) {
        frame_of(points + i * POINT_SIZE, bodies, &f);
        relative_velocity(&f, dvx, dvy, dw, out + 2 * i);
    }
}

/* Whether every point's bodies are rows of the n_bodies records. */
static inline int points_in_range(const char *points, int64_t n_points, int64_t n_bodies)
{
    for (int64_t i = 0; i < n_points; i++) {
        const char *p = points + i * POINT_SIZE;
        const int32_t a = i32_at(p, POINT_BODY_A), b = i32_at(p, POINT_BODY_B);
        if (a < 0 || b < 0 || a >= n_bodies || b >= n_bodies)
            return 0;
    }
    return 1;
}

#endif
