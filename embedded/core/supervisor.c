/* cochlea embedded runtime: the safety supervisor, the Python one's rules in C
 * (cochlea/runtime/supervisor.py). Checks allocate nothing and call no library function but
 * sqrt from libm. */
#include "cochlea_rt.h"

#include <math.h>

#ifdef COCHLEA_FLOAT
#define SQRT sqrtf /* VSQRT.F32 on a single-precision FPU */
#define FABS fabsf
#else
#define SQRT sqrt
#define FABS fabs
#endif

static const char *const RULE_NAMES[COCHLEA_RULE_COUNT] = {
    "none", "completed", "user-stop", "position-limit", "velocity-limit", "keep-out",
    "non-finite", "estimate-bound", "watchdog", "terminated", "log-failure"};
static const int EXIT_CODES[COCHLEA_RULE_COUNT] = {0, 0, 0, 10, 11, 12, 13, 14, 15, 16, 17};

int cochlea_exit_code(int rule)
{
    return (rule >= 0 && rule < COCHLEA_RULE_COUNT) ? EXIT_CODES[rule] : COCHLEA_EXIT_BACKEND;
}

const char *cochlea_rule_name(int rule)
{
    return (rule >= 0 && rule < COCHLEA_RULE_COUNT) ? RULE_NAMES[rule] : "unknown";
}

static void stop_at(cochlea_stop *stop, int rule, cochlea_real t)
{
    stop->rule = rule;
    stop->time_s = t;
    stop->period = -1; /* the loop's: it knows k */
    stop->joint = -1;
    stop->unit = -1;
    stop->what = 0;
    stop->value = COCHLEA_R(0.0);
    stop->limit = COCHLEA_R(0.0);
    stop->point[0] = stop->point[1] = COCHLEA_R(0.0);
    stop->centre[0] = stop->centre[1] = COCHLEA_R(0.0);
    stop->count = 0;
    stop->reason = 0;
}

/* The sum of squares of v (infinite when finite values' squares overflow). */
static cochlea_real squares(const cochlea_real *v, int n)
{
    cochlea_real s = COCHLEA_R(0.0);
    int i;
    for (i = 0; i < n; ++i) {
        s += v[i] * v[i];
    }
    return s;
}

/* Every value finite, however large, as the Python supervisor judges it; tested on the bits
 * (cochlea_fp.h): no compiler assumption can fold it away. */
static int all_finite(const cochlea_real *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        if (!cochlea_finite_real(v[i])) {
            return 0;
        }
    }
    return 1;
}

/* |v| without overflow where its sum of squares overflows: scaled by the largest |v_i|. */
static cochlea_real scaled_norm(const cochlea_real *v, int n)
{
    cochlea_real largest = COCHLEA_R(0.0), s = COCHLEA_R(0.0);
    int i;
    for (i = 0; i < n; ++i) {
        if (FABS(v[i]) > largest) {
            largest = FABS(v[i]);
        }
    }
    if (!(largest > COCHLEA_R(0.0))) {
        return COCHLEA_R(0.0);
    }
    for (i = 0; i < n; ++i) {
        const cochlea_real r = v[i] / largest;
        s += r * r;
    }
    return largest * SQRT(s);
}

int cochlea_check_state(const cochlea_limits *limits, cochlea_real t, const cochlea_real *q,
                        const cochlea_real *qd, cochlea_stop *stop)
{
    const int n = limits->n_joints;
    int j;
    if (!all_finite(q, n) || !all_finite(qd, n)) {
        stop_at(stop, COCHLEA_NON_FINITE, t);
        for (j = 0; j < n; ++j) {
            if (!cochlea_finite_real(q[j]) || !cochlea_finite_real(qd[j])) {
                stop->joint = j;
                break;
            }
        }
        return 1;
    }
    for (j = 0; j < n; ++j) {
        if (q[j] < limits->position_lo[j] || q[j] > limits->position_hi[j]) {
            stop_at(stop, COCHLEA_POSITION_LIMIT, t);
            stop->joint = j;
            stop->value = q[j];
            stop->limit = q[j] < limits->position_lo[j] ? limits->position_lo[j]
                                                        : limits->position_hi[j];
            return 1;
        }
    }
    for (j = 0; j < n; ++j) {
        if (FABS(qd[j]) > limits->velocity[j]) {
            stop_at(stop, COCHLEA_VELOCITY_LIMIT, t);
            stop->joint = j;
            stop->value = qd[j];
            stop->limit = limits->velocity[j];
            return 1;
        }
    }
    return 0;
}

int cochlea_check_keep_out(const cochlea_limits *limits, cochlea_real t, int n_points,
                           const cochlea_real *points, const cochlea_real *centres,
                           cochlea_stop *stop)
{
    int i;
    if (!(limits->keep_out_radius > COCHLEA_R(0.0))) {
        return 0;
    }
    for (i = 0; i < n_points; ++i) {
        const cochlea_real du = points[2 * i] - centres[2 * i];
        const cochlea_real dv = points[2 * i + 1] - centres[2 * i + 1];
        const cochlea_real r = SQRT(du * du + dv * dv);
        /* A NaN distance is not inside the circle here: the state check catches it first. */
        if (r < limits->keep_out_radius) {
            stop_at(stop, COCHLEA_KEEP_OUT, t);
            stop->unit = i;
            stop->value = r;
            stop->limit = limits->keep_out_radius;
            stop->point[0] = points[2 * i];
            stop->point[1] = points[2 * i + 1];
            stop->centre[0] = centres[2 * i];
            stop->centre[1] = centres[2 * i + 1];
            return 1;
        }
    }
    return 0;
}

int cochlea_check_command(const cochlea_limits *limits, cochlea_real t, const cochlea_real *tau,
                          int n_units, const cochlea_real *const *estimates,
                          const int *n_params, const cochlea_real *bounds, cochlea_stop *stop)
{
    int u;
    /* A command whose squares overflow (an effort past about 1e154 in double, 1.8e19 in
     * float: a controller that has blown up) is stopped as a non-finite one, not clipped. */
    if (!cochlea_finite_real(squares(tau, limits->n_joints))) {
        stop_at(stop, COCHLEA_NON_FINITE, t);
        stop->what = 1;
        return 1;
    }
    for (u = 0; u < n_units; ++u) {
        const cochlea_real tolerated = bounds[u] * (COCHLEA_R(1.0) + COCHLEA_ESTIMATE_TOLERANCE);
        const cochlea_real square = squares(estimates[u], n_params[u]);
        const int overflowed = !cochlea_finite_real(square);
        if (overflowed && !all_finite(estimates[u], n_params[u])) {
            stop_at(stop, COCHLEA_NON_FINITE, t);
            stop->what = 2;
            stop->unit = u;
            return 1;
        }
        /* finite values whose squares overflow are beyond any bound: estimate-bound */
        if (overflowed || square > tolerated * tolerated) {
            stop_at(stop, COCHLEA_ESTIMATE_BOUND, t);
            stop->unit = u;
            stop->value = overflowed ? scaled_norm(estimates[u], n_params[u]) : SQRT(square);
            stop->limit = bounds[u];
            return 1;
        }
    }
    return 0;
}

int cochlea_saturate(const cochlea_limits *limits, cochlea_real *tau)
{
    int j, clipped = 0;
    for (j = 0; j < limits->n_joints; ++j) {
        const cochlea_real lim = limits->effort[j];
        if (tau[j] > lim) {
            tau[j] = lim;
            ++clipped;
        } else if (tau[j] < -lim) {
            tau[j] = -lim;
            ++clipped;
        }
    }
    return clipped;
}
