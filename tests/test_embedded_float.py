"""Issue 28, items 3 and 4: the embedded loop one period at a time, and the float build on a
single-precision FPU.

* ``cochlea_loop_begin`` / ``cochlea_loop_period`` / ``cochlea_loop_end`` (embedded/core/loop.h)
  give the rows of ``cochlea_loop_run`` bit for bit (timing columns included, on a fake clock),
  the same rule and the same single shutdown;
* the optional ``kick_watchdog`` callback is called once per completed period, never after a
  rule;
* a tick of the port's period timer that finds a period still running is counted
  (``cochlea_loop_tick``, ``tick_overruns``), and only then;
* the float build's desired trajectory takes its time as the int64 period count (phases in
  64-bit integer turns, docs/embedded.md "The float build"): no staircase at 2^31 and 2^40
  periods, and within a documented bound of the double build's;
* the float build's period, cross-compiled for a Cortex-M4F, reaches no software double routine
  (``__aeabi_d*``, static call graph): not from the desired trajectory, not from the whole
  period (loop, supervisor, controller, estimate, goal current), also on the STM32F4 port
  (bridge, row stream, HAL, interrupts);
* its drive conversions (float, integer counts) within one LSB / a hundredth of a count of the
  double ones. (Its estimate, a compensated two-float sum, against the double build's in closed
  loop: tests/test_embedded_generated.py, test_float_build_follows_the_double_build.)
"""

from __future__ import annotations

import ctypes
import re
import shutil
import subprocess

import numpy as np
import pytest

from tests.embedded_build import ROOT, build_library, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

GENERATED = ROOT / "generated_c" / "embedded"
CORE = ROOT / "embedded" / "core"
PERIOD_NS = 1_000_000  # serial_joint's 1 kHz

_HARNESS = r"""
#include <math.h>
#include <string.h>
#include "loop.h"
#include "scenarios.h"

/* A fake clock: now_ns returns the time and then advances it by one step (a few us: the
 * work between two readings); wait_until_ns jumps to the deadline. The port's period timer
 * ticks at every deadline t0 + m h: a tick that the clock passes is delivered like an
 * interrupt, by calling cochlea_loop_tick, wherever the loop is. */
static cochlea_loop loop;
static double storage[16384];
static int64_t clock_ns, next_tick, step_ns, slow_step_ns;
static int64_t slow_k;
static long kicks, kicks_after_stop, shutdowns;
static double *rows_out;
static long rows_cap, rows_seen;

static void deliver_ticks(void)
{
    while (next_tick <= clock_ns) {
        cochlea_loop_tick(&loop);
        next_tick += loop.period_ns;
    }
}
static int64_t now_ns(void *c)
{
    int64_t t = clock_ns;
    (void)c;
    clock_ns += (loop.in_period && loop.k == slow_k) ? slow_step_ns : step_ns;
    deliver_ticks();
    return t;
}
static void wait_until_ns(void *c, int64_t deadline)
{
    (void)c;
    if (deadline > clock_ns) {
        clock_ns = deadline;
    }
    deliver_ticks();
}
static int b_read(void *c, double *q, double *qd)
{
    int i;
    (void)c;
    for (i = 0; i < loop.scenario->nq; ++i) {
        q[i] = 0.1 * sin(0.003 * (double)loop.k + (double)i);
        qd[i] = 0.3 * cos(0.003 * (double)loop.k + (double)i);
    }
    return 1;
}
static int b_write(void *c, const double *tau) { (void)c; (void)tau; return 1; }
static int b_shutdown(void *c) { (void)c; shutdowns += 1; return loop.scenario->nq; }
static void on_row(void *c, const double *row, int n)
{
    (void)c;
    if (rows_seen < rows_cap) {
        memcpy(rows_out + rows_seen * n, row, (size_t)n * sizeof *row);
    }
    rows_seen += 1;
}
static void kick(void *c)
{
    (void)c;
    kicks += 1;
    if (loop.stop.rule != COCHLEA_RULE_NONE) {
        kicks_after_stop += 1;
    }
}

int harness_row_length(void) { return cochlea_loop_row_length(&serial_joint_scenario); }

/* Runs serial_joint for `periods` periods, in real time on the fake clock; whole: through
 * cochlea_loop_run, else begin / period until a rule / end. Period slow (if >= 0) takes
 * slow_step per clock reading. out[rows x row_length]; counts[0..6]: rule, rows, kicks,
 * kicks after a rule, tick overruns, the loop's overruns, shutdowns. */
int harness_run(int whole, int use_kick, long periods, long slow, long step, long slow_step,
                double *out, long cap, long *counts)
{
    static cochlea_hal hal;
    cochlea_backend backend;
    const cochlea_scenario *sc = &serial_joint_scenario;
    int rule;
    hal.now_ns = now_ns;
    hal.wait_until_ns = wait_until_ns;
    backend.ctx = 0;
    backend.read = b_read;
    backend.write = b_write;
    backend.shutdown = b_shutdown;
    backend.current = 0;
    clock_ns = 1000000000LL;
    next_tick = clock_ns; /* period 0's deadline is t0, the first reading of begin */
    step_ns = step;
    slow_step_ns = slow_step;
    slow_k = slow;
    kicks = kicks_after_stop = shutdowns = 0;
    rows_out = out;
    rows_cap = cap;
    rows_seen = 0;
    if (cochlea_loop_init(&loop, sc, &hal, &backend, storage, 0.0,
                          (double)periods * sc->period_s, 20, 5, 1) != COCHLEA_LOOP_OK) {
        return -1;
    }
    loop.on_row = on_row;
    if (use_kick) {
        loop.kick_watchdog = kick;
    }
    if (whole) {
        rule = cochlea_loop_run(&loop);
    } else {
        rule = cochlea_loop_begin(&loop);
        while (rule == COCHLEA_RULE_NONE) {
            rule = cochlea_loop_period(&loop);
        }
        if (cochlea_loop_period(&loop) != rule) { /* the run has ended: the same rule */
            return -2;
        }
        if (cochlea_loop_end(&loop) != rule) {
            return -3;
        }
    }
    counts[0] = rule;
    counts[1] = (long)loop.rows;
    counts[2] = kicks;
    counts[3] = kicks_after_stop;
    counts[4] = (long)loop.tick_overruns;
    counts[5] = (long)loop.overruns;
    counts[6] = shutdowns;
    return 0;
}
"""


@pytest.fixture(scope="module")
def harness():
    sources = (sorted(CORE.glob("*.c")) + sorted(GENERATED.glob("*.c"))
               + [("float_harness.c", _HARNESS)])
    lib = ctypes.CDLL(str(build_library("embedded_float", sources, ("-O2", "-lm"),
                                        include=(CORE, GENERATED))))
    lib.harness_run.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.c_long, ctypes.c_long,
                                ctypes.c_long, ctypes.c_long,
                                ctypes.POINTER(ctypes.c_double), ctypes.c_long,
                                ctypes.POINTER(ctypes.c_long)]
    return lib


def run(lib, *, whole: bool, periods: int = 400, slow: int = -1, step_ns: int = 20_000,
        slow_step_ns: int = 20_000, kick: bool = True):
    n = lib.harness_row_length()
    rows = np.full((periods + 1, n), -1.0)
    counts = (ctypes.c_long * 7)()
    code = lib.harness_run(int(whole), int(kick), periods, slow, step_ns, slow_step_ns,
                           rows.ctypes.data_as(ctypes.POINTER(ctypes.c_double)), periods + 1,
                           counts)
    assert code == 0, f"harness refused: {code}"
    rule, nrows, kicks, late_kicks, ticks, overruns, shutdowns = list(counts)
    return dict(rule=rule, rows=rows[:nrows], kicks=kicks, late_kicks=late_kicks,
                tick_overruns=ticks, overruns=overruns, shutdowns=shutdowns)


COMPLETED, WATCHDOG = 1, 8


@pytest.mark.parametrize("slow", [-1, 150])
def test_begin_period_end_rows_bit_for_bit(harness, slow):
    """The split run logs the whole run's rows bit for bit (timing columns included), ends
    with the same rule and shuts down once; also with an overrunning period in it."""
    kwargs = dict(slow=slow, slow_step_ns=400_000)
    whole, split = run(harness, whole=True, **kwargs), run(harness, whole=False, **kwargs)
    assert whole["rule"] == split["rule"] == COMPLETED
    assert len(whole["rows"]) == len(split["rows"]) == 400
    assert whole["rows"].tobytes() == split["rows"].tobytes()
    assert whole["shutdowns"] == split["shutdowns"] == 1
    assert whole["overruns"] == split["overruns"]


def test_watchdog_kicked_once_per_period(harness):
    """kick_watchdog: once per completed period, none after the rule; none when unset."""
    for whole in (True, False):
        r = run(harness, whole=whole, periods=250)
        assert r["rule"] == COMPLETED
        assert r["kicks"] == len(r["rows"]) == 250
        assert r["late_kicks"] == 0
    assert run(harness, whole=False, kick=False)["kicks"] == 0


def test_watchdog_not_kicked_after_a_rule(harness):
    """A run the loop's own watchdog stops (every period from 100 on overruns: 20 in a row
    allowed) gets no kick for the period that broke the rule, nor after it."""
    r = run(harness, whole=False, periods=400, slow=100, slow_step_ns=10_000_000)
    assert r["rule"] == WATCHDOG
    assert r["kicks"] == 100  # periods 0..99; period 100 was a stall
    assert r["late_kicks"] == 0


@pytest.mark.parametrize("whole", [True, False])
def test_tick_overrun_counted(harness, whole):
    """A period still running at the next tick is one tick overrun; on time, none."""
    on_time = run(harness, whole=whole)
    assert on_time["rule"] == COMPLETED and on_time["tick_overruns"] == 0
    # Period 150: 0.25 ms per clock reading, 1.25 ms from its start to its end reading and
    # 1.5 ms to its return: the tick of period 151 fires while it runs (one tick only).
    late = run(harness, whole=whole, slow=150, slow_step_ns=250_000)
    assert late["rule"] == COMPLETED
    assert late["tick_overruns"] == 1
    assert late["overruns"] == 1  # the loop's own rule sees the same period


# --------------------------------------------------------------------------------------------
# The float build's desired trajectory from the period count
# --------------------------------------------------------------------------------------------

_DESIRED = r"""
#include <stdio.h>
#include <stdlib.h>
#include "SCENARIO.h"

/* desired_period of the scenario's default configuration at periods k0 .. k0 + n - 1, one
 * line each in hex: x, x_dot, x_ddot of every coordinate. */
int main(int argc, char **argv)
{
    static SCENARIO_state s;
    SCENARIO_config c;
    SCENARIO_real xd[UPPER_ND], xd_dot[UPPER_ND], xd_ddot[UPPER_ND];
    int64_t k0, k;
    long n;
    int i;
    if (argc != 3) {
        return 2;
    }
    k0 = (int64_t)strtoll(argv[1], NULL, 10);
    n = strtol(argv[2], NULL, 10);
    SCENARIO_default_config(&c);
    if (SCENARIO_init(&s, &c) != 0) {
        return 3;
    }
    for (k = k0; k < k0 + n; ++k) {
        if (SCENARIO_desired_period(&s, k, xd, xd_dot, xd_ddot) != 0) {
            return 4;
        }
        for (i = 0; i < UPPER_ND; ++i) {
            printf(" %a %a %a", (double)xd[i], (double)xd_dot[i], (double)xd_ddot[i]);
        }
        printf("\n");
    }
    return 0;
}
"""

#: The float build's desired against the double build's, per coordinate and derivative: at
#: most this times (1 + the largest |value| of that column in the samples). Measured: the
#: float evaluation of the trajectory (a few roundings of 6e-8) and its phase (under 2e-7
#: rad, 2^-32 turns plus the Q0.64 increment's error times k) give at most ~1e-6.
DESIRED_BOUND = 4e-6


@pytest.fixture(scope="module")
def desired_programs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("desired-period")
    programs = {}
    for scenario in ("serial_joint", "parallel_task"):
        source = folder / f"{scenario}_desired.c"
        source.write_text(_DESIRED.replace("SCENARIO", scenario)
                          .replace("UPPER", scenario.upper()))
        for precision, flags in (("double", []), ("float", ["-DCOCHLEA_FLOAT"])):
            program = folder / f"{scenario}-{precision}"
            done = subprocess.run(
                [compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", *flags,
                 f"-I{GENERATED}", str(source), str(GENERATED / f"{scenario}.c"), "-lm", "-o",
                 str(program)], capture_output=True, text=True)
            assert done.returncode == 0, done.stderr[-3000:]
            programs[scenario, precision] = program
    return programs


def desired_samples(program, k0: int, n: int) -> np.ndarray:
    out = subprocess.run([str(program), str(k0), str(n)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    return np.array([[float.fromhex(x) for x in line.split()]
                     for line in out.stdout.splitlines()])


@pytest.mark.parametrize("k0", [0, 86_400_000, 2**31 - 500, 2**40 - 500])
@pytest.mark.slow
def test_float_desired_from_the_period_count_has_no_staircase(desired_programs, k0):
    """serial_joint's sinusoid at 999 consecutive 1 ms periods from 0, one day, 2^31 and 2^40
    periods (24.9 days, 34.8 years): every period a new sample in float, and within
    DESIRED_BOUND of the double build's (which forms t = (double)k h)."""
    n = 999
    single = desired_samples(desired_programs["serial_joint", "float"], k0, n)
    double = desired_samples(desired_programs["serial_joint", "double"], k0, n)
    assert single.shape == double.shape and single.shape[0] == n
    moving = np.abs(double[1:] - double[:-1]).max(axis=0) > 0  # the columns that move
    repeats = int(np.sum(np.all(single[1:, moving] == single[:-1, moving], axis=1)))
    assert repeats == 0, f"{repeats} of {n - 1} periods repeat the previous desired sample"
    scale = 1.0 + np.abs(double).max(axis=0)
    err = float((np.abs(single - double) / scale).max())
    assert err <= DESIRED_BOUND, f"float desired off the double build's by {err:.3g}"


@pytest.mark.slow
def test_float_desired_switches_at_the_double_builds_period(desired_programs):
    """parallel_task's move ends at t = 5 s (fmin(t, 5), t <= 5, 5 <= t): the float build
    switches at the same period as the double build and stays within DESIRED_BOUND, also
    at 2^40 periods (the move long over)."""
    for k0, n in ((4_990, 20), (0, 400), (2**40 - 10, 20)):
        single = desired_samples(desired_programs["parallel_task", "float"], k0, n)
        double = desired_samples(desired_programs["parallel_task", "double"], k0, n)
        scale = 1.0 + np.abs(double).max(axis=0)
        err = float((np.abs(single - double) / scale).max())
        assert err <= DESIRED_BOUND, f"from period {k0}: off by {err:.3g}"
        # the velocity and acceleration are exactly 0 from the switch on in both builds
        still_d = np.all(double[:, 1::3] == 0, axis=1)
        still_s = np.all(single[:, 1::3] == 0, axis=1)
        assert np.array_equal(still_d, still_s)
        if k0 == 4_990:  # the switch is inside this window
            assert still_d.any() and not still_d.all()


# --------------------------------------------------------------------------------------------
# Software double in the float build's period, on a Cortex-M4F
# --------------------------------------------------------------------------------------------

ARM_CC, OBJDUMP = "arm-none-eabi-gcc", "arm-none-eabi-objdump"
M4F = ("-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard", "-O2")
#: The run-time library's software double routines (ARM EABI: __aeabi_d*, conversions to and
#: from double) and libm's double functions reached through them.
_SOFT_DOUBLE = re.compile(r"^(__aeabi_(d\w+|[ilu]+2d|f2d|ul2d|l2d)|__\w*df\w*)$")
_CALL = re.compile(r"\t(?:bl|b(?:\.w|\.n)?|b[a-z]{2}(?:\.w|\.n)?)\s+[0-9a-f]+ <([^>+]+)>")


def call_graph(elf) -> dict[str, set[str]]:
    """The static call graph of an ELF from its disassembly: direct calls (bl) and branches
    to another function (tail calls). Calls through pointers are not in it."""
    text = subprocess.run([OBJDUMP, "-d", str(elf)], capture_output=True, text=True,
                          check=True).stdout
    graph: dict[str, set[str]] = {}
    current = None
    for line in text.splitlines():
        m = re.match(r"^[0-9a-f]+ <([^>]+)>:$", line)
        if m:
            current = m.group(1)
            graph[current] = set()
            continue
        m = _CALL.search(line)
        if m and current and m.group(1) != current:
            graph[current].add(m.group(1))
    return graph


def reachable(graph, roots) -> dict[str, str]:
    """Every function reachable from roots, each with the function that first reached it."""
    parent = {r: "" for r in roots if r in graph}
    stack = list(parent)
    while stack:
        f = stack.pop()
        for g in graph.get(f, ()):
            if g not in parent:
                parent[g] = f
                stack.append(g)
    return parent


def soft_double(graph, roots) -> list[str]:
    """The software double routines reachable from roots, each with its call chain."""
    parent = reachable(graph, roots)
    out = []
    for f in sorted(parent):
        if _SOFT_DOUBLE.match(f):
            chain, g = [f], f
            while parent.get(g):
                g = parent[g]
                chain.append(g)
            out.append(" <- ".join(chain))
    return out


@pytest.fixture(scope="module")
def m4f_elf(tmp_path_factory):
    """serial_task and parallel_task_realistic's float controllers with the core, linked for
    a Cortex-M4F (single-precision FPU) by the QEMU port's linker script."""
    if shutil.which(ARM_CC) is None or shutil.which(OBJDUMP) is None:
        pytest.fail(f"{ARM_CC} or {OBJDUMP} missing: embedded/ports/ensure_tools.sh installs "
                    "them", pytrace=False)
    folder = tmp_path_factory.mktemp("m4f")
    out = {}
    qemu = ROOT / "embedded" / "ports" / "qemu_mps2"
    for scenario in ("serial_task", "parallel_task_realistic"):
        elf = folder / f"{scenario}.elf"
        done = subprocess.run(
            [ARM_CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-ffp-contract=off", *M4F,
             "-DCOCHLEA_FLOAT", f"-I{CORE}", f"-I{GENERATED}", f"-I{qemu}",
             *map(str, sorted(CORE.glob("*.c"))), str(GENERATED / f"{scenario}.c"),
             str(GENERATED / f"{scenario}_scenario.c"), str(qemu / "replay.c"),
             str(qemu / "port_mps2.c"), f"-DREPLAY_SCENARIO={scenario}",
             f"-DREPLAY_INPUTS=<inputs_{scenario}.h>", "-T", str(qemu / "mps2.ld"),
             "-nostartfiles", "--specs=nano.specs", "--specs=nosys.specs",
             "-Wl,--gc-sections", "-lm", "-o", str(elf)], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-3000:]
        out[scenario] = call_graph(elf)
    return out


@pytest.mark.parametrize("scenario", ["serial_task", "parallel_task_realistic"])
@pytest.mark.slow
def test_float_desired_calls_no_software_double(m4f_elf, scenario):
    """The float build's trajectory at period k (<name>_desired_period, what the loop's
    period runs) reaches no __aeabi_d* routine on a Cortex-M4F (it reached sin and cos in
    double before: 57 % of the period with the rest of the double below)."""
    graph = m4f_elf[scenario]
    assert f"{scenario}_desired_period" in graph
    found = soft_double(graph, [f"{scenario}_desired_period"])
    assert found == [], "\n".join(found)


#: What a float period runs on the Cortex-M4F replay (qemu_mps2/replay.c): the loop's period,
#: the scenario's entries it calls through pointers, and the goal current the replay's write
#: computes (the bridge's, on a board).
PERIOD_ROOTS = ("cochlea_loop_period", "step_period", "tool_points", "estimate")
#: The goal current's conversion the replay calls: the working precision's, or the double one
#: before it existed (the double one is linked in either way: drives.o is one section).
GOAL_CURRENT = ("cochlea_drive_goal_current_real", "cochlea_drive_goal_current")


@pytest.mark.parametrize("scenario", ["serial_task", "parallel_task_realistic"])
@pytest.mark.slow
def test_the_float_period_reaches_no_software_double(m4f_elf, scenario):
    """Issue 28 item 3: the whole float period on a Cortex-M4F (the loop, the supervisor,
    the controller and its estimate's compensated sum, the clip, the goal current) reaches
    no software double routine: 0 (14 before: the loop's and the supervisor's double
    interface, the scenario wrapper's conversions, the double estimate, the goal current)."""
    graph = m4f_elf[scenario]
    assert [r for r in PERIOD_ROOTS if r not in graph] == []
    goal = [g for g in GOAL_CURRENT if g in graph][:1]  # the first present: what it calls
    assert goal
    found = soft_double(graph, [*PERIOD_ROOTS, *goal])
    assert found == [], f"{len(found)} software double routines:\n" + "\n".join(found)
    # the call graph does see them where they are: the start-up's conversions run in double
    assert soft_double(graph, ["cochlea_drive_real_init"])
    assert soft_double(graph, ["cochlea_loop_init"])


@pytest.mark.slow
def test_the_stm32_float_firmware_period_reaches_no_software_double(tmp_path):
    """The STM32F4 board port in float (make stm32-firmware): its period -- the loop, the
    bridge's read (integer counts to float) and write (goal currents in float), the row
    stream's on_row, the watchdog kick, the HAL's clock and the interrupts that run inside
    a period -- reaches no software double routine. The double left in the firmware runs
    outside the period: the start-up, the report, the stream's framing between periods."""
    if shutil.which(ARM_CC) is None or shutil.which(OBJDUMP) is None:
        pytest.fail(f"{ARM_CC} or {OBJDUMP} missing: embedded/ports/ensure_tools.sh installs "
                    "them", pytrace=False)
    done = subprocess.run(["make", "--no-print-directory", "-s", f"BUILD={tmp_path}",
                           str(tmp_path / "stm32f4" / "float" / "cochlea-stm32f4.elf")],
                          cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warning" not in done.stderr
    graph = call_graph(tmp_path / "stm32f4" / "float" / "cochlea-stm32f4.elf")
    # the ports' shared firmware (embedded/ports/common/): its on_row and watchdog kick, the
    # board's clock and watchdog, the interrupts
    roots = ["cochlea_loop_period", "step_period", "tool_points", "estimate", "on_row",
             "kick", "stream_row", "board_now_ns", "stm32_hal_now", "board_iwdg_kick",
             "SysTick_Handler", "USART1_IRQHandler"]
    assert [r for r in roots if r not in graph] == []
    # the bridge's read and write, or the backend's adapters they are inlined into
    bridge = [r for r in ("cochlea_bridge_read", "cochlea_bridge_write", "backend_read",
                          "backend_write") if r in graph]
    assert {"read", "write"} <= {r.rsplit("_", 1)[1] for r in bridge}, bridge
    found = soft_double(graph, roots + bridge)
    assert found == [], f"{len(found)} software double routines:\n" + "\n".join(found)
    assert soft_double(graph, ["stream_pump"])  # widening the row, between periods


# --------------------------------------------------------------------------------------------
# The float build's drive conversions and estimate against the double build's
# --------------------------------------------------------------------------------------------

_DRIVES = r"""
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include "drives.h"
#include "ROBOT_drives.h"

/* Per drive: the float conversions (cochlea_drive_*_real, COCHLEA_FLOAT) against the double
 * functions of the same file. Prints, per drive: efforts tried, goal currents equal, the
 * largest goal current difference (LSB), the largest position difference over counts
 * sweeping the joint's range and 3 turns beyond (in counts), the largest relative velocity
 * difference. */
int main(void)
{
    int i;
    for (i = 0; i < ROBOT_N_DRIVES; ++i) {
        const cochlea_drive *d = &ROBOT_drives[i];
        cochlea_drive_real c;
        const double offset = d->q_offset + (d->revolute ? 2.0 * 3.141592653589793 : 0.0);
        const double span = d->position_hi - d->position_lo;
        const double q_turn = d->revolute ? 2.0 * 3.141592653589793 : span;
        long n = 0, same = 0, j;
        int worst = 0;
        double pos = 0.0, vel = 0.0;
        cochlea_drive_real_init(&c, d, offset);
        for (j = -200000; j <= 200000; ++j) {
            const double e = 1.3 * d->effort_limit * (double)j / 200000.0;
            const int a = cochlea_drive_goal_current(d, e, 1);
            const int b = cochlea_drive_goal_current_real(&c, (float)e, 1);
            n += 1;
            same += a == b;
            worst = abs(a - b) > worst ? abs(a - b) : worst;
        }
        for (j = 0; j <= 100000; ++j) {
            const double q = d->position_lo - q_turn * 3.0 + (span + 6.0 * q_turn) * j / 1e5;
            const int32_t counts = (int32_t)lround((q - offset) / d->q_per_count);
            const double want = cochlea_drive_position(d, counts, offset);
            const double got = (double)cochlea_drive_position_real(&c, counts);
            const double err = fabs(got - want) / fabs(d->q_per_count);
            pos = err > pos ? err : pos;
        }
        for (j = -30000; j <= 30000; j += 7) {
            const double want = cochlea_drive_velocity(d, (int32_t)j);
            const double got = (double)cochlea_drive_velocity_real(&c, (int32_t)j);
            const double err = j ? fabs(got - want) / fabs(want) : fabs(got);
            vel = err > vel ? err : vel;
        }
        printf("%s %ld %ld %d %.3g %.3g\n", d->name, n, same, worst, pos, vel);
    }
    return 0;
}
"""


@pytest.mark.parametrize("robot", ["serial", "parallel"])
def test_float_drive_conversions_follow_the_double_ones(tmp_path, robot):
    """Each shipped drive: the float goal current (in float, rounded by the float's own
    rounding, no nearbyint) is the double one's LSB on almost every effort and never more
    than one LSB off (400 001 efforts over 1.3 times the effort limit, clipped ones
    included); the float position (integer count difference from the middle of the limits)
    is within a hundredth of a count of the double one over the range and 3 turns beyond;
    the velocity within float rounding."""
    source = tmp_path / "drives_check.c"
    source.write_text(_DRIVES.replace("ROBOT", robot)
                      .replace(f"{robot}_N_DRIVES", f"{robot.upper()}_N_DRIVES"))
    program = tmp_path / "drives_check"
    done = subprocess.run(
        [compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-ffp-contract=off",
         "-DCOCHLEA_FLOAT", f"-I{CORE}", f"-I{GENERATED}", str(source), str(CORE / "drives.c"),
         "-lm", "-o", str(program)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = subprocess.run([str(program)], capture_output=True, text=True, timeout=60,
                           check=True).stdout.splitlines()
    assert len(lines) >= 5
    for line in lines:
        name, n, same, worst, pos, vel = line.split()
        assert int(worst) <= 1, line
        assert int(same) >= 0.999 * int(n), line
        assert float(pos) <= 0.01, line
        assert float(vel) <= 1.2e-7, line


# The float build's estimate against the double build's in closed loop (a compensated sum):
# tests/test_embedded_generated.py's test_float_build_follows_the_double_build (estimate_drift,
# DRIFT_BOUND), which this file had a copy of.


_SUPERVISOR = r"""
#include <math.h>
#include <stdio.h>
#include "cochlea_rt.h"

/* The float build's supervisor (COCHLEA_FLOAT: cochlea_real is float) on the refusals of the
 * double build: one line per case, "state|command|estimate <rule>" (0: none broken). */
int main(void)
{
    const float lo[2] = {-1.0f, -1.0f}, hi[2] = {1.0f, 1.0f}, vel[2] = {2.0f, 2.0f};
    const float eff[2] = {3.0f, 3.0f};
    const cochlea_limits limits = {2, lo, hi, vel, eff, 0.0f, 1, 1};
    const float bound[1] = {1.0f};
    const int n_params[1] = {2};
    /* Finite, its square overflows float: a position, a speed, an estimate past their limits
     * as in Python (where it does not overflow); a command so large stops as non-finite. */
    const float big = 3.0e19f;
    const float states[][4] = {{0.5f, 0.5f, 0.1f, 0.1f}, {NAN, 0.5f, 0.1f, 0.1f},
                               {0.5f, 0.5f, INFINITY, 0.1f}, {1.5f, 0.5f, 0.1f, 0.1f},
                               {0.5f, 0.5f, 0.1f, -2.5f}, {big, 0.0f, 0.0f, 0.0f}};
    const float commands[][2] = {{1.0f, -1.0f}, {NAN, 0.0f}, {0.0f, -INFINITY}, {big, 0.0f}};
    /* |p_hat| = 1 (at the bound), 1 + 1e-6 (within the float tolerance), 1 + 1e-5 (over) */
    const float estimates[][2] = {{0.6f, 0.8f}, {0.6000006f, 0.8000008f},
                                  {0.600006f, 0.800008f}, {NAN, 0.0f}, {-big, 0.0f}};
    cochlea_stop stop;
    size_t i;
    for (i = 0; i < sizeof states / sizeof states[0]; ++i) {
        const int broke = cochlea_check_state(&limits, 0.5f, states[i], states[i] + 2, &stop);
        printf("state %d\n", broke ? stop.rule : 0);
    }
    for (i = 0; i < sizeof commands / sizeof commands[0]; ++i) {
        const float *p[1] = {estimates[0]};
        const int broke = cochlea_check_command(&limits, 0.5f, commands[i], 1, p, n_params,
                                                bound, &stop);
        printf("command %d\n", broke ? stop.rule : 0);
    }
    for (i = 0; i < sizeof estimates / sizeof estimates[0]; ++i) {
        const float tau[2] = {0.0f, 0.0f};
        const float *p[1] = {estimates[i]};
        const int broke = cochlea_check_command(&limits, 0.5f, tau, 1, p, n_params, bound,
                                                &stop);
        printf("estimate %d %.3g\n", broke ? stop.rule : 0, broke ? (double)stop.value : 0.0);
    }
    return 0;
}
"""


def test_the_float_supervisor_keeps_every_refusal(tmp_path):
    """The supervisor compiled in float refuses what the double one refuses: a NaN or
    infinite state or command, a position or speed past its limit (one whose square
    overflows float too: position-limit, not non-finite), a NaN estimate and an estimate over
    its bound by 1e-5 or by 3e19 (its square overflows float: estimate-bound, with its norm);
    it passes an estimate at its bound and 1e-6 over it (the float tolerance, 16 float
    epsilons: 1 + 1e-9 is 1 in float). A command of 3e19 N m, which double clips, float
    stops as non-finite (its squares overflow): stricter, not looser."""
    source = tmp_path / "supervisor_check.c"
    source.write_text(_SUPERVISOR)
    program = tmp_path / "supervisor_check"
    done = subprocess.run(
        [compiler(), "-std=c99", "-Wall", "-Wextra", "-Werror", "-Wdouble-promotion", "-O2",
         "-DCOCHLEA_FLOAT", f"-I{CORE}", str(source), str(CORE / "supervisor.c"), "-lm", "-o",
         str(program)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = subprocess.run([str(program)], capture_output=True, text=True, timeout=30,
                           check=True).stdout.split("\n")
    NON_FINITE, POSITION, VELOCITY, BOUND = 6, 3, 4, 7
    assert lines[:-1] == [f"state {r}" for r in (0, NON_FINITE, NON_FINITE, POSITION,
                                                 VELOCITY, POSITION)] \
        + [f"command {r}" for r in (0, NON_FINITE, NON_FINITE, NON_FINITE)] \
        + [f"estimate {r}" for r in ("0 0", "0 0", f"{BOUND} 1", f"{NON_FINITE} 0",
                                     f"{BOUND} 3e+19")]
