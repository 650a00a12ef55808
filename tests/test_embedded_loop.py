"""The C loop (embedded/core/loop.c) is cochlea/runtime/loop.py's: driven through ctypes against
the same simulated robot (the Python ``SimBackend`` behind C callbacks), it logs the same rows
as ``RealTimeLoop`` period for period, and every supervisor rule a backend can provoke (a joint
outside its limits, too fast, a tool point in the keep-out circle, a non-finite state, failed
reads, a stop request) ends it at the same period with the same rule and the same row, after
exactly one safe shutdown."""

from __future__ import annotations

import ctypes
import math

import numpy as np
import pytest

from cochlea.runtime.loop import RealTimeLoop
from cochlea.runtime.sim_backend import SimBackend
from cochlea.runtime.supervisor import STOP_CODES, build_supervisor
from cochlea.sim import load_scenario, unit_setups
from tests.embedded_build import ROOT, build_library, compiler

pytestmark = pytest.mark.skipif(compiler() is None, reason="no C compiler")

GENERATED = ROOT / "generated_c" / "embedded"
CORE = ROOT / "embedded" / "core"

READ = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_double),
                        ctypes.POINTER(ctypes.c_double))
WRITE = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_double))
SHUTDOWN = ctypes.CFUNCTYPE(ctypes.c_int)
ROW = ctypes.CFUNCTYPE(None, ctypes.POINTER(ctypes.c_double), ctypes.c_int)

_SHIM = r"""
#include "loop.h"
#include "scenarios.h"

typedef int (*read_fn)(double *, double *);
typedef int (*write_fn)(const double *);
typedef int (*shutdown_fn)(void);
typedef void (*row_fn)(const double *, int);
static read_fn rd;
static write_fn wr;
static shutdown_fn sd;
static row_fn rw;
static cochlea_loop loop;
static double storage[16384]; /* the controller's state: aligned for doubles */
static double current[16];     /* the backend's measured current, filled by its read */

static int b_read(void *c, double *q, double *qd) { (void)c; return rd(q, qd); }
static int b_write(void *c, const double *tau) { (void)c; return wr(tau); }
static int b_shutdown(void *c) { (void)c; return sd(); }
static void on_row(void *c, const double *row, int n) { (void)c; rw(row, n); }

int shim_index(const char *name)
{
    int i, k;
    for (i = 0; cochlea_scenarios[i]; ++i) {
        const char *a = cochlea_scenarios[i]->name;
        for (k = 0; a[k] && a[k] == name[k]; ++k) {
        }
        if (a[k] == name[k]) return i;
    }
    return -1;
}

int shim_row_length(int i) { return cochlea_loop_row_length(cochlea_scenarios[i]); }

void shim_request_stop(int rule) { loop.stop_request = rule; }

double *shim_current(void) { return current; }

int shim_run(int i, read_fn r, write_fn w, shutdown_fn s, row_fn row, double duration,
             int misses, int errors, int measured, double *stop)
{
    cochlea_backend backend;
    int code;
    if (cochlea_scenarios[i]->state_size > sizeof storage) return -100;
    rd = r; wr = w; sd = s; rw = row;
    backend.ctx = 0; backend.read = b_read; backend.write = b_write;
    backend.shutdown = b_shutdown;
    backend.current = measured ? current : 0;
    code = cochlea_loop_init(&loop, cochlea_scenarios[i], 0, &backend, storage, 0.0,
                             duration, misses, errors, 0);
    if (code != COCHLEA_LOOP_OK) return -code;
    loop.on_row = on_row;
    code = cochlea_loop_run(&loop);
    stop[0] = loop.stop.time_s; stop[1] = loop.stop.joint; stop[2] = loop.stop.unit;
    stop[3] = loop.stop.what; stop[4] = loop.stop.value; stop[5] = loop.stop.limit;
    stop[6] = loop.stop.count; stop[7] = loop.stop.reason; stop[8] = (double)loop.rows;
    return code;
}

const char *shim_rule_name(int rule) { return cochlea_rule_name(rule); }
int shim_exit_code(int rule) { return cochlea_exit_code(rule); }
"""


@pytest.fixture(scope="module")
def lib():
    sources = sorted(CORE.glob("*.c")) + sorted(GENERATED.glob("*.c"))
    path = build_library("loop", [*sources, ("shim.c", _SHIM)], ("-O2",),
                         include=[CORE, GENERATED])
    library = ctypes.CDLL(str(path))
    library.shim_index.argtypes = [ctypes.c_char_p]
    library.shim_run.argtypes = [ctypes.c_int, READ, WRITE, SHUTDOWN, ROW, ctypes.c_double,
                                 ctypes.c_int, ctypes.c_int, ctypes.c_int,
                                 ctypes.POINTER(ctypes.c_double)]
    library.shim_current.restype = ctypes.POINTER(ctypes.c_double)
    library.shim_rule_name.restype = ctypes.c_char_p
    return library


#: A's per N m of the stand-in drives that measure current (any factor that is not 1 will do).
AMPS_PER_EFFORT = 0.37


class Injected:
    """A backend around ``SimBackend`` that changes what period ``at`` (and later) reads.
    ``measured``: its drives measure current, as the Dynamixel bridge's do (the loop logs
    ``joint_current_A``): each good read reports the effort last written times
    AMPS_PER_EFFORT plus the period's index in mA, so every period's value is its own."""

    def __init__(self, backend: SimBackend, at: int = -1, change=None, fail_from: int = -1,
                 measured: bool = False, fail_first: int = 0):
        self.backend, self.at, self.change, self.fail_from = backend, at, change, fail_from
        self.fail_first = fail_first  # the first reads fail, before anything is measured
        self.k = 0
        self.last_io_time_s = 0.0
        self.shutdowns = 0
        self.written = np.zeros(backend.nq)
        self.joint_current_A = np.zeros(backend.nq) if measured else None

    def enable(self):
        self.backend.enable()

    def disable(self):
        self.shutdowns += 1
        self.backend.disable()

    def read(self, x: np.ndarray) -> bool:
        k, self.k = self.k, self.k + 1
        if 0 <= self.fail_from <= k or k < self.fail_first:
            return False
        ok = self.backend.read(x)
        if k == self.at and self.change is not None:
            self.change(x)
        if ok and self.joint_current_A is not None:
            self.joint_current_A[:] = AMPS_PER_EFFORT * self.written + 1e-3 * k
        return ok

    def write(self, tau: np.ndarray) -> bool:
        ok = self.backend.write(tau)
        self.written[:] = tau  # as applied (on the drives' grid, where the plant has one)
        return ok


def python_run(name: str, periods: int, **injection):
    sc = load_scenario(name)
    setups = unit_setups(sc)
    backend = Injected(SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant,
                                  steps=periods), **injection)
    supervisor = build_supervisor(setups, sc.system.keep_out_radius)
    loop = RealTimeLoop(setups, backend, supervisor, sc.period, periods, realtime=False,
                        substeps=sc.plant_substeps)
    stop = loop.run()
    # The measured current goes last; a backend that measures none has no such columns (one
    # schema for every log: cochlea.log_schema).
    assert loop.current_at == loop.width - (0 if backend.joint_current_A is None else loop.n)
    rows = loop.buffer[:loop.rows].copy()
    if backend.joint_current_A is None:  # the C loop's row always has the block: NaN here
        rows = np.hstack([rows, np.full((len(rows), loop.n), np.nan)])
    return stop, rows, backend


def c_run(lib, name: str, periods: int, **injection):
    sc = load_scenario(name)
    setups = unit_setups(sc)
    n = sum(u.controller_model.nq for u in setups)
    backend = Injected(SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant,
                                  steps=periods), **injection)
    backend.enable()
    x = np.zeros(2 * n)
    rows, written = [], []

    current = np.ctypeslib.as_array(lib.shim_current(), (n,))

    def read(q, qd):
        x[:n] = np.ctypeslib.as_array(q, (n,))
        x[n:] = np.ctypeslib.as_array(qd, (n,))
        ok = backend.read(x)
        np.ctypeslib.as_array(q, (n,))[:] = x[:n]
        np.ctypeslib.as_array(qd, (n,))[:] = x[n:]
        if ok and backend.joint_current_A is not None:  # the bridge's: good reads only
            current[:] = backend.joint_current_A
        return int(ok)

    def write(tau):
        applied = np.ctypeslib.as_array(tau, (n,)).copy()
        ok = backend.write(applied)  # on the drives' effort grid, in place, where it has one
        written.append(applied)
        return int(ok)

    def shutdown():
        backend.write(np.zeros(n))
        backend.disable()
        return n

    def row(values, length):
        rows.append(np.ctypeslib.as_array(values, (length,)).copy())

    callbacks = READ(read), WRITE(write), SHUTDOWN(shutdown), ROW(row)
    stop = (ctypes.c_double * 9)()
    index = lib.shim_index(name.encode())
    assert index >= 0
    rule = lib.shim_run(index, *callbacks, periods * sc.period, 20, 5,
                        int(backend.joint_current_A is not None), stop)
    assert rule > 0, rule
    rows = np.array(rows)
    # The loop logs the command it wrote (as the Dynamixel bridge's run does); the simulated
    # drives apply it on their effort grid, which the Python loop's SimBackend logs instead.
    for k, applied in enumerate(written):
        tau = rows[k, 1 + 2 * n:1 + 3 * n]
        quantum = np.concatenate([u.effort_grid.quantum if u.effort_grid is not None
                                  else np.zeros(u.controller_model.nq) for u in setups])
        assert np.all(np.abs(tau - applied) <= 0.5 * quantum + 1e-12 * np.abs(tau)), k
        rows[k, 1 + 2 * n:1 + 3 * n] = applied
    return rule, list(stop), rows, backend


def assert_rows_equal(c_rows: np.ndarray, py_rows: np.ndarray, n: int):
    """Every column but the four of timing (before the n of measured current); NaN where the
    other has NaN; the timing NaN in the same rows."""
    assert c_rows.shape == py_rows.shape
    timing = np.arange(c_rows.shape[1] - n - 4, c_rows.shape[1] - n)
    a, b = np.delete(c_rows, timing, axis=1), np.delete(py_rows, timing, axis=1)
    assert np.array_equal(np.isnan(a), np.isnan(b))
    finite = ~np.isnan(a)
    scale = np.maximum(1.0, np.abs(b))
    assert np.max(np.abs(a - b)[finite] / scale[finite], initial=0.0) < 1e-9
    assert np.array_equal(np.isnan(c_rows[:, timing]).all(axis=1),
                          np.isnan(py_rows[:, timing]).all(axis=1))


@pytest.mark.parametrize("name", ["serial_joint", "serial_task", "parallel_joint",
                                  "parallel_task", "serial_task_realistic",
                                  "parallel_task_realistic"])
@pytest.mark.slow
def test_the_c_loop_logs_the_python_loops_rows(lib, name):
    """400 periods, or up to the same stop: on the realistic preset's geared plant (issue 24)
    the serial arms' realistic controller meets the MX-64's backlash and the supervisor stops
    it on the velocity limit within 30 ms, in C and in Python at the same period."""
    periods = 400
    rule, stop, c_rows, backend = c_run(lib, name, periods)
    py_stop, py_rows, py_backend = python_run(name, periods)
    expected = "velocity-limit" if name == "serial_task_realistic" else "completed"
    assert lib.shim_rule_name(rule).decode() == py_stop.rule == expected
    assert stop[0] == pytest.approx(py_stop.time) and stop[8] == len(py_rows)
    assert len(py_rows) == periods or expected != "completed"
    n = backend.backend.nq
    assert_rows_equal(c_rows, py_rows, n)
    assert np.isnan(c_rows[:, -n:]).all()  # a simulated robot measures no current
    assert backend.shutdowns == py_backend.shutdowns == 1


def assert_current_logged(rows: np.ndarray, backend: Injected, good_reads: int):
    """The current block of each row is what the read of its period reported, after the
    timing: the effort written the period before (AMPS_PER_EFFORT) plus the index of the
    period's read in mA; after the last good read, that read's."""
    n = backend.backend.nq
    tau, current = rows[:, 1 + 2 * n:1 + 3 * n], rows[:, -n:]
    assert np.isfinite(current).all()
    k = np.minimum(np.arange(len(rows)), good_reads - 1)
    previous = np.vstack([np.zeros(n), tau[:-1]])[k]
    assert np.allclose(current, AMPS_PER_EFFORT * previous + 1e-3 * k[:, None], rtol=0,
                       atol=1e-12)


@pytest.mark.parametrize("name", ["serial_task", "parallel_joint"])
@pytest.mark.slow
def test_a_backends_measured_current_is_logged_after_the_timing_as_python_does(lib, name):
    periods = 300
    rule, stop, c_rows, backend = c_run(lib, name, periods, measured=True)
    py_stop, py_rows, _ = python_run(name, periods, measured=True)
    assert lib.shim_rule_name(rule).decode() == py_stop.rule == "completed"
    assert_rows_equal(c_rows, py_rows, backend.backend.nq)
    assert_current_logged(c_rows, backend, periods)


def _faults():
    """(scenario, injection, rule): what a backend can make the loop stop on."""
    def joint_beyond(j, margin):
        def change(x):
            x[j] = 2.9670597283903604 + margin  # the serial joints' limit, 170 deg
        return change

    def too_fast(x):
        x[len(x) // 2 + 1] = -7.0  # arm1.joint2 at 7 rad/s, limit 6 rad/s

    def not_finite(x):
        x[2] = math.nan

    return {
        "position-limit": ("serial_joint", {"at": 37, "change": joint_beyond(4, 1e-3)}),
        "velocity-limit": ("serial_joint", {"at": 12, "change": too_fast}),
        "non-finite": ("serial_task", {"at": 25, "change": not_finite}),
        "watchdog": ("parallel_joint", {"fail_from": 30}),
    }


@pytest.mark.parametrize("measured", [False, True], ids=["no-current", "measured-current"])
@pytest.mark.parametrize("expected", list(_faults()))
def test_every_rule_stops_both_loops_alike(lib, expected, measured):
    """Also with drives that measure current: the stop's row keeps the last good read's
    current (a state stop NaNs what follows the state up to it, a failed read repeats it)."""
    name, injection = _faults()[expected]
    rule, stop, c_rows, backend = c_run(lib, name, 200, measured=measured, **injection)
    py_stop, py_rows, py_backend = python_run(name, 200, measured=measured, **injection)
    assert py_stop.rule == expected
    assert lib.shim_rule_name(rule).decode() == expected
    assert lib.shim_exit_code(rule) == STOP_CODES[expected] == py_stop.code
    assert stop[0] == pytest.approx(py_stop.time)
    assert_rows_equal(c_rows, py_rows, backend.backend.nq)
    if measured:
        fail_from = injection.get("fail_from", -1)
        assert_current_logged(c_rows, backend, fail_from if fail_from >= 0 else len(c_rows))
    assert backend.shutdowns == py_backend.shutdowns == 1
    if expected == "position-limit":
        assert stop[1] == 4 and stop[4] == pytest.approx(2.9680597283903604)
    if expected == "velocity-limit":
        assert stop[1] == 1 and stop[4] == -7.0 and stop[5] == 6.0
    if expected == "watchdog":
        assert stop[6] == 6 and stop[7] == 1  # six failed reads in a row


@pytest.mark.parametrize("name", ["serial_task", "parallel_joint"])
def test_nothing_is_commanded_before_the_first_good_read_in_either_loop(lib, name):
    """The first three reads fail: both loops write zero effort, step no controller and log NaN
    for the state and the errors until the first good read, then run alike (a controller
    computed on the zeros the loops started with once commanded the slider's full force)."""
    failed = 3
    rule, stop, c_rows, backend = c_run(lib, name, 60, fail_first=failed)
    py_stop, py_rows, _ = python_run(name, 60, fail_first=failed)
    assert lib.shim_rule_name(rule).decode() == py_stop.rule == "completed"
    n = backend.backend.nq
    assert_rows_equal(c_rows, py_rows, n)
    state, tau = c_rows[:, 1:1 + 2 * n], c_rows[:, 1 + 2 * n:1 + 3 * n]
    assert np.isnan(state[:failed]).all() and np.isfinite(state[failed:]).all()
    assert not tau[:failed].any() and tau[failed].any()


@pytest.mark.parametrize("name", ["serial_task", "serial_joint"])
def test_keep_out_stops_both_loops_alike(lib, name):
    """Arm 1's tool put on the cochlea centre by a measurement that reaches into the circle:
    a joint-space run stops there as a task-space one does."""
    sc = load_scenario(name)
    setups = unit_setups(sc)
    supervisor = build_supervisor(setups, sc.system.keep_out_radius)
    rng = np.random.default_rng(7)
    inside = None
    n = 6
    for _ in range(20000):  # a joint position inside the limits whose tool is in the circle
        q = np.concatenate([rng.uniform(-2.9, 2.9, 3), setups[1].x0[:3]])
        point, centre = np.split(supervisor.keep_out_points(q)[0], 2)  # arm1's tool
        if math.hypot(point[0] - centre[0], point[1] - centre[1]) < \
                0.5 * supervisor.limits.keep_out_radius:
            inside = q
            break
    assert inside is not None

    def change(x):
        x[:n] = inside
        x[n:] = 0.0

    rule, stop, c_rows, _ = c_run(lib, name, 100, at=40, change=change)
    py_stop, py_rows, _ = python_run(name, 100, at=40, change=change)
    assert py_stop.rule == "keep-out" == lib.shim_rule_name(rule).decode()
    assert stop[0] == pytest.approx(py_stop.time) and stop[2] == 0  # arm1's tool, point 0
    assert_rows_equal(c_rows, py_rows, 6)


def test_a_stop_request_is_the_users_stop(lib):
    sc = load_scenario("serial_joint")
    setups = unit_setups(sc)
    backend = SimBackend(setups, sc.period, sc.plant_substeps)

    def request(x):
        lib.shim_request_stop(2)  # COCHLEA_USER_STOP, as the port's SIGINT handler sets it

    rule, stop, rows, _ = c_run(lib, "serial_joint", 100, at=30, change=request)
    assert lib.shim_rule_name(rule).decode() == "user-stop" and lib.shim_exit_code(rule) == 0
    assert stop[0] == pytest.approx(31 * sc.period) and len(rows) == 31
    del backend
