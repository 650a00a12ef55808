/* cochlea on a Cortex-M core: one scenario's whole period loop (embedded/core/loop.c: the
 * supervisor, the generated controller, the clip) replayed on canned measurements, each
 * period's command and Dynamixel goal current printed bit for bit.
 *
 * The same file builds for QEMU's mps2 boards (port_mps2.c: semihosting) and for the host
 * (port_host.c: stdout), so the two outputs can be compared line for line
 * (tests/test_embedded_qemu.py). The scenario is compiled in: -DREPLAY_SCENARIO=serial_task and
 * an inputs header (inputs_<scenario>.h, written by record_inputs.py from a host simulation)
 * named by -DREPLAY_INPUTS='<inputs_serial_task.h>' (found on the include path, so a test can put
 * other inputs first).
 *
 * Output, one line each, all numbers lower-case hex:
 *   S <scenario> <precision: double|float> <nq> <periods>
 *   R <k> <tau[0..nq) as the 16 hex digits of each IEEE double (N m, N)> <goal current[0..nq)
 *     as the 4 hex digits of each int16 (the drive's LSB)>
 *   P <the final estimate p_hat[0..np) as 16 hex digits each>
 *   C <calibration ticks> <calibration instructions> <ticks of all periods> <ticks of the
 *     longest period>: the port's tick counter (port_ticks) from each period's read to its
 *     write (the supervisor, the controller, the clip: not the printing). On the mps2 port
 *     under `qemu-system-arm -icount shift=0` a tick is a fixed number of instructions, which
 *     the calibration (a loop of known length) measures: instructions per period =
 *     ticks / periods * calibration instructions / calibration ticks. The host port: zeros.
 *   E <rule (enum cochlea_rule)> <rows>
 * then the port ends with status 0 when the loop ran every period (rule "completed"), 1 when
 * a rule stopped it, 2 when the loop refused its configuration.
 * No malloc, no stdio: the port prints whole lines (port_line). */
#include <stdint.h>

#include "cochlea_rt.h"
#include "loop.h"
#include "scenario.h"

#ifndef REPLAY_SCENARIO
#error "define REPLAY_SCENARIO (the scenario's name) and REPLAY_INPUTS (its inputs header)"
#endif
#define REPLAY_CAT2(a, b) a##b
#define REPLAY_CAT(a, b) REPLAY_CAT2(a, b)
#define REPLAY_STR2(a) #a
#define REPLAY_STR(a) REPLAY_STR2(a)
#define REPLAY_SC REPLAY_CAT(REPLAY_SCENARIO, _scenario)

#include REPLAY_INPUTS /* INPUT_NQ, INPUT_STEPS, input_q[INPUT_STEPS][INPUT_NQ], input_qd */

extern const cochlea_scenario REPLAY_SC;

/* The port: print one line (no newline in it) and end the program with a status. */
void port_line(const char *text);
void port_exit(int status);
/* A free-running 24-bit tick counter, counting up (0 where the port has none), and the ticks
 * of a loop of *instructions instructions (the port sets it). */
uint32_t port_ticks(void);
uint32_t port_calibrate(uint32_t *instructions);

typedef struct {
    long k;                          /* the period the next read measures */
    uint32_t read_tick;              /* port_ticks() at the period's read */
    uint64_t ticks;                  /* the periods' ticks, read to write, added up */
    uint32_t longest;                /* the longest period's */
    const cochlea_scenario *sc;
    char line[1024]; /* the longest: P and 17 characters per parameter */
} replay;

static replay the_replay;
/* The canned measurements in the working precision (rounded once before the run, so that a
 * period's read is a copy in both builds), and each drive's conversions (drives.h). */
static cochlea_real replay_q[INPUT_STEPS][INPUT_NQ], replay_qd[INPUT_STEPS][INPUT_NQ];
static cochlea_drive_real replay_conv[INPUT_NQ];
/* The controller's state, aligned for any real type. */
static double controller[8192];
static cochlea_loop the_loop;

static char *put_str(char *at, const char *s)
{
    while (*s) {
        *at++ = *s++;
    }
    return at;
}

static char *put_hex(char *at, uint64_t v, int digits)
{
    static const char hex[] = "0123456789abcdef";
    int i;
    *at++ = ' ';
    for (i = digits - 1; i >= 0; --i) {
        *at++ = hex[(v >> (4 * i)) & 0xfu];
    }
    return at;
}

static uint64_t bits(double x)
{
    union {
        double d;
        uint64_t u;
    } v;
    v.d = x;
    return v.u;
}

static int replay_read(void *ctx, cochlea_real *q, cochlea_real *qd)
{
    replay *r = (replay *)ctx;
    int j;
    long k = r->k < INPUT_STEPS ? r->k : INPUT_STEPS - 1;
    r->read_tick = port_ticks();
    for (j = 0; j < INPUT_NQ; ++j) {
        q[j] = replay_q[k][j];
        qd[j] = replay_qd[k][j];
    }
    return 1;
}

static int replay_write(void *ctx, const cochlea_real *tau)
{
    replay *r = (replay *)ctx;
    char *at = r->line;
    int j, n = r->sc->nq;
    uint32_t ticks = (port_ticks() - r->read_tick) & 0xffffffu;
    r->ticks += ticks;
    r->longest = ticks > r->longest ? ticks : r->longest;
    at = put_str(at, "R");
    at = put_hex(at, (uint64_t)r->k, 4);
    for (j = 0; j < n; ++j) {
        at = put_hex(at, bits((double)tau[j]), 16);
    }
    for (j = 0; j < n; ++j) {
        int16_t goal = cochlea_drive_goal_current_real(&replay_conv[j], tau[j],
                                                       r->sc->bridge_offset_current);
        at = put_hex(at, (uint16_t)goal, 4);
    }
    *at = '\0';
    port_line(r->line);
    r->k += 1;
    return 1;
}

static int replay_shutdown(void *ctx)
{
    return ((replay *)ctx)->sc->nq;
}

int replay_main(void)
{
    const cochlea_scenario *sc = &REPLAY_SC;
    replay *r = &the_replay;
    cochlea_backend backend;
    char *at;
    const cochlea_real *p;
    int j, rule;
    long k;
    uint32_t calibration_instructions = 0, calibration_ticks;
    r->k = 0;
    r->ticks = 0;
    r->longest = 0;
    r->sc = sc;
    if (sc->nq != INPUT_NQ || sc->state_size > sizeof controller || sc->np > 56) {
        port_line("E inputs or state do not fit the scenario");
        return 2;
    }
    for (k = 0; k < INPUT_STEPS; ++k) {
        for (j = 0; j < INPUT_NQ; ++j) {
            replay_q[k][j] = (cochlea_real)input_q[k][j];
            replay_qd[k][j] = (cochlea_real)input_qd[k][j];
        }
    }
    for (j = 0; j < INPUT_NQ; ++j) {
        cochlea_drive_real_init(&replay_conv[j], &sc->drives[j], sc->drives[j].q_offset);
    }
    backend.ctx = r;
    backend.read = replay_read;
    backend.write = replay_write;
    backend.shutdown = replay_shutdown;
    backend.current = 0;
    at = put_str(r->line, "S " REPLAY_STR(REPLAY_SCENARIO));
    at = put_str(at, sc->real_size == 4 ? " float" : " double");
    at = put_hex(at, (uint64_t)sc->nq, 4);
    at = put_hex(at, (uint64_t)INPUT_STEPS, 4);
    *at = '\0';
    port_line(r->line);
    calibration_ticks = port_calibrate(&calibration_instructions);
    /* Back to back (not real time), no clock: the timing columns are 0. */
    if (cochlea_loop_init(&the_loop, sc, 0, &backend, controller, sc->period_s,
                          INPUT_STEPS * sc->period_s, 10, 3, 0) != COCHLEA_LOOP_OK) {
        port_line("E loop init refused");
        return 2;
    }
    rule = cochlea_loop_run(&the_loop);
    p = sc->estimate(controller);
    at = put_str(r->line, "P");
    for (j = 0; j < sc->np; ++j) {
        at = put_hex(at, bits((double)p[j]), 16);
    }
    *at = '\0';
    port_line(r->line);
    at = put_str(r->line, "C");
    at = put_hex(at, calibration_ticks, 8);
    at = put_hex(at, calibration_instructions, 8);
    at = put_hex(at, r->ticks, 16);
    at = put_hex(at, r->longest, 8);
    *at = '\0';
    port_line(r->line);
    at = put_str(r->line, "E");
    at = put_hex(at, (uint64_t)rule, 4);
    at = put_hex(at, (uint64_t)the_loop.rows, 4);
    *at = '\0';
    port_line(r->line);
    return rule == COCHLEA_COMPLETED ? 0 : 1;
}
