/* cochlea embedded runtime: the control loop, cochlea/runtime/loop.py in C.
 *
 * Each period k (t = k h), at the absolute deadline t0 + k h:
 *   1. a stop request (the port's signal handler: user stop, terminate) ends the run, and so
 *      does a log that cannot take this period's row (the port's log_ready: log-failure);
 *   2. read the measurement; more than watchdog_errors consecutive failures end the run
 *      (a failed read leaves the last measurement and skips the state's checks);
 *   3. the supervisor checks the measured state: finite, position and velocity limits, then
 *      every tool point against its keep-out circle (task-space scenarios);
 *   4. the generated controller computes the command and the next estimate;
 *   5. the supervisor checks them (finite; |p_hat| within its bound) and clips the command;
 *   6. write the command; the row of the period goes to the port's on_row callback;
 *   7. the overrun rule (cochlea-run's OverrunWatch, COCHLEA_OVERRUN_POLICY): a period that
 *      starts more than lateness_limit late ends the run before it reads anything; after the
 *      write, a period whose own work (from its deadline or the previous period's end,
 *      whichever is later) took more than a period is an overrun; more than watchdog_misses
 *      overruns in a row, or one period whose own work exceeds watchdog_misses periods (a
 *      stall), end the run. Catch-up periods after a stall run late but are no overruns.
 * Whatever ends the run, the backend's shutdown (zero effort, drives off) runs before
 * cochlea_loop_run returns: it is the only exit (cochlea_loop_end, for a port that runs the
 * periods itself: below).
 *
 * The row of a period is cochlea-run's log.bin row: t, q[nq], qd[nq], tau[nq], per unit its
 * errors[ne] and the estimate used in the period[np], then start lateness, wall period,
 * compute and backend i/o time (s), then the measured motor current of every joint (A, at the
 * joint's sign: the backend's last good read; NaN when it measures none). A stop on the state
 * logs the state and NaN after it up to the current; a stop on the command logs the command as
 * computed (never written) and NaN timing.
 * No allocation, no stdio: the caller owns every buffer.
 */
#ifndef COCHLEA_LOOP_H
#define COCHLEA_LOOP_H

#include "cochlea_rt.h"
#include "scenario.h"

#ifdef __cplusplus
extern "C" {
#endif

#define COCHLEA_MAX_JOINTS 16
#define COCHLEA_MAX_UNITS 4
#define COCHLEA_MAX_POINTS 8
#define COCHLEA_MAX_ERRORS 64
#define COCHLEA_MAX_ROW 512

/* The least the loop may fall behind its absolute deadlines before the watchdog stops it (s);
 * more when watchdog_misses periods are longer (cochlea/runtime/supervisor.py MAX_LATENESS_S). */
#define COCHLEA_MAX_LATENESS_S 0.1

/* The overrun policy in one sentence, word for word cochlea-run's OVERRUN_POLICY (summary.json's
 * timing.overrun_policy; docs/runtime.md states it in full). */
#define COCHLEA_OVERRUN_POLICY                                                                 \
    "period k is due at t0 + k h; it overruns when its own work -- from its deadline or the "  \
    "previous period's end, whichever is later, to its end -- takes longer than h; late "      \
    "periods that catch up within h each are late, not overruns. The watchdog stops the run "  \
    "on N consecutive overruns (--watchdog-misses N), on one period whose own work exceeds N " \
    "periods (a stall), or when a period starts more than max(N h, 0.1 s) late"

/* cochlea_stop.reason of a watchdog stop. */
enum cochlea_watchdog_reason {
    COCHLEA_WATCHDOG_OVERRUNS = 0, /* count consecutive overruns; value: the last one's own work */
    COCHLEA_WATCHDOG_READS = 1,    /* count consecutive failed reads */
    COCHLEA_WATCHDOG_LATE = 2,     /* value: the lateness of the period's start, limit: allowed */
    COCHLEA_WATCHDOG_STALL = 3     /* value: the period's own work, limit: the stall limit (s) */
};

/* Why cochlea_loop_init refused: nothing was started. */
enum cochlea_loop_error {
    COCHLEA_LOOP_OK = 0,
    COCHLEA_LOOP_TOO_BIG,        /* the scenario does not fit the loop's buffers */
    COCHLEA_LOOP_BAD_DURATION,   /* a period outside 50 us..1 s, or a duration not finite,
                                  * under half a period or over 4e9 s */
    COCHLEA_LOOP_BAD_WATCHDOG,   /* a watchdog count below 1 */
    COCHLEA_LOOP_BAD_CONTROLLER, /* the controller's init refused its configuration */
    COCHLEA_LOOP_NO_CLOCK        /* a real-time loop without now_ns and wait_until_ns */
};

typedef struct {
    /* Configuration (cochlea_loop_init). */
    const cochlea_scenario *scenario;
    const cochlea_hal *hal;          /* now_ns, wait_until_ns */
    cochlea_backend backend;
    void *controller;                /* scenario->state_size bytes, the caller's */
    cochlea_limits limits;           /* from the scenario, with the watchdog's counts */
    double period_s;                 /* the control period (s) */
    cochlea_real period_real;        /* the same in the working precision (the row's t) */
    int64_t period_ns;
    int64_t steps;                   /* periods to run; period k starts at t = k period_s */
    int realtime;                    /* 0: periods back to back, no waiting (tests) */
    /* Called at the end of every period with its row (row_length values). It runs inside
     * the period: copy the row and return (the POSIX port hands it to a writer thread).
     * The row is in the working precision (float in the float build: its t column then
     * resolves 1 ms periods up to about 2.3 h; a port that logs longer runs forms t = k h
     * from the period count outside the period, as the STM32 row stream does). */
    void (*on_row)(void *ctx, const cochlea_real *row, int row_length);
    void *row_ctx;
    /* Optional, called with row_ctx at the start of every period, before anything is read or
     * commanded: 0 when the log cannot take the period's row (its writer failed, or a ring it
     * has not emptied is full), which ends the run with COCHLEA_LOG_FAILURE. Same rules as
     * on_row: no blocking, no allocation. */
    int (*log_ready)(void *ctx);
    /* Optional (0 by cochlea_loop_init; the port sets it after): kicks the hardware watchdog.
     * Called with watchdog_ctx once at the end of every period that completed (its command
     * written, its row out), from the loop's context; never after a rule has ended the run,
     * so a watchdog with a timeout of a few periods resets a core whose loop stopped calling
     * cochlea_loop_period. Same rules as on_row: no blocking, no allocation. A field of the
     * loop rather than of cochlea_hal so that a port that fills its HAL field by field
     * cannot leave it uninitialised. */
    void (*kick_watchdog)(void *ctx);
    void *watchdog_ctx;
    /* Set from outside the loop (a signal handler): COCHLEA_USER_STOP or COCHLEA_TERMINATED. */
    volatile int stop_request;
    /* Results. */
    int row_length;
    int64_t rows;                    /* periods logged */
    uint32_t deadline_misses;        /* periods that ended after the next one was due */
    uint32_t overruns;               /* periods whose own work overran (the overrun rule) */
    int64_t lateness_max_ns;         /* the latest start against its deadline */
    int64_t stall_ns;                /* watchdog_misses periods: one period's own work limit */
    int64_t lateness_limit_ns;       /* max(stall_ns, COCHLEA_MAX_LATENESS_S) */
    cochlea_stop stop;               /* why it ended (stop.rule) */
    int shutdown_confirmed;          /* the backend's shutdown result */
    int64_t t0_ns, end_ns;           /* start of period 0 and the end of the run (hal time) */
    /* Ticks of the port's period timer that found a period still running
     * (cochlea_loop_tick): the period overran its tick, whatever the loop's own clock says.
     * Reported (summary.json's timing.tick_overruns), not a rule. */
    volatile uint32_t tick_overruns;
    /* Between cochlea_loop_begin and cochlea_loop_end. */
    int64_t k;                       /* the next period */
    volatile int in_period;          /* 1 while cochlea_loop_period runs */
    int read_errors;                 /* consecutive failed reads (and writes) */
    int measured;                    /* 1 from the run's first good read */
    int consecutive_overruns;
    int64_t previous_start_ns, previous_end_ns;
    /* The supervisor's limits in the working precision (the scenario's, rounded once at
     * init: a float period compares float with float). */
    cochlea_real position_lo[COCHLEA_MAX_JOINTS], position_hi[COCHLEA_MAX_JOINTS];
    cochlea_real velocity[COCHLEA_MAX_JOINTS], effort[COCHLEA_MAX_JOINTS];
    /* Scratch, in the working precision (cochlea_real: float in the float build). */
    cochlea_real q[COCHLEA_MAX_JOINTS], qd[COCHLEA_MAX_JOINTS], tau[COCHLEA_MAX_JOINTS];
    cochlea_real errors[COCHLEA_MAX_ERRORS];
    cochlea_real points[2 * COCHLEA_MAX_POINTS], centres[2 * COCHLEA_MAX_POINTS];
    const cochlea_real *estimates[COCHLEA_MAX_UNITS];
    int n_params[COCHLEA_MAX_UNITS];
    cochlea_real bounds[COCHLEA_MAX_UNITS];
    cochlea_real row[COCHLEA_MAX_ROW];
} cochlea_loop;

/* The timing columns of a row (s), cochlea-run's TIMING_COLUMNS. */
#define COCHLEA_TIMING_COLUMNS 4

/* The length of a log row of the scenario (see above). */
int cochlea_loop_row_length(const cochlea_scenario *sc);
/* Where a row's timing columns start; the current's follow them. */
int cochlea_loop_timing_at(const cochlea_scenario *sc);

/* Configure the loop and initialise the controller (p_hat = p_hat0). period_s: the control
 * period (0: the scenario's; cochlea-run's --rate); duration_s: the run (rounded to whole
 * periods); watchdog_misses and watchdog_errors as cochlea-run's. The
 * backend must already be started (cochlea_bridge_start): the loop only reads, writes and
 * shuts it down. COCHLEA_LOOP_OK or a cochlea_loop_error; on an error nothing ran. */
int cochlea_loop_init(cochlea_loop *loop, const cochlea_scenario *sc, const cochlea_hal *hal,
                      const cochlea_backend *backend, void *controller, double period_s,
                      double duration_s, int watchdog_misses, int watchdog_errors,
                      int realtime);

/* The time of period k (s): k period_s, formed in double from the int64 period count the
 * loop carries, so that it resolves every period at any run length the loop accepts (at
 * 2^40 periods of 1 ms its spacing is 2.4e-7 s). The double build's period uses it; the
 * float build's does not (a Cortex-M4F has no double: its period forms the row's and the
 * stop's t in float), so a float port calls it outside the period (loop->stop.period). */
double cochlea_loop_time(const cochlea_loop *loop, int64_t k);

/* The run in three parts, for a port whose timer interrupt or RTOS task runs one period at
 * each tick (docs/embedded.md, "One period at a time"):
 *   cochlea_loop_begin   once, right before period 0's tick: t0 (period 0's deadline) is now;
 *   cochlea_loop_period  once per tick, from the loop's context (a task, or the main loop the
 *                        tick wakes; not from the interrupt itself: the HAL contract), until it
 *                        returns a rule; with realtime it first waits for the period's deadline
 *                        t0 + k h (returns at once when the tick came on time); every later
 *                        call returns the same rule and does nothing;
 *   cochlea_loop_end     once, after a rule (or to abandon the run): the backend's shutdown
 *                        (zero effort, drives off) and the controller's terminate. A port must
 *                        call it on every path out, as cochlea_loop_run does.
 * The rows, the rules and the stop are those of cochlea_loop_run bit for bit (it is the three
 * in a row). COCHLEA_RULE_NONE while the run goes on, else the rule (enum cochlea_rule). */
int cochlea_loop_begin(cochlea_loop *loop);
int cochlea_loop_period(cochlea_loop *loop);
int cochlea_loop_end(cochlea_loop *loop);

/* For the port's period timer interrupt, at every tick: a period still running
 * (cochlea_loop_period not yet returned) counts one tick overrun (loop->tick_overruns). It
 * reads one volatile int and increments one volatile counter that nothing else writes: the
 * one core function an interrupt may call (cochlea_rt.h's contract). */
void cochlea_loop_tick(cochlea_loop *loop);

/* Run every period until the end or a rule; then the backend's shutdown. The rule
 * (enum cochlea_rule); loop->stop says where, cochlea_exit_code() the process's exit code.
 * cochlea_loop_begin, cochlea_loop_period until a rule, cochlea_loop_end. */
int cochlea_loop_run(cochlea_loop *loop);

#ifdef __cplusplus
}
#endif

#endif /* COCHLEA_LOOP_H */
