/* cochlea embedded runtime: the pieces every port shares.
 *
 * What a stopped run reports (rules and exit codes, the same as cochlea-run's; README lists
 * them), the hardware-abstraction layer a port implements, and the limits the supervisor
 * enforces. Portable C99: no allocation, no stdio, no libc beyond <stddef.h> and <stdint.h>.
 * Units are SI throughout: rad, m, rad/s, m/s, N m, N, s.
 */
#ifndef COCHLEA_RT_H
#define COCHLEA_RT_H

#include <stddef.h>
#include <stdint.h>

#include "cochlea_fp.h" /* refuses -ffast-math; cochlea_finite() */

#ifdef __cplusplus
extern "C" {
#endif

/* ---- rules and exit codes --------------------------------------------------------------- */

/* Why a run ended. The order is the Python supervisor's; cochlea_exit_code() maps each to
 * cochlea-run's exit code. */
enum cochlea_rule {
    COCHLEA_RULE_NONE = 0,      /* still running */
    COCHLEA_COMPLETED,          /* exit 0 */
    COCHLEA_USER_STOP,          /* SIGINT or the port's stop request: exit 0 */
    COCHLEA_POSITION_LIMIT,     /* exit 10 */
    COCHLEA_VELOCITY_LIMIT,     /* exit 11 */
    COCHLEA_KEEP_OUT,           /* exit 12 */
    COCHLEA_NON_FINITE,         /* exit 13 */
    COCHLEA_ESTIMATE_BOUND,     /* exit 14 */
    COCHLEA_WATCHDOG,           /* exit 15 */
    COCHLEA_TERMINATED,         /* SIGTERM, or SIGHUP (a hang-up): exit 16 */
    COCHLEA_LOG_FAILURE,        /* the port's log failed or fell a whole ring behind: exit 17 */
    COCHLEA_RULE_COUNT
};

/* Exit code of a process whose motors could not be started or talked to (cochlea-run's). */
#define COCHLEA_EXIT_BACKEND 5

int cochlea_exit_code(int rule);
/* The rule's name as summary.json and cochlea-run spell it ("velocity-limit", ...). */
const char *cochlea_rule_name(int rule);

/* Where a rule was broken: enough for the port to print the same message as cochlea-run. */
typedef struct {
    int rule;          /* enum cochlea_rule */
    cochlea_real time_s; /* the period's time (s; in the float build a float: exact from
                          * period, below) */
    int joint;         /* joint index (position, velocity, non-finite state), else -1 */
    int unit;          /* unit index (estimate rules) or keep-out point index, else -1 */
    int what;          /* non-finite: 0 state, 1 command, 2 estimate */
    cochlea_real value; /* the offending value: position, speed, |p_hat|, distance (SI) */
    cochlea_real limit; /* the limit it broke (SI) */
    cochlea_real point[2]; /* keep-out: the tool point and the circle's centre (m, world) */
    cochlea_real centre[2];
    int count;         /* watchdog: consecutive overruns or failed reads */
    int reason;        /* watchdog: 0 overruns, 1 backend read failures, 2 too late, 3 a stall
                        * (loop.h's enum cochlea_watchdog_reason) */
    int64_t period;    /* the period the rule ended the run in (the loop's k; steps for
                        * "completed"), -1 if the loop did not set it: its exact time is
                        * cochlea_loop_time(loop, period) (last: the fields before it keep
                        * their places) */
} cochlea_stop;

/* ---- the hardware-abstraction layer ----------------------------------------------------- */

/* Everything a port implements. The core calls nothing else that touches hardware or time.
 * Callbacks return a negative number on an error of the port itself.
 *
 * The contract (the core's deadlines rest on it):
 * - Context. The core calls every callback from the loop's own context (the thread or main
 *   loop that runs cochlea_bridge_* and cochlea_loop_run), never from an interrupt, and never
 *   two at once. None of them may be called by the port from an interrupt either. The only
 *   thing an interrupt or signal handler may do is store COCHLEA_USER_STOP or
 *   COCHLEA_TERMINATED in cochlea_loop.stop_request (a volatile int: one aligned store),
 *   and, from the period timer's interrupt, call cochlea_loop_tick (loop.h: counts a tick
 *   that finds a period still running).
 *   A UART interrupt fills the port's own ring buffer; serial_read copies out of it.
 * - Every callback returns in bounded time: serial_read within its timeout (plus the copy),
 *   serial_write within the time its bytes take on the wire plus a bounded margin (give up
 *   with -1 on an adapter that stops taking them), wait_until_ns at its deadline. The core
 *   bounds each of its waits by now_ns() alone, whatever the line delivers (bridge.c), so a
 *   callback that blocks longer is the one thing it cannot end.
 * - serial_write returns after the last byte has left the transmitter (the shift register,
 *   not a FIFO) when the port switches an RS-485 transceiver with rs485_direction: the
 *   direction goes back to receive right after it returns, and an early return would cut
 *   the frame's end. With an adapter that switches by itself (rs485_direction NULL) it may
 *   return once the adapter has the bytes (the POSIX port: the kernel's queue; it does not
 *   tcdrain, which has no timeout).
 * - now_ns is a 64-bit monotonic count of nanoseconds that never wraps and never goes back.
 *   A port on a wrapping hardware timer (a 32-bit counter at 1 MHz wraps every 71.6 min, a
 *   16-bit one in ms) must extend it to 64 bits: count the wraps (the overflow interrupt, or
 *   a comparison with the last reading at least once per wrap period) and combine them with
 *   the counter so that a reading taken across a wrap is never off by a whole wrap.
 * - Memory the core is handed (the scenario's controller state of state_size bytes, the
 *   cochlea_bridge and cochlea_loop structs) must be aligned for double (8 bytes): the
 *   generated code loads doubles from the state, and a Cortex-M faults on an unaligned
 *   double load (LDRD/VLDR). Static storage of a struct, or a union with a double, is. */
typedef struct {
    void *ctx;
    /* Send n bytes; the number sent (all of them, or an error). Returns when they are
     * transmitted (above). */
    long (*serial_write)(void *ctx, const uint8_t *data, size_t n);
    /* Receive up to n bytes, waiting at most timeout_ns for them to start arriving (0: only
     * what has already arrived, no wait); the number received (0: timeout, never more than
     * n). Must not block longer than the timeout; it may return early with fewer bytes. */
    long (*serial_read)(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns);
    /* Drop whatever the port has received and not yet read (may be NULL). */
    void (*serial_discard_input)(void *ctx);
    /* Switch an RS-485 transceiver to transmit (1) or receive (0); NULL when the adapter
     * switches by itself (U2D2, USB-RS485 with automatic direction). */
    void (*rs485_direction)(void *ctx, int transmit);
    /* Monotonic time (ns, 64-bit, never wrapping: above) and a wait until an absolute
     * monotonic time (returns at once for a time already past). */
    int64_t (*now_ns)(void *ctx);
    void (*wait_until_ns)(void *ctx, int64_t deadline_ns);
} cochlea_hal;

/* ---- a backend: the motors (cochlea_bridge_backend) or a simulated robot ---------------- */

/* What the loop drives. q, qd and tau hold every joint of the scenario in its order (SI), in
 * the working precision (cochlea_real: float in the float build, cochlea_fp.h). */
typedef struct {
    void *ctx;
    /* One measurement; 1, or 0 on a failure (q and qd then left as they were). */
    int (*read)(void *ctx, cochlea_real *q, cochlea_real *qd);
    /* One command; 1, or 0 on a failure. */
    int (*write)(void *ctx, const cochlea_real *tau);
    /* The safe stop: zero effort, drives off. The number of drives that confirmed it. */
    int (*shutdown)(void *ctx);
    /* The measured motor current of every joint (A, signed so that a positive current drives
     * the joint positively), refreshed by every good read; the loop logs it after the timing.
     * NULL when the backend measures no current: those columns are then NaN. */
    const cochlea_real *current;
} cochlea_backend;

/* ---- the supervisor ----------------------------------------------------------------------- */

/* What the supervisor enforces, per joint of the whole system in the loop's order (SI), in
 * the working precision (the loop keeps its own copies of the scenario's double limits). */
typedef struct {
    int n_joints;
    const cochlea_real *position_lo; /* rad or m */
    const cochlea_real *position_hi;
    const cochlea_real *velocity;  /* rad/s or m/s */
    const cochlea_real *effort;    /* N m or N: every command is clipped to it */
    cochlea_real keep_out_radius;  /* m; 0 or less: no keep-out rule (no circle described) */
    int watchdog_misses;           /* consecutive overruns tolerated (loop.h's overrun rule) */
    int watchdog_errors;           /* consecutive backend failures tolerated */
} cochlea_limits;

/* The measured state: finite, inside the position limits, under the velocity limits (in that
 * order, first joint first, as the Python supervisor). 1 and *stop filled when a rule is
 * broken, else 0. */
int cochlea_check_state(const cochlea_limits *limits, cochlea_real t, const cochlea_real *q,
                        const cochlea_real *qd, cochlea_stop *stop);

/* Tool points against the keep-out circle: n_points points and their circles' centres
 * (m, world frame). */
int cochlea_check_keep_out(const cochlea_limits *limits, cochlea_real t, int n_points,
                           const cochlea_real *points, const cochlea_real *centres,
                           cochlea_stop *stop);

/* The command (finite) and each unit's next estimate (finite, |p_hat| within its bound with
 * the Python supervisor's 1e-9 relative tolerance; in the float build 16 float epsilons,
 * 1.9e-6, since 1 + 1e-9 is 1 in float and the float projection rounds to about 6e-8).
 * estimates[u] has n_params[u] values. */
#ifdef COCHLEA_FLOAT
#define COCHLEA_ESTIMATE_TOLERANCE 1.9073486e-6f /* 16 FLT_EPSILON */
#else
#define COCHLEA_ESTIMATE_TOLERANCE 1e-9
#endif
int cochlea_check_command(const cochlea_limits *limits, cochlea_real t, const cochlea_real *tau,
                          int n_units, const cochlea_real *const *estimates,
                          const int *n_params, const cochlea_real *bounds, cochlea_stop *stop);

/* Clip every command to its joint's effort limit; the number of joints clipped. */
int cochlea_saturate(const cochlea_limits *limits, cochlea_real *tau);

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_RT_H */
