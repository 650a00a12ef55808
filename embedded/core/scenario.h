/* cochlea embedded runtime: a scenario as the runtime runs it.
 *
 * cochlea-codegen writes one cochlea_scenario per scenario (generated_c/embedded/
 * <name>_scenario.c, from the same scenario file as cochlea-run's) and the table of all of them
 * (scenarios.{h,c}). It puts the generated controller behind the runtime's interface in the
 * working precision (cochlea_real, cochlea_fp.h: the generated <name>_real of the same
 * build, passed through with no conversion), and carries what the loop and the run's
 * summary need: the drive table and limits of the robot, each unit's names and units, the
 * keep-out tool points.
 * Units are SI throughout: rad, m, rad/s, m/s, N m, N, s, kg.
 */
#ifndef COCHLEA_SCENARIO_H
#define COCHLEA_SCENARIO_H

#include <stddef.h>
#include <stdint.h>

#include "drives.h"

#ifdef __cplusplus
extern "C" {
#endif

/* One controlled unit (an arm, the mechanism). Offsets index the scenario's whole arrays. */
typedef struct {
    const char *name;                   /* "arm1", "mechanism" */
    const char *controller;             /* "g (corrected), task space" */
    int nq, nd, np, ne;                 /* joints, desired coordinates, parameters, errors */
    int q0, d0, p0, e0;                 /* first joint, coordinate, parameter, error */
    const char *const *tracked_names;   /* nd: the tracked coordinates ("x", "joint1") */
    const char *const *tracked_units;   /* nd: "m" or "rad" */
    const char *const *joint_names;     /* nq: "joint1" */
    const char *const *joint_units;     /* nq: "rad" or "m" */
    const char *const *param_names;     /* np: "link1.m" */
    const char *const *param_units;     /* np: "kg" */
    const double *p_nominal;            /* np: the description's values */
    double bound;                       /* the projection radius of |p_hat| */
    const char *error_names[2];         /* the two error blocks: "e_g", "e_v" */
    int tracking_sign;                  /* +1: first block = desired - actual; -1: reversed */
    int n_points;                       /* keep-out tool points */
    const char *const *point_labels;
} cochlea_unit_info;

typedef struct {
    const char *name, *robot, *space, *controller, *variant, *parameterisation;
    double period_s;                    /* the control period */
    double duration_s;                  /* the scenario's own run length */
    double keep_out_radius;             /* m; 0: no keep-out rule (no circle described) */
    int n_units;
    const cochlea_unit_info *units;
    int nq, nd, np, ne, n_points;       /* sizes of the whole scenario */
    const cochlea_drive *drives;        /* nq drives, in the joints' order */
    const double *position_lo, *position_hi, *velocity, *effort;  /* nq, the supervisor's */
    size_t state_size;                  /* bytes of the controller's state */
    int real_size;                      /* sizeof the working precision: 4 float, 8 double
                                         * (cochlea_loop_init refuses one that is not the
                                         * loop's cochlea_real) */
    /* Set p_hat to p_hat0 with the scenario's gains, for a loop of period period_s (the
     * estimate's Euler step); 0, or -1. */
    int (*init)(void *state, double period_s);
    /* One period: q, qd[nq] measured (unit after unit); command[nq] clipped to the effort
     * limits; errors[ne]. 0; -1 not initialised; 1 non-finite command or error; 2 non-finite
     * estimate (the state then unchanged). */
    int (*step)(void *state, double t, const cochlea_real *q, const cochlea_real *qd,
                cochlea_real *command, cochlea_real *errors);
    void (*terminate)(void *state);
    /* The desired trajectory at t: nd positions, velocities, accelerations (double: for the
     * report, outside the period). */
    int (*desired)(double t, double *xd, double *xd_dot, double *xd_ddot);
    /* The estimate p_hat the next period will use (np values, unit after unit; in the float
     * build the high part of its compensated two-float sum). */
    const cochlea_real *(*estimate)(const void *state);
    /* The keep-out tool points at q[nq]: (u, v) of each point and of its circle's centre. */
    int (*tool_points)(const cochlea_real *q, cochlea_real *points, cochlea_real *centres);
    /* 1: the bridge adds the fit's offset current to every command (it compensates the
     * gearbox's friction); 0: the controller's model carries friction and compensates it, so
     * the bridge must not (cochlea.robots.motor_fit.bridge_compensates_friction). */
    int bridge_offset_current;
    /* The loop's period k (t = k period_s): step at the period count instead of its time,
     * the loop's entry. The double build forms t = (double)k period_s exactly as the loop
     * does (the same command bit for bit); the float build evaluates the trajectory from k
     * without double (docs/embedded.md, "The float build"). NULL: the loop calls step (the
     * double build only: the float build's loop refuses a scenario without it). */
    int (*step_period)(void *state, int64_t k, const cochlea_real *q, const cochlea_real *qd,
                       cochlea_real *command, cochlea_real *errors);
    /* The run's log columns, named by the one schema of every log (cochlea/log_schema.py,
     * docs/logs.md): log.csv's header (n_log_columns names) and log.bin's columns
     * (n_raw_columns names, one per value of a row), and the schema's version. */
    int schema_version;
    int n_log_columns;
    const char *const *log_columns;
    int n_raw_columns;
    const char *const *raw_columns;
    /* Where the scenario starts the joints (nq, rad or m, the loop's order), or NULL: the
     * bridge's start-up refuses a robot standing farther from it than its tolerance
     * (cochlea_bridge.expected_start). */
    const double *initial_q;
} cochlea_scenario;

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_SCENARIO_H */
