/* cochlea all-in-C simulation: what simulate.c needs of a scenario.
 *
 * A scenario is compiled in through "sim_scenario.h", which bench/embedded_bench.py writes from
 * the scenario (build/embedded-sim/<scenario>/<precision>/sim_scenario.h), with sim_plant.c
 * beside it: each unit's plant period specialised to the scenario, its true parameters,
 * friction, dry friction and period folded in as literals (CasADi; the same results as the
 * general kernel, bit for bit, or within an ulp per sin and cos where SIM_INLINE_TRIG says so).
 * The header includes the scenario's embedded
 * controller (generated_c/embedded/<scenario>.h) and the headers of its pose kernels and of a
 * geared plant's kernel, which stays general (generated_c/<group>.h), and defines:
 *
 *   SIM_NAME            the scenario's name (a string)
 *   SIM_C(x)            the controller's identifier x: SIM_C(_step) is <scenario>_step
 *   SIM_CONTROLLER_SOURCE  the controller's source, "<scenario>.c", which simulate.c includes
 *                       (it calls the step's halves: the desired sample, then the step on it)
 *   SIM_UNITS, SIM_NQ, SIM_NX, SIM_ND, SIM_NP, SIM_NE
 *                       the controller's sizes (<SCENARIO>_UNITS, ...)
 *   SIM_NPOSE           logged pose coordinates, all units
 *   SIM_NXP             the plants' states, all units (SIM_NX, or more with the gearbox)
 *   SIM_PERIOD          s: the control period (the plant integrates one period per call)
 *   SIM_DURATION        s: the scenario's duration
 *   SIM_DELAY           periods of measurement delay
 *   SIM_JITTER          whole periods the delay jitters above SIM_DELAY ([plant]
 *                       delay_jitter_periods; 0: none), and then sim_jitter_seed
 *   SIM_ENCODER_COUNTS  whole encoder counts of position noise ([plant] encoder_noise_counts;
 *                       0: none), and then sim_encoder_seed
 *   SIM_INLINE_TRIG     1: sin and cos from sim_trig.h's sim_sincos (inline, within an ulp of
 *                       libm) in sim_plant.c and in the double build's controller; 0: libm
 *                       (bench/embedded_bench.py's inline_trig_applies says where)
 *   sim_jitter_seed[4], sim_encoder_seed[4]
 *                       the numpy PCG64 generator of each stream of the scenario's seed
 *                       (cochlea.sim.setup.disturbance_rng) as it starts: state and increment,
 *                       each as its high and low 64 bits
 *   sim_units[SIM_UNITS] one sim_unit per unit, in the controller's order
 *
 * Units: SI throughout (rad, m, rad/s, m/s, N m, N, s). */
#ifndef COCHLEA_SIM_H
#define COCHLEA_SIM_H

#include <stddef.h>
#include <stdint.h>

/* A generated kernel (CasADi's calling convention); the plant and pose kernels need no work
 * memory (iw and w are NULL). */
typedef int (*sim_kernel)(const double **arg, double **res, long long int *iw, double *w,
                          int mem);

/* One unit of the scenario: its plant, its start and how it is measured and driven. */
typedef struct {
    const char *name;
    int nq;    /* joints; the measured and logged state is x = [q, qd] (rad or m, rad/s or m/s) */
    int nxp;   /* the plant's state: 2 nq, or with the gearbox 4 nq ([q, qd, theta, theta_dot]:
                  the encoder on the link, so x is its first 2 nq) */
    int np;    /* estimated parameters */
    int nd;    /* desired coordinates */
    int ne;    /* errors */
    int npose; /* logged pose coordinates (m, rad) */
    /* x_next = plant(x, tau, p, friction, h[, coulomb]): the period (RK4 with the scenario's
     * sub-steps, or the geared plant's linearly implicit steps) on the plant's state; a plant
     * specialised to the scenario (sim_plant.c) reads x and tau only, the data below folded in */
    sim_kernel plant;
    sim_kernel pose;          /* pose = fk_world(q) (in sim_plant.c where SIM_INLINE_TRIG) */
    const double *x0;         /* the plant's initial state (nxp) */
    const double *plant_p;    /* the plant's parameters (SI) */
    const double *friction;   /* viscous friction per joint: N m s/rad or N s/m */
    /* The plant's 6th input: its dry friction (3 nq: the Coulomb levels, N m or N, the static
     * levels, the Stribeck velocities, rad/s or m/s) or the geared plant's drive (7 nq:
     * armature, backlash, stiffness, damping, Coulomb, static, Stribeck velocity); NULL: none */
    const double *coulomb;
    /* Measurement grid, per entry of x (NULL: continuous): where quantum[i] > 0 the
     * controller sees offset[i] + quantum[i] * nearbyint((x[i] - offset[i]) / quantum[i]) */
    const double *quantum;
    const double *offset;
    /* Effort grid, per joint (NULL: the command as given): where effort_quantum[i] > 0 the
     * drive applies effort_quantum[i] * nearbyint(tau / effort_quantum[i]), then every joint
     * within +-effort_bound[i] (N m or N) */
    const double *effort_quantum;
    const double *effort_bound;
    /* The bridge's offset current, per joint (NULL: none), before the effort grid: the drive
     * applies tau + effort_offset[i] * clip(tau / effort_ramp[i], -1, 1) (N m or N) */
    const double *effort_offset;
    const double *effort_ramp;
    /* The motor's torque-constant error, per joint (NULL: none): the plant integrates
     * torque_scale[i] (1 + e) times the applied effort, which the log keeps */
    const double *torque_scale;
} sim_unit;

#endif
