/* cochlea embedded runtime: the control loop (loop.h says what each period does). */
#include "loop.h"

#include <math.h>

/* The time of period k in the working precision: the double build's own (double)k h, bit
 * for bit as before; the float build's in float (no double routine in the period; the
 * control itself runs on k, the row's and the stop's t are for the log). */
static cochlea_real period_time(const cochlea_loop *loop, int64_t k)
{
#ifdef COCHLEA_FLOAT
    return (cochlea_real)k * loop->period_real;
#else
    return cochlea_loop_time(loop, k);
#endif
}

int cochlea_loop_timing_at(const cochlea_scenario *sc)
{
    int u, n = 1 + 3 * sc->nq;
    for (u = 0; u < sc->n_units; ++u) {
        n += sc->units[u].ne + sc->units[u].np;
    }
    return n;
}

int cochlea_loop_row_length(const cochlea_scenario *sc)
{
    /* The current goes last, as in cochlea-run's rows: every earlier column keeps its place
     * in logs read by position. */
    return cochlea_loop_timing_at(sc) + COCHLEA_TIMING_COLUMNS + sc->nq;
}

int cochlea_loop_init(cochlea_loop *loop, const cochlea_scenario *sc, const cochlea_hal *hal,
                      const cochlea_backend *backend, void *controller, double period_s,
                      double duration_s, int watchdog_misses, int watchdog_errors,
                      int realtime)
{
    int u, i;
    double periods;
    const double h = period_s > 0.0 ? period_s : sc->period_s;
    loop->scenario = sc;
    loop->hal = hal;
    loop->backend = *backend;
    loop->controller = controller;
    loop->realtime = realtime;
    loop->on_row = 0;
    loop->row_ctx = 0;
    loop->log_ready = 0;
    loop->kick_watchdog = 0;
    loop->watchdog_ctx = 0;
    loop->tick_overruns = 0;
    loop->in_period = 0;
    loop->k = 0;
    loop->stop_request = COCHLEA_RULE_NONE;
    loop->rows = 0;
    loop->deadline_misses = 0;
    loop->overruns = 0;
    loop->lateness_max_ns = 0;
    loop->stop.rule = COCHLEA_RULE_NONE;
    loop->shutdown_confirmed = -1;
    loop->t0_ns = loop->end_ns = 0;
    if (sc->nq > COCHLEA_MAX_JOINTS || sc->n_units > COCHLEA_MAX_UNITS
        || sc->n_points > COCHLEA_MAX_POINTS || sc->ne > COCHLEA_MAX_ERRORS
        || cochlea_loop_row_length(sc) > COCHLEA_MAX_ROW) {
        return COCHLEA_LOOP_TOO_BIG;
    }
    periods = duration_s / h;
    /* Up to 4e9 s: the deadlines k period_ns stay far inside int64 (4e18 ns). */
    if (!(h >= 5e-5 && h <= 1.0 && periods >= 0.5 && duration_s <= 4.0e9)) { /* and NaN */
        return COCHLEA_LOOP_BAD_DURATION;
    }
    if (watchdog_misses < 1 || watchdog_errors < 1) {
        return COCHLEA_LOOP_BAD_WATCHDOG;
    }
    if (realtime && (hal == 0 || hal->now_ns == 0 || hal->wait_until_ns == 0)) {
        return COCHLEA_LOOP_NO_CLOCK;
    }
    loop->steps = (int64_t)nearbyint(periods);
    loop->period_s = h;
    loop->period_ns = (int64_t)nearbyint(h * 1e9);
    loop->stall_ns = (int64_t)watchdog_misses * loop->period_ns;
    loop->lateness_limit_ns = (int64_t)nearbyint(COCHLEA_MAX_LATENESS_S * 1e9);
    if (loop->stall_ns > loop->lateness_limit_ns) {
        loop->lateness_limit_ns = loop->stall_ns;
    }
    loop->row_length = cochlea_loop_row_length(sc);
    loop->limits.n_joints = sc->nq;
    loop->limits.keep_out_radius = (cochlea_real)sc->keep_out_radius;
    loop->limits.watchdog_misses = watchdog_misses;
    loop->limits.watchdog_errors = watchdog_errors;
    /* The scenario's controller must compute in the loop's working precision (its pointers
     * are passed through as they are), and the float build steps by the period count. */
    if (sc->real_size != (int)sizeof(cochlea_real)) {
        return COCHLEA_LOOP_BAD_CONTROLLER;
    }
#ifdef COCHLEA_FLOAT
    if (!sc->step_period) {
        return COCHLEA_LOOP_BAD_CONTROLLER;
    }
#endif
    for (i = 0; i < sc->nq; ++i) {
        loop->position_lo[i] = (cochlea_real)sc->position_lo[i];
        loop->position_hi[i] = (cochlea_real)sc->position_hi[i];
        loop->velocity[i] = (cochlea_real)sc->velocity[i];
        loop->effort[i] = (cochlea_real)sc->effort[i];
    }
    loop->limits.position_lo = loop->position_lo;
    loop->limits.position_hi = loop->position_hi;
    loop->limits.velocity = loop->velocity;
    loop->limits.effort = loop->effort;
    loop->period_real = (cochlea_real)h;
    if (sc->init(controller, h) != 0) {
        return COCHLEA_LOOP_BAD_CONTROLLER;
    }
    for (u = 0; u < sc->n_units; ++u) {
        loop->estimates[u] = sc->estimate(controller) + sc->units[u].p0;
        loop->n_params[u] = sc->units[u].np;
        loop->bounds[u] = (cochlea_real)sc->units[u].bound;
    }
    for (i = 0; i < sc->nq; ++i) {
        loop->q[i] = loop->qd[i] = loop->tau[i] = COCHLEA_R(0.0);
    }
    return COCHLEA_LOOP_OK;
}

double cochlea_loop_time(const cochlea_loop *loop, int64_t k)
{
    return (double)k * loop->period_s;
}

static int64_t now(const cochlea_loop *loop)
{
    return (loop->hal && loop->hal->now_ns) ? loop->hal->now_ns(loop->hal->ctx) : 0;
}

static void fill_nan(cochlea_real *v, int n)
{
    int i;
    for (i = 0; i < n; ++i) {
        v[i] = (cochlea_real)NAN; /* NAN is a float constant: no promotion warning */
    }
}

static void emit(cochlea_loop *loop)
{
    loop->rows += 1;
    if (loop->on_row) {
        loop->on_row(loop->row_ctx, loop->row, loop->row_length);
    }
}

static void stop_here(cochlea_stop *stop, int rule, cochlea_real t)
{
    stop->rule = rule;
    stop->time_s = t;
    stop->period = -1; /* cochlea_loop_period sets it */
    stop->joint = stop->unit = -1;
    stop->what = 0;
    stop->value = stop->limit = COCHLEA_R(0.0);
    stop->point[0] = stop->point[1] = stop->centre[0] = stop->centre[1] = COCHLEA_R(0.0);
    stop->count = 0;
    stop->reason = 0;
}

int cochlea_loop_begin(cochlea_loop *loop)
{
    if (!loop->backend.current) { /* stays NaN: nothing measures it */
        fill_nan(loop->row + cochlea_loop_timing_at(loop->scenario) + COCHLEA_TIMING_COLUMNS,
                 loop->scenario->nq);
    }
    loop->k = 0;
    loop->read_errors = 0;
    /* Nothing measured yet: a failed first read leaves NaN in q and qd, never a state the
     * robot is not in, and the period commands zero effort until the first good read. */
    loop->measured = 0;
    fill_nan(loop->q, loop->scenario->nq);
    fill_nan(loop->qd, loop->scenario->nq);
    loop->consecutive_overruns = 0;
    loop->previous_end_ns = 0;
    loop->in_period = 0;
    loop->t0_ns = now(loop);
    loop->previous_start_ns = loop->t0_ns;
    return COCHLEA_RULE_NONE;
}

/* The period's rule: recorded in loop->stop (stop_here) by the caller of period(). */
static int period(cochlea_loop *loop)
{
    const cochlea_scenario *sc = loop->scenario;
    const cochlea_backend *be = &loop->backend;
    const int n = sc->nq;
    cochlea_real *row = loop->row;
    cochlea_real *row_tau = row + 1 + 2 * n;
    cochlea_real *timing = row + cochlea_loop_timing_at(sc);
    cochlea_real *current = timing + COCHLEA_TIMING_COLUMNS;
    const int64_t t0 = loop->t0_ns, k = loop->k;
    int64_t start, io_start, io_ns, end, deadline;
    int u, i, r;
    {
        /* Time is the period count k (int64: no rounding, no wrap): the controller steps by
         * k. t is formed here for the row and the stop only: in double in the double build;
         * in float in the float build (it would staircase from a few hours on, 7.8 ms steps
         * from 86 400 s: a port forms the exact k h outside the period, stop.period). */
        const cochlea_real t = period_time(loop, k);
        deadline = t0 + k * loop->period_ns;
        if (loop->realtime) {
            loop->hal->wait_until_ns(loop->hal->ctx, deadline);
        }
        loop->in_period = 1; /* from here a tick of the port's timer finds the period late */
        start = now(loop);
        if (loop->stop_request) {
            stop_here(&loop->stop, loop->stop_request, t);
            return loop->stop.rule;
        }
        if (loop->realtime) { /* too far behind to catch up: stop before commanding anything */
            const int64_t lateness = start - deadline;
            if (lateness > loop->lateness_max_ns) {
                loop->lateness_max_ns = lateness;
            }
            if (lateness > loop->lateness_limit_ns) {
                stop_here(&loop->stop, COCHLEA_WATCHDOG, t);
                loop->stop.reason = COCHLEA_WATCHDOG_LATE;
                loop->stop.value = (cochlea_real)lateness * COCHLEA_R(1e-9);
                loop->stop.limit = (cochlea_real)loop->lateness_limit_ns * COCHLEA_R(1e-9);
                return COCHLEA_WATCHDOG;
            }
        }
        if (loop->log_ready && !loop->log_ready(loop->row_ctx)) {
            stop_here(&loop->stop, COCHLEA_LOG_FAILURE, t);
            return COCHLEA_LOG_FAILURE;
        }
        io_start = now(loop);
        r = be->read(be->ctx, loop->q, loop->qd);
        io_ns = now(loop) - io_start;
        loop->read_errors = r ? 0 : loop->read_errors + 1;
        if (loop->read_errors > loop->limits.watchdog_errors) {
            stop_here(&loop->stop, COCHLEA_WATCHDOG, t);
            loop->stop.count = loop->read_errors;
            loop->stop.reason = 1;
            return COCHLEA_WATCHDOG;
        }
        row[0] = t;
        for (i = 0; i < n; ++i) {
            row[1 + i] = loop->q[i];
            row[1 + n + i] = loop->qd[i];
        }
        if (be->current) { /* the last good read's, like q and qd after a failed read */
            for (i = 0; i < n; ++i) {
                current[i] = be->current[i];
            }
        }
        if (r && (cochlea_check_state(&loop->limits, t, loop->q, loop->qd, &loop->stop)
                  || (loop->limits.keep_out_radius > COCHLEA_R(0.0) && sc->n_points > 0
                      && sc->tool_points(loop->q, loop->points, loop->centres) == 0
                      && cochlea_check_keep_out(&loop->limits, t, sc->n_points, loop->points,
                                                loop->centres, &loop->stop)))) {
            fill_nan(row_tau, (int)(current - row_tau)); /* nothing was commanded */
            emit(loop);
            return loop->stop.rule;
        }
        { /* the estimate this period uses, in the row */
            const cochlea_real *p_hat = sc->estimate(loop->controller);
            cochlea_real *cell = row_tau + n;
            for (u = 0; u < sc->n_units; ++u) {
                const cochlea_unit_info *unit = &sc->units[u];
                cell += unit->ne;
                for (i = 0; i < unit->np; ++i) {
                    cell[i] = p_hat[unit->p0 + i];
                }
                cell += unit->np;
            }
        }
        loop->measured = loop->measured || r;
        if (!loop->measured) {
            /* No state measured yet: command nothing (zero effort keeps the drives' Bus
             * Watchdog fed and their torque off) and step no controller. */
            for (i = 0; i < n; ++i) {
                loop->tau[i] = COCHLEA_R(0.0);
            }
            fill_nan(loop->errors, sc->ne);
            r = 0;
        } else {
#ifdef COCHLEA_FLOAT
            r = sc->step_period(loop->controller, k, loop->q, loop->qd, loop->tau,
                                loop->errors); /* cochlea_loop_init checked it is there */
#else
            r = sc->step_period ? sc->step_period(loop->controller, k, loop->q, loop->qd,
                                                  loop->tau, loop->errors)
                                : sc->step(loop->controller, t, loop->q, loop->qd, loop->tau,
                                           loop->errors);
#endif
        }
        { /* errors, unit after unit, between tau and the estimate */
            cochlea_real *cell = row_tau + n;
            for (u = 0; u < sc->n_units; ++u) {
                const cochlea_unit_info *unit = &sc->units[u];
                for (i = 0; i < unit->ne; ++i) {
                    cell[i] = loop->errors[unit->e0 + i];
                }
                cell += unit->ne + unit->np;
            }
        }
        if (r == 0) { /* finite: the supervisor's estimate rule on the next estimate */
            r = cochlea_check_command(&loop->limits, t, loop->tau, sc->n_units, loop->estimates,
                                      loop->n_params, loop->bounds, &loop->stop) ? 3 : 0;
        } else {
            stop_here(&loop->stop, COCHLEA_NON_FINITE, t);
            loop->stop.what = r == 2 ? 2 : 1;
        }
        if (r != 0) { /* the refused command is logged as computed; it was never written */
            for (i = 0; i < n; ++i) {
                row_tau[i] = loop->tau[i];
            }
            fill_nan(timing, COCHLEA_TIMING_COLUMNS);
            emit(loop);
            return loop->stop.rule;
        }
        cochlea_saturate(&loop->limits, loop->tau); /* the controller clipped it already */
        io_start = now(loop);
        if (!be->write(be->ctx, loop->tau)) {
            loop->read_errors += 1;
        }
        io_ns += now(loop) - io_start;
        for (i = 0; i < n; ++i) {
            row_tau[i] = loop->tau[i];
        }
        end = now(loop);
#ifdef COCHLEA_FLOAT
        /* in float from integer nanoseconds: the lateness as start - deadline, exact */
        timing[0] = (cochlea_real)(start - deadline) * 1e-9f;
        timing[1] = (cochlea_real)(start - loop->previous_start_ns) * 1e-9f;
        timing[2] = (cochlea_real)(end - start) * 1e-9f;
        timing[3] = (cochlea_real)io_ns * 1e-9f;
#else
        timing[0] = (double)(start - t0) * 1e-9 - t;
        timing[1] = (double)(start - loop->previous_start_ns) * 1e-9;
        timing[2] = (double)(end - start) * 1e-9;
        timing[3] = (double)io_ns * 1e-9;
#endif
        emit(loop);
        loop->previous_start_ns = start;
        if (loop->realtime) {
            /* The period's own work runs from its deadline, or from the previous period's end
             * when that was later (a catch-up period): lateness inherited from a stall is not
             * this period's overrun. */
            const int64_t begin = (k > 0 && loop->previous_end_ns > deadline) ? loop->previous_end_ns : deadline;
            const int64_t own = end - begin;
            loop->previous_end_ns = end;
            if (end - t0 > (int64_t)(k + 1) * loop->period_ns) {
                loop->deadline_misses += 1; /* reported, not a rule */
            }
            if (own <= loop->period_ns) {
                loop->consecutive_overruns = 0;
            } else {
                loop->overruns += 1;
                loop->consecutive_overruns += 1;
                if (own > loop->stall_ns) {
                    stop_here(&loop->stop, COCHLEA_WATCHDOG, t);
                    loop->stop.reason = COCHLEA_WATCHDOG_STALL;
                    loop->stop.count = loop->consecutive_overruns;
                    loop->stop.value = (cochlea_real)own * COCHLEA_R(1e-9);
                    loop->stop.limit = (cochlea_real)loop->stall_ns * COCHLEA_R(1e-9);
                    return COCHLEA_WATCHDOG;
                }
                if (loop->consecutive_overruns > loop->limits.watchdog_misses) {
                    stop_here(&loop->stop, COCHLEA_WATCHDOG, t);
                    loop->stop.reason = COCHLEA_WATCHDOG_OVERRUNS;
                    loop->stop.count = loop->consecutive_overruns;
                    loop->stop.value = (cochlea_real)own * COCHLEA_R(1e-9);
                    return COCHLEA_WATCHDOG;
                }
            }
        }
    }
    return COCHLEA_RULE_NONE;
}

int cochlea_loop_period(cochlea_loop *loop)
{
    int rule;
    if (loop->stop.rule != COCHLEA_RULE_NONE) { /* the run has ended: nothing more */
        return loop->stop.rule;
    }
    if (loop->k >= loop->steps) {
        stop_here(&loop->stop, COCHLEA_COMPLETED, period_time(loop, loop->steps));
        loop->stop.period = loop->steps;
        return COCHLEA_COMPLETED;
    }
    rule = period(loop);
    if (rule != COCHLEA_RULE_NONE) {
        loop->stop.period = loop->k;
    } else {
        loop->k += 1;
        if (loop->kick_watchdog) { /* a whole period done: the hardware watchdog may wait */
            loop->kick_watchdog(loop->watchdog_ctx);
        }
    }
    loop->in_period = 0;
    return rule;
}

void cochlea_loop_tick(cochlea_loop *loop)
{
    if (loop->in_period) {
        loop->tick_overruns += 1;
    }
}

int cochlea_loop_end(cochlea_loop *loop)
{
    loop->end_ns = now(loop);
    loop->shutdown_confirmed = loop->backend.shutdown(loop->backend.ctx);
    loop->scenario->terminate(loop->controller);
    return loop->stop.rule;
}


int cochlea_loop_run(cochlea_loop *loop)
{
    int rule = cochlea_loop_begin(loop);
    while (rule == COCHLEA_RULE_NONE) {
        rule = cochlea_loop_period(loop);
    }
    (void)cochlea_loop_end(loop);
    return rule;
}
