/* cochlea on an STM32F405/407: one scenario's real-time loop over the Dynamixel bus.
 *
 * At reset: the clocks (hal_stm32f4.c), TIM2 as the 64-bit clock, the console (USART2), the
 * bus (USART1, its receive interrupt), SysTick at the loop's period. Then, as
 * build/cochlea-embedded does: the controller and the loop first (a refused configuration moves nothing), the bridge's
 * start-up (PING and model check, configuration, Bus Watchdog, first read; the torque with the
 * first nonzero command), and the periods: SysTick's interrupt (cochlea_loop_tick) wakes the
 * core from WFI and the main context runs cochlea_loop_period; the independent watchdog is
 * started with period 0 and kicked after every completed period (loop.kick_watchdog). Every
 * end goes through cochlea_loop_end (zero current, torque off, confirmed per motor); the
 * firmware then reports on the console and parks: it never starts the motors again without a
 * reset, and refuses to start at all after a watchdog reset.
 *
 * Compiled in: the scenario (STM32_SCENARIO), the run's length (STM32_DURATION_S, 0: the
 * scenario's), the watchdog counts (cochlea-run's --watchdog-misses, --watchdog-errors), the
 * bus's baud rate, its read timeout, whether PA8 switches an RS-485 transceiver.
 *
 * The console's lines (115200 8N1, key=value; docs/embedded.md, "STM32F4 port"):
 *   cochlea-stm32f4 scenario=S precision=float|double clock=pll|unmodelled|no-hse|no-pll
 *       baud=B timer_hz=F period_ns=P periods=N
 *   start ok | start failed error=E step=S drive=D detail=X
 *       | refused what=clock|watchdog-reset|homing|configuration|loop ...
 *   end rule=NAME exit=C rows=N kicks=K tick_overruns=T deadline_misses=M overruns=O
 *       lateness_max_ns=L t0_ns=T run_ns=R reads=N good_reads=G rx_overflows=V
 *       failures=none|KIND:COUNT,... confirmed_off=A/B stack_bytes=S stop_joint=J
 *       stop_value_u=V stop_limit_u=L (the stop's joint, value and limit in micro-SI units)
 * An end line is always the last; after it the core parks (WFI), the motors off. */
#include <stdint.h>

#include "bridge.h"
#include "cochlea_rt.h"
#include "hal_stm32f4.h"
#include "loop.h"
#include "scenario.h"
#include "stream.h"

#ifndef STM32_SCENARIO
#define STM32_SCENARIO serial_joint
#endif
#ifndef STM32_DURATION_S
#define STM32_DURATION_S 0.0 /* the scenario's own */
#endif
#ifndef STM32_WATCHDOG_MISSES
#define STM32_WATCHDOG_MISSES 20
#endif
#ifndef STM32_WATCHDOG_ERRORS
#define STM32_WATCHDOG_ERRORS 5
#endif
#ifndef STM32_RATE_HZ
#define STM32_RATE_HZ 0 /* the scenario's; else the control rate (cochlea-run's --rate) */
#endif
#ifndef STM32_BAUD
#define STM32_BAUD 4000000u
#endif
#ifndef STM32_READ_TIMEOUT_NS
#define STM32_READ_TIMEOUT_NS 5000000 /* a period's SYNC_READ reply (ns) */
#endif
#ifndef STM32_RS485
#define STM32_RS485 1 /* PA8 drives the transceiver's direction */
#endif
/* The independent watchdog while the periods run: over the loop's own lateness limit (0.1 s)
 * and a period's read timeout even at the LSI's fastest (47 kHz: 0.68 of nominal), so it
 * fires only on a core that stopped, never before the loop's own rules. */
#define IWDG_RUN_MS 250u
/* Through the safe stop (its waits are bounded; 6 motors confirm in well under a second)
 * and then kicked by SysTick while the core parks. */
#define IWDG_STOP_MS 4000u
#ifndef STM32_STREAM_BAUD
#define STM32_STREAM_BAUD 921600u /* the row stream on USART3 (stream.h) */
#endif
#ifndef STM32_STREAM_EVERY
#define STM32_STREAM_EVERY 10u /* every N-th period's row is streamed */
#endif
#ifndef STM32_BUS_WATCHDOG_MS
#define STM32_BUS_WATCHDOG_MS 100 /* the motors stop by themselves when the bus goes quiet */
#endif

#define CAT2(a, b) a##b
#define CAT(a, b) CAT2(a, b)
#define STR2(a) #a
#define STR(a) STR2(a)

extern const cochlea_scenario CAT(STM32_SCENARIO, _scenario);
uint32_t stm32f4_stack_used(void);

static cochlea_bridge bridge;
static cochlea_loop the_loop;
static stm32f4_uart bus;
static union {
    double align; /* aligned for double loads (cochlea_rt.h) */
    uint8_t bytes[16384];
} controller;
static volatile int running; /* between cochlea_loop_begin and cochlea_loop_end */
static volatile int parked;  /* after the end: SysTick kicks the watchdog */
static volatile int iwdg_on;
static uint32_t kicks;
/* The row stream's own cost, in TIM2 counts (STM32_TIMER_HZ; 1 ns under QEMU, where with
 * -icount shift=0 a count is an instruction): the largest in-period on_row, and the largest
 * framing between two periods. */
static uint32_t stream_row_max, stream_pump_max;
static char line[2048]; /* a console line, or the stream's header (its columns) */

static char *put(char *at, const char *s)
{
    while (*s && at < line + sizeof line - 3) {
        *at++ = *s++;
    }
    return at;
}

static char *put_int(char *at, int64_t v)
{
    char digits[24];
    int n = 0;
    uint64_t u = v < 0 ? (uint64_t)0 - (uint64_t)v : (uint64_t)v;
    if (v < 0) {
        at = put(at, "-");
    }
    do {
        digits[n++] = (char)('0' + u % 10u);
        u /= 10u;
    } while (u);
    while (n > 0 && at < line + sizeof line - 3) {
        *at++ = digits[--n];
    }
    return at;
}

static char *put_kv(char *at, const char *key, int64_t v)
{
    at = put(at, " ");
    at = put(at, key);
    at = put(at, "=");
    return put_int(at, v);
}

static void say(char *at)
{
    at[0] = '\r';
    at[1] = '\n';
    at[2] = '\0';
    stm32f4_console_write(line);
}

static void park(void)
{
    parked = 1;
    for (;;) {
        stm32f4_idle();
    }
}

/* SysTick, every period: a tick that finds a period still running is counted; after the
 * end the watchdog is fed here (the motors are off; a reset would only park again). */
static void on_tick(void *ctx)
{
    (void)ctx;
    if (running) {
        cochlea_loop_tick(&the_loop);
    }
    if (parked && iwdg_on) {
        stm32f4_iwdg_kick(0);
    }
}

static void on_row(void *ctx, const cochlea_real *row, int row_length)
{
    const uint32_t before = stm32f4_timer_count();
    uint32_t spent;
    stm32f4_stream_row(ctx, row, row_length);
    spent = stm32f4_timer_count() - before;
    stream_row_max = spent > stream_row_max ? spent : stream_row_max;
}

static void kick(void *ctx)
{
    stm32f4_iwdg_kick(ctx);
    kicks += 1u;
}

static void end_line(int rule, int64_t run_ns)
{
    const stm32f4_stream_counts *sc;
    char *at;
    /* the rows still queued first, so that the end's counts are final (bounded: 2 s) */
    stm32f4_stream_flush_rows(stm32f4_now_ns() + 2000000000);
    sc = stm32f4_stream_counts_now();
    at = put(line, "end rule=");
    at = put(at, rule == COCHLEA_RULE_NONE ? "none" : cochlea_rule_name(rule));
    at = put_kv(at, "exit", rule == COCHLEA_RULE_NONE ? COCHLEA_EXIT_BACKEND
                                                      : cochlea_exit_code(rule));
    at = put_kv(at, "rows", the_loop.rows);
    at = put_kv(at, "kicks", kicks);
    at = put_kv(at, "tick_overruns", the_loop.tick_overruns);
    at = put_kv(at, "deadline_misses", the_loop.deadline_misses);
    at = put_kv(at, "overruns", the_loop.overruns);
    at = put_kv(at, "lateness_max_ns", the_loop.lateness_max_ns);
    at = put_kv(at, "t0_ns", the_loop.t0_ns);
    at = put_kv(at, "run_ns", run_ns);
    at = put_kv(at, "reads", bridge.reads);
    at = put_kv(at, "good_reads", bridge.good_reads);
    at = put_kv(at, "rx_overflows", bus.overflows);
    at = put(at, " failures=");
    {
        int kind, any = 0;
        for (kind = 0; kind < COCHLEA_FAIL_KINDS; ++kind) {
            if (bridge.failures[kind] > 0) {
                at = put(at, any ? "," : "");
                at = put(at, cochlea_failure_name(kind));
                at = put(at, ":");
                at = put_int(at, bridge.failures[kind]);
                any = 1;
            }
        }
        at = put(at, any ? "" : "none");
    }
    at = put_kv(at, "confirmed_off", bridge.confirmed_off);
    at = put(at, "/");
    at = put_int(at, bridge.n);
    at = put_kv(at, "stack_bytes", stm32f4_stack_used());
    /* where a rule was broken: the joint, and the value and limit in micro-SI (urad, um,
     * urad/s, um/s) */
    at = put_kv(at, "stop_joint", the_loop.stop.joint);
    at = put_kv(at, "stop_value_u", (int64_t)(the_loop.stop.value * 1e6));
    at = put_kv(at, "stop_limit_u", (int64_t)(the_loop.stop.limit * 1e6));
    /* the stop's time (us), and the row stream's counts (stream.h) */
#ifdef COCHLEA_FLOAT /* the period's float t rounded: the exact k h, after the run */
    at = put_kv(at, "stop_time_us",
                (int64_t)((the_loop.stop.period >= 0
                               ? cochlea_loop_time(&the_loop, the_loop.stop.period)
                               : (double)the_loop.stop.time_s) * 1e6));
#else
    at = put_kv(at, "stop_time_us", (int64_t)(the_loop.stop.time_s * 1e6));
#endif
    at = put_kv(at, "stream_every", sc->every);
    at = put_kv(at, "rows_seen", sc->rows_seen);
    at = put_kv(at, "rows_queued", sc->rows_queued);
    at = put_kv(at, "rows_dropped", sc->rows_dropped);
    at = put_kv(at, "rows_sent", sc->rows_sent);
    at = put_kv(at, "rows_crc", sc->rows_crc);
    at = put_kv(at, "frames", sc->frames);
    at = put_kv(at, "stream_row_counts_max", stream_row_max);
    at = put_kv(at, "stream_pump_counts_max", stream_pump_max);
    *at = '\0';
    stm32f4_stream_end(line + 4, stm32f4_now_ns() + 2000000000); /* without "end " */
    say(at);
}

/* The stream's header frame: what the host needs to write cochlea-run's files. */
static void stream_header(const cochlea_scenario *sc, double period, double duration, int clock)
{
    static const char *const clock_names[] = {"pll", "unmodelled", "no-hse", "no-pll"};
    const int length = cochlea_loop_row_length(sc);
    int i;
    char *at = put(line, "cochlea-stm32f4-stream version=1 scenario=" STR(STM32_SCENARIO)
                         " precision=");
    at = put(at, sc->real_size == 4 ? "float" : "double");
    at = put(at, " clock=");
    at = put(at, clock_names[clock]);
    at = put_kv(at, "period_ns", (int64_t)(period * 1e9 + 0.5));
    at = put_kv(at, "periods", (int64_t)(duration / period + 0.5));
    at = put_kv(at, "every", STM32_STREAM_EVERY);
    at = put_kv(at, "row_length", length > STREAM_MAX_ROW ? 0 : length);
    at = put_kv(at, "schema_version", sc->schema_version);
    at = put_kv(at, "watchdog_misses", STM32_WATCHDOG_MISSES);
    at = put_kv(at, "watchdog_errors", STM32_WATCHDOG_ERRORS);
    at = put_kv(at, "timer_hz", STM32_TIMER_HZ);
    at = put(at, " columns=");
    for (i = 0; i < sc->n_raw_columns; ++i) {
        at = put(at, i ? "," : "");
        at = put(at, sc->raw_columns[i]);
    }
    *at = '\0';
    stm32f4_stream_init(STM32_STREAM_BAUD, STM32_STREAM_EVERY, length, period);
    stm32f4_stream_header(line);
}

int main(void)
{
    const cochlea_scenario *sc = &CAT(STM32_SCENARIO, _scenario);
    const double duration = STM32_DURATION_S > 0.0 ? STM32_DURATION_S : sc->duration_s;
    const double period = STM32_RATE_HZ > 0 ? 1.0 / (double)STM32_RATE_HZ : sc->period_s;
    static const char *const clock_names[] = {"pll", "unmodelled", "no-hse", "no-pll"};
    cochlea_hal hal;
    cochlea_backend backend;
    cochlea_start_report report;
    int clock, rule, error;
    int64_t started;
    char *at;

    clock = stm32f4_clock_init();
    stm32f4_clock_start();
    stm32f4_console_init();
    at = put(line, "cochlea-stm32f4 scenario=" STR(STM32_SCENARIO) " precision=");
    at = put(at, sc->real_size == 4 ? "float" : "double");
    at = put(at, " clock=");
    at = put(at, clock_names[clock]);
    at = put_kv(at, "baud", STM32_BAUD);
    at = put_kv(at, "timer_hz", STM32_TIMER_HZ);
    at = put_kv(at, "period_ns", (int64_t)(period * 1e9 + 0.5));
    at = put_kv(at, "periods", (int64_t)(duration / period + 0.5));
    say(at);
    stream_header(sc, period, duration, clock);
    if (clock == STM32F4_CLOCK_NO_HSE || clock == STM32F4_CLOCK_NO_PLL) {
        say(put(line, "refused what=clock: the crystal or the PLL did not start; nothing moved"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    if (stm32f4_reset_by_watchdog()) {
        say(put(line, "refused what=watchdog-reset: the last run ended in a watchdog reset; "
                      "power-cycle to run again; nothing moved"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    {
        /* A slider's encoder loses its turns at power-on: without the homing record's check
         * (cochlea-run's --homing, not carried by this firmware) it must not move. */
        int j;
        for (j = 0; j < sc->nq; ++j) {
            if (!sc->drives[j].revolute) {
                say(put(line, "refused what=homing: a prismatic joint needs the homing record's "
                              "check, which this firmware does not carry; nothing moved"));
                end_line(COCHLEA_RULE_NONE, 0);
                park();
            }
        }
    }
    stm32f4_bus_init(&bus, STM32_BAUD);
    stm32f4_hal(&hal, &bus, STM32_RS485);
    if (sc->state_size > sizeof controller.bytes
        || stm32f4_tick_start((int64_t)(period * 1e9 + 0.5), on_tick, 0) != 0
        || cochlea_bridge_init(&bridge, &hal, sc->drives, sc->nq, STM32_READ_TIMEOUT_NS,
                               STM32_BUS_WATCHDOG_MS * 1e-3) != 0
        || cochlea_bridge_use_realtime_tick(&bridge) != 0) {
        say(put(line, "refused what=configuration: the scenario does not fit the firmware"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    bridge.offset_current = sc->bridge_offset_current;
    backend = cochlea_bridge_backend(&bridge);
    /* The controller before the motors: a configuration it refuses moves nothing. */
    error = cochlea_loop_init(&the_loop, sc, &hal, &backend, controller.bytes, period,
                              duration, STM32_WATCHDOG_MISSES, STM32_WATCHDOG_ERRORS, 1);
    if (error != COCHLEA_LOOP_OK) {
        at = put(line, "refused what=loop");
        say(put_kv(at, "error", error));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    the_loop.kick_watchdog = kick;
    the_loop.on_row = on_row; /* a copy into a slot, or a count: never a wait */
    if (!cochlea_bridge_start(&bridge, &report)) {
        at = put(line, "start failed");
        at = put_kv(at, "error", report.error);
        at = put_kv(at, "step", report.step);
        at = put_kv(at, "drive", report.drive);
        say(put_kv(at, "detail", report.detail));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    say(put(line, "start ok"));
    /* Period 0 right after a tick, so that each later tick comes just before its deadline. */
    {
        const uint32_t ticks = stm32f4_ticks();
        while (stm32f4_ticks() == ticks) {
            stm32f4_idle();
        }
    }
    running = 1;
    rule = cochlea_loop_begin(&the_loop);
    started = the_loop.t0_ns;
    stm32f4_iwdg_start(IWDG_RUN_MS);
    iwdg_on = 1;
    while (rule == COCHLEA_RULE_NONE) {
        /* waits (WFI) for its deadline: the tick's interrupt wakes the core */
        rule = cochlea_loop_period(&the_loop);
        {
            /* between periods: frames the queued rows */
            const uint32_t before = stm32f4_timer_count();
            uint32_t spent;
            stm32f4_stream_pump();
            spent = stm32f4_timer_count() - before;
            stream_pump_max = spent > stream_pump_max ? spent : stream_pump_max;
        }
    }
    stm32f4_iwdg_timeout(IWDG_STOP_MS);
    cochlea_loop_end(&the_loop); /* zero current, torque off, confirmed: every path */
    running = 0;
    end_line(rule, stm32f4_now_ns() - started);
    park();
    return 0;
}
