"""Issue 28: nothing in the embedded core waits past its deadline, the core refuses a build that
would fold its NaN checks away, and the float build's time does not staircase.

- **No hang.** A small program drives ``embedded/core/bridge.c`` over a fake HAL whose clock
  advances a little per call (2.5 us per read, the time of one byte at 4 Mbaud) and whose line
  delivers, on every read, whatever the case says: one garbage byte, a full buffer of garbage,
  headers claiming the longest frame the parser accepts, headers packed as densely as they fit,
  valid status packets from a motor that is not in the chain, a stuck line, a byte just inside
  each timeout. ``cochlea_bridge_start`` and ``cochlea_bridge_read`` must return a failure
  within their deadlines counted in the fake clock (start: every transaction's timeout and
  retries; read: its timeout, plus the quiet line it waits for after a failed read), and the
  process must end within seconds of wall time. Before issue 28 every one of them looped
  forever (the deadline was checked only when a read returned no byte).
- **No fast-math.** Every core file and every generated controller fails to compile under
  ``-ffast-math`` and ``-ffinite-math-only``, with a message that says why; the supervisor's
  finiteness checks work on the bits.
- **No staircase.** In the float build (``COCHLEA_FLOAT``) the loop carries time as an int64
  period count and the desired trajectory is evaluated in double: at 2^31 and 2^40 periods of
  1 ms, 999 consecutive periods give 999 different desired samples, each the double build's
  to float rounding.

Every program is compiled with the embedded tests' warnings (-Wall -Wextra -Werror ...).
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from .embedded_build import WARNINGS, compiler

ROOT = Path(__file__).resolve().parents[1]
CORE = ROOT / "embedded" / "core"
GENERATED = ROOT / "generated_c" / "embedded"

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

MS = 1_000_000
TIMEOUT_NS = 5 * MS  # the bridge's read timeout in these runs
SETUP_NS = 20 * MS  # max(4 timeouts, 20 ms): a start-up transaction's
STOP_NS = 10 * MS  # max(timeout, 10 ms): a shut-down confirmation's
READ_STEP_NS = 2_500  # what the fake clock advances per serial_read call
WALL_S = 10.0  # generous: each case takes milliseconds

HARNESS = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "bridge.h"

/* The fake line: what every serial_read delivers, and a clock that moves only when called. */
typedef struct {
    int64_t t;            /* fake ns */
    const char *mode;
    uint32_t seed;
    uint8_t stream[4096]; /* a repeating pattern, for the structured modes */
    size_t stream_len, pos;
    long reads, writes;
    int64_t step;         /* ns per read */
    size_t split;         /* ontime: the first reply's length */
} fake;

static uint8_t noise(fake *f)
{
    f->seed = f->seed * 1103515245u + 12345u;
    return (uint8_t)(f->seed >> 16);
}

static int64_t now_ns(void *ctx) { return ((fake *)ctx)->t; }

static void wait_until_ns(void *ctx, int64_t deadline)
{
    fake *f = ctx;
    if (deadline > f->t) {
        f->t = deadline;
    }
}

static long serial_write(void *ctx, const uint8_t *data, size_t n)
{
    fake *f = ctx;
    (void)data;
    f->writes += 1;
    f->t += 1000;
    return (long)n;
}

static void from_stream(fake *f, uint8_t *data, size_t n)
{
    size_t i;
    for (i = 0; i < n; ++i) {
        data[i] = f->stream[f->pos];
        f->pos = (f->pos + 1) % f->stream_len;
    }
}

static long serial_read(void *ctx, uint8_t *data, size_t n, int64_t timeout_ns)
{
    fake *f = ctx;
    size_t i;
    f->reads += 1;
    if (n == 0) {
        return 0;
    }
    if (!strcmp(f->mode, "ontime")) {
        /* Both replies came in time, but the host got back to the line only after the
         * deadline (preempted for 0.5 us): the first reply from the wait, the second, already
         * there, only from a read that does not wait. */
        const size_t part = timeout_ns > 0 ? f->split : f->stream_len - f->split;
        const uint8_t *from = timeout_ns > 0 ? f->stream : f->stream + f->split;
        if (timeout_ns > 0) {
            f->t += timeout_ns + 500;
        }
        n = n < part ? n : part;
        memcpy(data, from, n);
        return (long)n;
    }
    if (!strcmp(f->mode, "silent")) {       /* nothing: the ordinary timeout */
        f->t += timeout_ns > 0 ? timeout_ns : 0;
        return 0;
    }
    if (!strcmp(f->mode, "slow")) {         /* one byte just inside every timeout */
        f->t += timeout_ns > 1 ? timeout_ns - 1 : 1;
        data[0] = noise(f);
        return 1;
    }
    f->t += f->step;
    if (!strcmp(f->mode, "byte")) {         /* one garbage byte per call */
        data[0] = noise(f);
        return 1;
    }
    if (!strcmp(f->mode, "burst")) {        /* a full buffer of garbage per call */
        for (i = 0; i < n; ++i) {
            data[i] = noise(f);
        }
        return (long)n;
    }
    if (!strcmp(f->mode, "stuck")) {        /* a line stuck at 0xFF */
        memset(data, 0xFF, n);
        return (long)n;
    }
    if (!strcmp(f->mode, "overlong")) {     /* more than asked: the parser must clamp */
        for (i = 0; i < n; ++i) {
            data[i] = noise(f);
        }
        return (long)n + 100;
    }
    from_stream(f, data, n);                /* huge, dense, stranger */
    return (long)n;
}

static void discard(void *ctx) { (void)ctx; }

/* The line of mode, and the HAL over it; 0, or nonzero on a bad mode. */
static int setup(fake *fp, cochlea_hal *hal, const char *mode)
{
    fake f;
    size_t i;
    memset(&f, 0, sizeof f);
    f.mode = mode;
    f.seed = 12345u;
    f.step = 2500;
    f.t = 1000000000LL;
    if (!strcmp(f.mode, "huge")) {          /* headers claiming a 2041-byte frame, then noise */
        const uint8_t h[7] = {0xFF, 0xFF, 0xFD, 0x00, 0x01, 0xF2, 0x07};
        memcpy(f.stream, h, 7);
        for (i = 7; i < 2100; ++i) {
            f.stream[i] = (uint8_t)(i * 37u + 11u);
        }
        f.stream_len = 2100;
    } else if (!strcmp(f.mode, "dense")) {  /* such headers back to back: the most CRC work */
        const uint8_t h[7] = {0xFF, 0xFF, 0xFD, 0x00, 0x01, 0xF2, 0x07};
        for (i = 0; i < 7 * 500; ++i) {
            f.stream[i] = h[i % 7];
        }
        f.stream_len = 7 * 500;
    } else if (!strcmp(f.mode, "stranger")) { /* good status packets from ID 200 */
        const uint8_t params[3] = {0x1F, 0x01, 0x2B};
        const int32_t len = dxl_status(f.stream, sizeof f.stream, 200, 0, params, 3);
        if (len <= 0) {
            return 3;
        }
        f.stream_len = (size_t)len;
    } else if (!strcmp(f.mode, "ontime")) { /* both motors' replies to the SYNC_READ */
        const uint8_t state[10] = {0}; /* Present Current .. Position (the MX-64's) */
        const int32_t one = dxl_status(f.stream, sizeof f.stream, 1, 0, state, sizeof state);
        const int32_t two = one > 0 ? dxl_status(f.stream + one, sizeof f.stream - (size_t)one,
                                                 2, 0, state, sizeof state) : -1;
        if (two <= 0) {
            return 3;
        }
        f.stream_len = (size_t)(one + two);
        f.split = (size_t)one;
    } else {
        f.stream_len = 1;
    }
    *fp = f;
    hal->ctx = fp;
    hal->serial_write = serial_write;
    hal->serial_read = serial_read;
    hal->serial_discard_input = discard;
    hal->rs485_direction = NULL;
    hal->now_ns = now_ns;
    hal->wait_until_ns = wait_until_ns;
    return 0;
}
/* MAIN */
/* Two MX-64s: their control-table items as the generated drive tables give them. */
#define MX64_ITEMS {{9, 1}, {11, 1}, {38, 2}, {64, 1}, {70, 1}, {98, 1}, {102, 2}, {88, 2}, \
                    {120, 2}, {126, 2}, {128, 4}, {132, 4}}
static const dxl_table TABLES[2] = {{"MX-64", MX64_ITEMS, 0}, {"MX-64", MX64_ITEMS, 0}};
static const dxl_bus BUS = {DXL_SYNC_READ, DXL_SYNC_WRITE, "SYNC_READ", 2, TABLES};
static const cochlea_drive DRIVES[2] = {
    {"arm1.link1", 1, 311, 1, 0.0015339807878856412, 0.0, 0.023980823922402087, 1.0,
     0.92, 20.0, 0.14, 297.6, 0.00336, 731, -2.96, 2.96, 6.0, 2.5, &BUS},
    {"arm1.link2", 2, 311, 1, 0.0015339807878856412, 0.0, 0.023980823922402087, 1.0,
     0.81, 20.0, 0.19, 297.6, 0.00336, 667, -2.96, 2.96, 6.0, 2.5, &BUS},
};

int main(int argc, char **argv)
{
    static fake f;
    static cochlea_bridge b;
    cochlea_hal hal;
    if (argc != 3 || setup(&f, &hal, argv[1]) != 0) {
        return 2;
    }
    if (cochlea_bridge_init(&b, &hal, DRIVES, 2, 5000000LL, 0.1) != 0) {
        return 4;
    }
    if (!strcmp(argv[2], "start")) {
        cochlea_start_report r;
        const int64_t t0 = f.t;
        const int ok = cochlea_bridge_start(&b, &r);
        printf("start ok=%d error=%d step=%d elapsed_ns=%lld reads=%ld writes=%ld\n", ok, r.error,
               r.step, (long long)(f.t - t0), f.reads, f.writes);
    } else {
        double q[2], qd[2];
        int k;
        b.active = 1;  /* as after a good start: the period's reads */
        for (k = 0; k < 8; ++k) {
            const int64_t t0 = f.t;
            const int ok = cochlea_bridge_read(&b, q, qd);
            printf("read ok=%d failure=%s elapsed_ns=%lld\n", ok,
                   cochlea_failure_name(b.last_failure), (long long)(f.t - t0));
        }
        {
            const int64_t t0 = f.t;
            const int confirmed = cochlea_bridge_stop(&b);
            printf("stop confirmed=%d elapsed_ns=%lld\n", confirmed, (long long)(f.t - t0));
        }
    }
    return 0;
}
"""

LINES = ["silent", "byte", "burst", "stuck", "overlong", "slow", "huge", "dense", "stranger"]


@pytest.fixture(scope="module")
def nohang(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("nohang")
    source = folder / "nohang.c"
    source.write_text(HARNESS)
    program = folder / "nohang"
    done = subprocess.run(
        [compiler(), *WARNINGS, "-O2", f"-I{CORE}", str(source), str(CORE / "bridge.c"),
         str(CORE / "dxl.c"), str(CORE / "drives.c"), "-lm", "-o", str(program)],
        capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return program


def run(program: Path, line: str, what: str | None) -> list[dict[str, str]]:
    began = time.monotonic()
    try:
        done = subprocess.run([str(program), line, *([what] if what else [])],
                              capture_output=True, text=True, timeout=WALL_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{what} on a {line!r} line still running after {WALL_S} s of wall time")
    wall = time.monotonic() - began
    assert done.returncode == 0, done.stderr
    assert wall < WALL_S
    rows = []
    for text in done.stdout.splitlines():
        kind, *fields = text.split()
        rows.append({"kind": kind, **dict(f.split("=", 1) for f in fields)})
    return rows


@pytest.mark.parametrize("line", LINES)
@pytest.mark.slow
def test_start_up_ends_at_its_deadlines_whatever_the_line_delivers(nohang, line):
    (row,) = run(nohang, line, "start")
    assert row["ok"] == "0"
    # PING of the first motor: 3 tries of one set-up timeout, then the safe stop's torque-off
    # confirmations: 2 tries of 10 ms per motor; each wait may overshoot by one read's step
    # (and every write takes 1 us of fake time).
    budget = 3 * SETUP_NS + 2 * 2 * STOP_NS + 64 * READ_STEP_NS
    assert int(row["elapsed_ns"]) <= budget, row
    assert int(row["elapsed_ns"]) >= 3 * SETUP_NS  # it did wait its timeouts
    assert row["error"] in ("1", "2")  # no answer, or corrupted answers only
    assert row["step"] == "1"  # at the first PING


@pytest.mark.parametrize("line", LINES)
@pytest.mark.slow
def test_each_read_ends_at_its_deadline_whatever_the_line_delivers(nohang, line):
    rows = run(nohang, line, "read")
    reads = [r for r in rows if r["kind"] == "read"]
    (stop,) = [r for r in rows if r["kind"] == "stop"]
    assert len(reads) == 8
    # the first read: its own timeout; every later one first waits for a quiet line (at most
    # two timeouts, then late-traffic) and then its own timeout
    first, later = reads[0], reads[1:]
    assert first["ok"] == "0"
    assert int(first["elapsed_ns"]) <= TIMEOUT_NS + 4 * READ_STEP_NS, first
    for r in later:
        assert r["ok"] == "0"
        assert int(r["elapsed_ns"]) <= 3 * TIMEOUT_NS + 8 * READ_STEP_NS, r
    assert first["failure"] in ("timeout", "crc")
    # the safe stop: its quiet line and two confirmations per motor, each at most 10 ms
    assert int(stop["elapsed_ns"]) <= 2 * TIMEOUT_NS + 2 * 2 * STOP_NS + 64 * READ_STEP_NS, stop
    assert stop["confirmed"] == "0"


LOOP = HARNESS.split("/* MAIN */")[0] + r"""
#include "loop.h"
#include "serial_joint.h"

extern const cochlea_scenario serial_joint_scenario;

int main(int argc, char **argv)
{
    static fake f;
    static cochlea_bridge b;
    static cochlea_loop loop;
    static serial_joint_state controller;
    const cochlea_scenario *sc = &serial_joint_scenario;
    cochlea_hal hal;
    cochlea_backend backend;
    int64_t t0;
    int rule;
    if (argc != 2 || setup(&f, &hal, argv[1]) != 0) {
        return 2;
    }
    if (cochlea_bridge_init(&b, &hal, sc->drives, sc->nq, 5000000LL, 0.1) != 0) {
        return 4;
    }
    b.active = 1;  /* as after a good start */
    backend = cochlea_bridge_backend(&b);
    /* 10 s at 1 kHz, the watchdog's defaults: 20 overruns, 5 failed reads; real time on the
     * fake clock */
    if (cochlea_loop_init(&loop, sc, &hal, &backend, &controller, 0.0, 10.0, 20, 5, 1)
        != COCHLEA_LOOP_OK) {
        return 5;
    }
    t0 = f.t;
    rule = cochlea_loop_run(&loop);
    printf("loop rule=%d exit=%d reason=%d rows=%lld elapsed_ns=%lld\n", rule,
           cochlea_exit_code(rule), loop.stop.reason, (long long)loop.rows,
           (long long)(f.t - t0));
    return 0;
}
"""


@pytest.fixture(scope="module")
def nohang_loop(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("nohang_loop")
    source = folder / "nohang_loop.c"
    source.write_text(LOOP)
    program = folder / "nohang_loop"
    done = subprocess.run(
        [compiler(), *WARNINGS, "-O2", f"-I{CORE}", f"-I{GENERATED}", str(source),
         *(str(CORE / f) for f in ("bridge.c", "dxl.c", "drives.c", "loop.c", "supervisor.c")),
         str(GENERATED / "serial_joint.c"), str(GENERATED / "serial_joint_scenario.c"), "-lm",
         "-o", str(program)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return program


@pytest.mark.parametrize("line", ["byte", "dense", "stranger", "slow"])
@pytest.mark.slow
def test_the_loops_watchdog_stops_a_run_on_a_babbling_line(nohang_loop, line):
    """The whole loop over the bridge: the reads fail within their deadlines, so the watchdog
    (failed reads, or the lateness they cause) ends the run through the safe stop, exit 15,
    in a fraction of a second of fake time."""
    (row,) = run(nohang_loop, line, None)
    assert row["exit"] == "15", row  # COCHLEA_WATCHDOG
    # at most 6 failed reads of 3 timeouts each, and the safe stop: its quiet line and two
    # 10 ms confirmations per motor (6)
    budget = 6 * (3 * TIMEOUT_NS + 8 * READ_STEP_NS) + 2 * TIMEOUT_NS + 6 * 2 * STOP_NS \
        + 6 * MS
    assert int(row["elapsed_ns"]) <= budget, row


@pytest.mark.slow
def test_a_reply_in_before_the_deadline_still_counts(nohang):
    """The deadline bounds the wait, not the bytes: replies that came in time but were read
    only after it (the host was busy when the wait ended) are taken, with one last look that
    does not wait."""
    rows = run(nohang, "ontime", "read")
    reads = [r for r in rows if r["kind"] == "read"]
    assert len(reads) == 8
    for r in reads:
        assert r["ok"] == "1", r
        assert int(r["elapsed_ns"]) <= TIMEOUT_NS + 2_000, r


# --------------------------------------------------------------------------------------------
# No fast-math build
# --------------------------------------------------------------------------------------------

FAST_MATH = {"-ffast-math": "do not build with -ffast-math",
             "-ffinite-math-only": "do not build with -ffinite-math-only"}


def fast_math_sources() -> list[Path]:
    """Every core file but the codec (dxl.c: integers only, standalone by design), a whole
    generated scenario (controller and its runtime table) and the library's closed loop:
    everything that computes in floating point."""
    core = [c for c in sorted(CORE.glob("*.c")) if c.name != "dxl.c"]
    assert len(core) >= 4
    return [*core, GENERATED / "serial_task.c",
            GENERATED / "serial_task_scenario.c", ROOT / "generated_c" / "closed_loop.c"]


@pytest.mark.parametrize("flag", sorted(FAST_MATH))
@pytest.mark.slow
def test_a_build_that_would_fold_the_nan_checks_is_refused(flag, tmp_path):
    for source in fast_math_sources():
        for precision in ([], ["-DCOCHLEA_FLOAT"]):
            done = subprocess.run(
                [compiler(), *WARNINGS, "-O2", flag, *precision, f"-I{CORE}",
                 f"-I{GENERATED}", f"-I{ROOT / 'generated_c'}", "-c", str(source), "-o",
                 str(tmp_path / "x.o")], capture_output=True, text=True)
            assert done.returncode != 0, f"{source.name} {flag} {precision}: compiled"
            assert FAST_MATH[flag] in done.stderr, done.stderr[-2000:]
            assert "NaN and infinity checks" in done.stderr
            assert not (tmp_path / "x.o").exists()


@pytest.mark.slow
def test_the_same_sources_compile_without_it(tmp_path):
    """The refusal is the flag's, not the sources': the same commands without it succeed."""
    for source in fast_math_sources():
        done = subprocess.run(
            [compiler(), *WARNINGS, "-O2", f"-I{CORE}", f"-I{GENERATED}",
             f"-I{ROOT / 'generated_c'}", "-c", str(source), "-o", str(tmp_path / "x.o")],
            capture_output=True, text=True)
        assert done.returncode == 0, f"{source.name}: {done.stderr[-2000:]}"


FINITE = r"""
#include <stdio.h>
#include "cochlea_rt.h"

int main(void)
{
    volatile double zero = 0.0;
    const double nan = zero / zero, inf = 1.0 / zero;
    const double values[] = {0.0, -0.0, 1.0, -2.5, 1e-310, 1.7976931348623157e308, nan, -nan,
                             inf, -inf};
    const double lo[1] = {-1.0}, hi[1] = {1.0}, vel[1] = {1.0}, eff[1] = {1.0};
    cochlea_limits limits = {1, lo, hi, vel, eff, 0.0, 1, 1};
    const double p[1] = {0.5};
    const double *estimates[1] = {p};
    const int n_params[1] = {1};
    const double bound[1] = {1.0};
    cochlea_stop stop;
    size_t i;
    for (i = 0; i < sizeof values / sizeof values[0]; ++i) {
        const double tau[1] = {values[i]};
        printf("%d %d\n", cochlea_finite(values[i]),
               cochlea_check_command(&limits, 0.0, tau, 1, estimates, n_params, bound, &stop));
    }
    return 0;
}
"""


def test_the_finiteness_test_reads_the_bits(tmp_path):
    """cochlea_finite on every class of double; the supervisor refuses NaN, infinite and
    unsquarable commands (the Python supervisor's rule) and passes the others."""
    source = tmp_path / "finite.c"
    source.write_text(FINITE)
    program = tmp_path / "finite"
    done = subprocess.run([compiler(), *WARNINGS, "-O2", f"-I{CORE}", str(source),
                           str(CORE / "supervisor.c"), "-lm", "-o", str(program)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    rows = [tuple(map(int, line.split()))
            for line in subprocess.run([str(program)], capture_output=True, text=True,
                                       timeout=30).stdout.splitlines()]
    finite = [r[0] for r in rows]
    refused = [r[1] for r in rows]
    assert finite == [1, 1, 1, 1, 1, 1, 0, 0, 0, 0]
    # the largest double squares to infinity: non-finite to the supervisor, as in Python
    assert refused == [0, 0, 0, 0, 0, 1, 1, 1, 1, 1]


# --------------------------------------------------------------------------------------------
# No staircase in the float build
# --------------------------------------------------------------------------------------------

STAIRCASE = r"""
#include <stdio.h>
#include <stdlib.h>
#include "loop.h"
#include "serial_joint.h"

/* the loop carries its period count in 64 bits */
typedef char steps_are_int64[sizeof(((cochlea_loop *)0)->steps) == 8 ? 1 : -1];
typedef char rows_are_int64[sizeof(((cochlea_loop *)0)->rows) == 8 ? 1 : -1];

int main(int argc, char **argv)
{
    static cochlea_loop loop;
    int64_t k0, k;
    long n;
    if (argc != 3) {
        return 2;
    }
    k0 = (int64_t)strtoll(argv[1], NULL, 10);
    n = strtol(argv[2], NULL, 10);
    loop.period_s = SERIAL_JOINT_PERIOD;
    for (k = k0; k < k0 + n; ++k) {
        const double t = cochlea_loop_time(&loop, k);  /* the loop's own t of period k */
        serial_joint_real xd[SERIAL_JOINT_ND], xd_dot[SERIAL_JOINT_ND], xd_ddot[SERIAL_JOINT_ND];
        int i;
        if (serial_joint_desired(t, xd, xd_dot, xd_ddot) != 0) {
            return 3;
        }
        printf("%a", t);
        for (i = 0; i < SERIAL_JOINT_ND; ++i) {
            printf(" %a %a %a", (double)xd[i], (double)xd_dot[i], (double)xd_ddot[i]);
        }
        printf("\n");
    }
    return 0;
}
"""


@pytest.fixture(scope="module")
def staircase(tmp_path_factory):
    folder = tmp_path_factory.mktemp("staircase")
    source = folder / "staircase.c"
    source.write_text(STAIRCASE)
    programs = {}
    for precision, flags in (("double", []), ("float", ["-DCOCHLEA_FLOAT"])):
        program = folder / f"staircase-{precision}"
        done = subprocess.run(
            [compiler(), *WARNINGS, "-O2", *flags, f"-I{CORE}", f"-I{GENERATED}", str(source),
             str(CORE / "loop.c"), str(CORE / "supervisor.c"), str(GENERATED / "serial_joint.c"),
             "-lm", "-o",
             str(program)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-3000:]
        programs[precision] = program
    return programs


def samples(program: Path, k0: int, n: int):
    import numpy as np
    out = subprocess.run([str(program), str(k0), str(n)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    rows = np.array([[float.fromhex(x) for x in line.split()]
                     for line in out.stdout.splitlines()])
    return rows[:, 0], rows[:, 1:]


@pytest.mark.parametrize("k0", [2**31 - 500, 2**40 - 500, 86_400_000])
@pytest.mark.slow
def test_the_float_build_has_no_staircase_at_any_run_length(staircase, k0):
    """999 consecutive 1 ms periods around 2^31 and 2^40 periods (24.9 days, 34.8 years) and
    from one day: every period a new time and a new desired sample, each the double
    build's rounded to float."""
    import numpy as np
    n = 999
    t, single = samples(staircase["float"], k0, n)
    t_double, double = samples(staircase["double"], k0, n)
    assert np.array_equal(t, t_double)
    assert np.all(np.diff(t) > 0)  # the loop's t resolves every period
    assert np.allclose(np.diff(t), 1e-3, rtol=1e-3, atol=0)
    repeats = int(np.sum(np.all(single[1:] == single[:-1], axis=1)))
    assert repeats == 0, f"{repeats} of {n - 1} periods repeat the previous desired sample"
    assert np.array_equal(single, double.astype(np.float32).astype(np.float64))
