/* cochlea embedded runtime: joint <-> motor conversions of one Dynamixel drive, the Python
 * bridge's (cochlea/dynamixel/drives.py, cochlea/robots/motor_fit.py) in C.
 *
 * Joint side SI (rad or m, rad/s or m/s, N m or N); motor side in control-table units, each
 * the model's, from its data (cochlea/dynamixel/models): Present Position in counts (2 pi /
 * counts per turn: 4096 on the X series, 607500 on a PH42-020-S300-R), Present Velocity in its
 * LSB (0.229 rpm X series, 0.01 rpm P series), currents in its LSB (3.36 mA MX-64(2.0), 2.69 mA
 * XM540-W270, 1 mA P series). Nothing here assumes one: each drive carries them in its
 * constants. The tables of a robot are generated from its description
 * (generated_c/embedded/<robot>_drives.h).
 */
#ifndef COCHLEA_DRIVES_H
#define COCHLEA_DRIVES_H

#include <stdint.h>

#include "cochlea_fp.h" /* refuses -ffast-math */

#ifdef __cplusplus
extern "C" {
#endif

struct dxl_bus; /* dxl.h: the chain's transfers and each motor's control-table items */

/* One joint and its motor. The conversion constants are the Python bridge's own values
 * (generated, printed to 17 digits), so C and Python give the same counts bit for bit. */
typedef struct {
    const char *name;          /* the joint, e.g. "arm1.joint2" */
    uint8_t id;                /* Dynamixel ID */
    uint16_t model_number;     /* what PING must answer (311 MX-64(2.0), 1120 XM540-W270) */
    int revolute;              /* 1 revolute (rad), 0 prismatic (m) */
    double q_per_count;        /* direction ratio 2 pi / counts per turn (rad or m per
                                * count; the model's counts per turn, 4096 on the X series) */
    double q_offset;           /* -direction ratio zero_offset (rad or m) */
    double qd_per_lsb;         /* direction ratio velocity LSB (rad/s or m/s per LSB; the
                                * model's LSB, 0.229 rpm on the X series) */
    double torque_per_effort;  /* direction ratio: motor N m per joint N m (or N) */
    double inv_a;              /* 1 / a of the fit (A per N m) */
    double inv_ramp;           /* 1 / ramp (per N m) */
    double i0;                 /* -b / a: the current the fit's offset takes (A) */
    double lsb_per_ampere;     /* current LSBs per A */
    double ampere_per_lsb;     /* A per Present Current LSB at the joint's sign (the mounting's
                                * direction applied): positive drives the joint positively */
    int32_t current_limit_lsb; /* Current Limit (address 38) this joint uses */
    double position_lo;        /* joint limits (rad or m) */
    double position_hi;
    double velocity_limit;     /* rad/s or m/s */
    double effort_limit;       /* N m or N */
    const struct dxl_bus *bus; /* the chain's bus (the same for every drive of the table):
                                * where the bridge reads and writes, from the model data */
} cochlea_drive;

/* q = q_per_count counts + position_offset, with position_offset the drive's q_offset plus
 * the whole turns chosen at start-up (cochlea_drive_unwrap). */
double cochlea_drive_position(const cochlea_drive *d, int32_t counts, double position_offset);
double cochlea_drive_velocity(const cochlea_drive *d, int32_t velocity_lsb);
/* A revolute joint's encoder is single-turn after power-up: the offset that puts q nearest
 * the middle of its limits (whole turns added); a prismatic joint keeps its offset. q is the
 * position read with position_offset. */
double cochlea_drive_unwrap(const cochlea_drive *d, double q, double position_offset);
/* Goal Current (LSB) for a joint effort: the fit's inverse
 * I = tau_m / a + I0 clip(tau_m / ramp, -1, 1), tau_m = torque_per_effort effort, rounded
 * half to even, within +-current_limit_lsb. offset_current 0 leaves out the offset term I0
 * (the gearbox's friction), for a controller that compensates friction itself: friction is
 * compensated once (cochlea.robots.motor_fit.bridge_compensates_friction). A non-finite
 * effort gives 0 (the caller reports it). */
int16_t cochlea_drive_goal_current(const cochlea_drive *d, double effort, int offset_current);
/* The measured motor current (A) of a Present Current reading (LSB), at the joint's sign:
 * what cochlea-run logs as current.<joint>_A (the Python bridge's joint_current_A). */
double cochlea_drive_current(const cochlea_drive *d, int16_t present_lsb);

/* The per-period conversions in the working precision (cochlea_real, cochlea_fp.h), from a
 * drive's constants rounded once, outside the period (cochlea_drive_real_init: at start-up,
 * once the position offset is known). In the double build they are the functions above, bit
 * for bit. In the float build (a Cortex-M4F has no double instruction) they run in float
 * and integer counts only:
 * - position: q = (counts - count0) q_per_count + q0, the count difference an integer
 *   (count0 the count nearest the middle of the joint's limits, q0 its position, formed in
 *   double at init), so the float product stays within the joint's range whatever the
 *   encoder's count: error a few 1e-7 rad (or m), far under one count;
 * - velocity and current: the LSB times the constant, in float;
 * - goal current: the fit's inverse in float, clipped to the current limit, rounded half to
 *   even by the float's own rounding (no nearbyint: the value is under 2^22): the double
 *   function's LSB, or one LSB from it where the float rounding crosses a half
 *   (tests/test_embedded_float.py measures it). */
typedef struct {
    const cochlea_drive *drive;
    double position_offset;     /* the double build's, as cochlea_drive_position takes it */
    int32_t count0;             /* float build: the count nearest the middle of the limits */
    cochlea_real q0;            /* its position (rad or m) */
    cochlea_real q_per_count, qd_per_lsb, ampere_per_lsb;
    cochlea_real torque_per_effort, inv_a, inv_ramp, i0, lsb_per_ampere;
    cochlea_real current_limit; /* current_limit_lsb */
} cochlea_drive_real;

void cochlea_drive_real_init(cochlea_drive_real *c, const cochlea_drive *d,
                             double position_offset);
cochlea_real cochlea_drive_position_real(const cochlea_drive_real *c, int32_t counts);
cochlea_real cochlea_drive_velocity_real(const cochlea_drive_real *c, int32_t velocity_lsb);
cochlea_real cochlea_drive_current_real(const cochlea_drive_real *c, int16_t present_lsb);
int16_t cochlea_drive_goal_current_real(const cochlea_drive_real *c, cochlea_real effort,
                                        int offset_current);

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_DRIVES_H */
