/* cochlea on a board (board.h: the STM32F4 and OpenCR ports): one scenario's real-time loop
 * over the Dynamixel bus, the same on every board.
 *
 * At reset: the bus's power switch off (OpenCR's; a no-op elsewhere), the clocks, the timer
 * as the 64-bit clock, the console, the bus (its receive ring), SysTick at the loop's period.
 * Then, as build/cochlea-embedded does: the controller and the loop first (a refused
 * configuration moves nothing), the bus's power on (and the motors' boot time), the bridge's
 * start-up (PING and model check, configuration, Bus Watchdog, first read; the torque with the
 * first nonzero command), and the periods: SysTick's interrupt (cochlea_loop_tick) wakes the
 * core from WFI and the main context runs cochlea_loop_period; the independent watchdog is
 * started with period 0 and kicked after every completed period (loop.kick_watchdog). Every
 * end goes through cochlea_loop_end (zero current, torque off, confirmed per motor), then the
 * bus's power goes off; the firmware then reports on the console and parks: it never starts
 * the motors again without a reset, and refuses to start at all after a watchdog reset.
 *
 * Compiled in: the scenario (STM32_SCENARIO), the run's length (STM32_DURATION_S, 0: the
 * scenario's), the watchdog counts (cochlea-run's --watchdog-misses, --watchdog-errors), the
 * bus's baud rate, its read timeout, whether the board switches an RS-485 (or half-duplex TTL)
 * transceiver's direction; for a prismatic joint, its homing record (STM32_HOMED).
 *
 * The console's lines (115200 8N1, key=value; docs/embedded.md, "STM32F4 port"; NAME is
 * board_name, stm32f4 or opencr):
 *   cochlea-NAME scenario=S precision=float|double clock=pll|unmodelled|no-hse|no-pll
 *       baud=B timer_hz=F period_ns=P periods=N [homed=DATE]
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
#include "board.h"
#include "loop.h"
#include "scenario.h"
#include "stream.h"

#ifdef STM32_HOMED
/* The slider's homing record, compiled in (make STM32_HOMING_RECORD=FILE: its drive, token and
 * offset, checked against the scenario by cochlea.dynamixel.homing_firmware at build time). */
#include "homing_record.h"
#endif

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
#define STM32_RS485 1 /* the board's direction pin drives the transceiver */
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

static cochlea_bridge bridge;
static cochlea_loop the_loop;
static union {
    double align; /* aligned for double loads (cochlea_rt.h) */
    uint8_t bytes[16384];
} controller;
static volatile int running; /* between cochlea_loop_begin and cochlea_loop_end */
static volatile int parked;  /* after the end: SysTick kicks the watchdog */
static volatile int iwdg_on;
static uint32_t kicks;
/* The row stream's own cost, in the board's timer counts (board_timer_hz(); 1 ns under QEMU,
 * where with -icount shift=0 a count is an instruction): the largest in-period on_row, and
 * the largest framing between two periods. */
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
    board_console_write(line);
}

static void park(void)
{
    parked = 1;
    for (;;) {
        board_idle();
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
        board_iwdg_kick(0);
    }
}

static void on_row(void *ctx, const cochlea_real *row, int row_length)
{
    const uint32_t before = board_timer_count();
    uint32_t spent;
    stream_row(ctx, row, row_length);
    spent = board_timer_count() - before;
    stream_row_max = spent > stream_row_max ? spent : stream_row_max;
}

static void kick(void *ctx)
{
    board_iwdg_kick(ctx);
    kicks += 1u;
}

static void end_line(int rule, int64_t run_ns)
{
    const stream_counts *sc;
    char *at;
    /* Every end comes here after the safe stop (torque off, confirmed per motor) or before
     * the bus started: the bus's power off. */
    board_bus_power(0);
    /* the rows still queued first, so that the end's counts are final (bounded: 2 s) */
    stream_flush_rows(board_now_ns() + 2000000000);
    sc = stream_counts_now();
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
    at = put_kv(at, "rx_overflows", board_bus_rx_overflows());
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
    at = put_kv(at, "stack_bytes", board_stack_used());
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
    stream_end(line + 4, board_now_ns() + 2000000000); /* without "end " */
    say(at);
}

/* The stream's header frame: what the host needs to write cochlea-run's files. */
static void send_header(const cochlea_scenario *sc, double period, double duration, int clock)
{
    static const char *const clock_names[] = {"pll", "unmodelled", "no-hse", "no-pll"};
    const int length = cochlea_loop_row_length(sc);
    int i;
    char *at = put(line, "cochlea-");
    at = put(at, board_name);
    at = put(at, "-stream version=1 scenario=" STR(STM32_SCENARIO) " precision=");
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
    at = put_kv(at, "timer_hz", board_timer_hz());
    at = put(at, " columns=");
    for (i = 0; i < sc->n_raw_columns; ++i) {
        at = put(at, i ? "," : "");
        at = put(at, sc->raw_columns[i]);
    }
    *at = '\0';
    stream_init(STM32_STREAM_BAUD, STM32_STREAM_EVERY, length, period);
    stream_header(line);
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

    board_bus_power(0); /* the motors stay unpowered until the bus starts */
    clock = board_clock_init();
    board_clock_start();
    board_console_init();
    at = put(line, "cochlea-");
    at = put(at, board_name);
    at = put(at, " scenario=" STR(STM32_SCENARIO) " precision=");
    at = put(at, sc->real_size == 4 ? "float" : "double");
    at = put(at, " clock=");
    at = put(at, clock_names[clock]);
    at = put_kv(at, "baud", STM32_BAUD);
    at = put_kv(at, "timer_hz", board_timer_hz());
    at = put_kv(at, "period_ns", (int64_t)(period * 1e9 + 0.5));
    at = put_kv(at, "periods", (int64_t)(duration / period + 0.5));
#ifdef STM32_HOMED
    at = put(at, " homed=" STM32_HOMING_DATE); /* the compiled-in record's date */
#endif
    say(at);
    send_header(sc, period, duration, clock);
    if (clock == BOARD_CLOCK_NO_HSE || clock == BOARD_CLOCK_NO_PLL) {
        say(put(line, "refused what=clock: the crystal or the PLL did not start; nothing moved"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    if (board_reset_by_watchdog()) {
        say(put(line, "refused what=watchdog-reset: the last run ended in a watchdog reset; "
                      "power-cycle to run again; nothing moved"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    {
        /* A slider's encoder loses its turns at power-on: it moves only counted from the
         * homing record compiled in, and only while its motor still holds the record's token
         * (the bridge reads it at the start, before any write: cochlea_bridge_expect_homing). */
        int j, sliders = 0;
        for (j = 0; j < sc->nq; ++j) {
            if (!sc->drives[j].revolute) {
                ++sliders;
#ifdef STM32_HOMED
                if (j != STM32_HOMING_DRIVE || sc->drives[j].id != STM32_HOMING_MOTOR_ID) {
                    sliders = -1; /* a record made for another scenario's joint */
                    break;
                }
#endif
            }
        }
#ifdef STM32_HOMED
        if (sliders != 1) {
            say(put(line, "refused what=homing: the homing record compiled in is not for this "
                          "scenario's prismatic joint (rebuild with its record); nothing moved"));
            end_line(COCHLEA_RULE_NONE, 0);
            park();
        }
#else
        if (sliders > 0) {
            say(put(line, "refused what=homing: a prismatic joint needs its homing record, "
                          "compiled in: build with STM32_HOMING_RECORD=FILE (OpenCR: "
                          "OPENCR_HOMING_RECORD), the record cochlea-dxl home wrote; nothing "
                          "moved"));
            end_line(COCHLEA_RULE_NONE, 0);
            park();
        }
#endif
    }
    board_bus_init(STM32_BAUD);
    board_bus_hal(&hal, STM32_RS485);
    if (sc->state_size > sizeof controller.bytes
        || board_tick_start((int64_t)(period * 1e9 + 0.5), on_tick, 0) != 0
        || cochlea_bridge_init(&bridge, &hal, sc->drives, sc->nq, STM32_READ_TIMEOUT_NS,
                               STM32_BUS_WATCHDOG_MS * 1e-3) != 0
        || cochlea_bridge_use_realtime_tick(&bridge) != 0) {
        say(put(line, "refused what=configuration: the scenario does not fit the firmware"));
        end_line(COCHLEA_RULE_NONE, 0);
        park();
    }
    bridge.offset_current = sc->bridge_offset_current;
#ifdef STM32_HOMED
    cochlea_bridge_expect_homing(&bridge, STM32_HOMING_DRIVE, STM32_HOMING_MARKER,
                                 STM32_HOMING_OFFSET_M);
#endif
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
    /* The bus's power on only now, the configuration accepted; then the motors' boot time
     * (none on a board without a switch). */
    board_bus_power(1);
    hal.wait_until_ns(hal.ctx, board_now_ns() + (int64_t)board_bus_power_settle_ms() * 1000000);
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
        const uint32_t ticks = board_ticks();
        while (board_ticks() == ticks) {
            board_idle();
        }
    }
    running = 1;
    rule = cochlea_loop_begin(&the_loop);
    started = the_loop.t0_ns;
    board_iwdg_start(IWDG_RUN_MS);
    iwdg_on = 1;
    while (rule == COCHLEA_RULE_NONE) {
        /* waits (WFI) for its deadline: the tick's interrupt wakes the core */
        rule = cochlea_loop_period(&the_loop);
        {
            /* between periods: frames the queued rows */
            const uint32_t before = board_timer_count();
            uint32_t spent;
            stream_pump();
            spent = board_timer_count() - before;
            stream_pump_max = spent > stream_pump_max ? spent : stream_pump_max;
        }
    }
    board_iwdg_timeout(IWDG_STOP_MS);
    cochlea_loop_end(&the_loop); /* zero current, torque off, confirmed: every path */
    running = 0;
    end_line(rule, board_now_ns() - started);
    park();
    return 0;
}
