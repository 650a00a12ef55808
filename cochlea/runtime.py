"""The real-time loop: absolute deadlines, a safety supervisor, and a log written behind it.

Each period reads the state from a backend, runs every unit's fused controller step, passes the
command through the :class:`Supervisor`, writes it, and records the period into preallocated
arrays. Nothing in the period allocates, formats or touches the disk: a writer thread appends
finished rows to ``log.bin`` behind the loop, and the CSV, summary and figures are produced
after the loop has stopped -- whatever stopped it.

On any supervisor rule the loop commands zero effort and disables the drives in the same
period, then finishes the log and reports the rule, its time and values.
"""

from __future__ import annotations

import gc
import json
import math
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .backends import Backend
from .errors import CochleaError
from .simulation import SimulationResult, UnitLog, UnitSetup, plant_step

# Exit codes of a stopped run (README lists them).
EXIT_OK = 0
EXIT_BACKEND = 5
STOP_CODES = {
    "completed": 0,
    "user-stop": 0,  # SIGINT (Ctrl-C): the user's own stop, after the same safe sequence
    "position-limit": 10,
    "velocity-limit": 11,
    "keep-out": 12,
    "non-finite": 13,
    "estimate-bound": 14,
    "watchdog": 15,
    "terminated": 16,  # SIGTERM
}


#: The loop sleeps until this long before each deadline, then spins: the OS wakes a sleeping
#: thread late by up to a few hundred microseconds on a loaded machine.
SPIN_NS = 500_000


class BufferedFunction:
    """A CasADi Function called through preallocated numpy buffers (no allocation per call).

    ``inputs[i]`` and ``outputs[j]`` are flat float64 arrays bound once; fill the inputs in
    place, call, read the outputs in place.
    """

    def __init__(self, f: ca.Function):
        self.function = f
        self.inputs = [np.zeros(f.nnz_in(i)) for i in range(f.n_in())]
        self.outputs = [np.zeros(f.nnz_out(i)) for i in range(f.n_out())]
        self._buffer, self._trigger = f.buffer()
        for i, a in enumerate(self.inputs):
            self._buffer.set_arg(i, memoryview(a))
        for i, a in enumerate(self.outputs):
            self._buffer.set_res(i, memoryview(a))

    def __call__(self) -> None:
        self._trigger()


class _CKernel:
    """A generated C kernel (:mod:`cochlea.ckernels`) behind the same interface: ``inputs`` and
    ``outputs`` lists of the kernel's own buffers, in order, and a call. SX kernels cannot
    fail, so the call's return code is not checked in the period."""

    def __init__(self, kernel):
        self.kernel = kernel
        self.inputs = list(kernel.inputs.values())
        self.outputs = list(kernel.outputs.values())
        self._trigger = kernel.call

    def __call__(self) -> None:
        self._trigger()


KERNEL_SOURCES = ("c", "casadi")


def unit_kernels(u: UnitSetup, substeps: int, source: str = "c"):
    """A unit's ``(step, plant_step, pose)`` kernels and where they come from.

    ``source="c"``: the generated C kernels, checked against the Functions the setup uses (a
    missing or stale library falls back to CasADi with a warning); ``"casadi"``: CasADi
    Functions called through preallocated buffers.
    """
    if source == "c":
        from . import ckernels
        from .csim import unit_kernels as find

        try:
            lib = ckernels.load()
            names = find(lib, u, substeps)
            return (_CKernel(lib.kernel(names.step)), _CKernel(lib.kernel(names.plant)),
                    _CKernel(lib.kernel(names.pose)), "c")
        except CochleaError as exc:
            import warnings

            warnings.warn(f"{exc}; running on the CasADi kernels", stacklevel=2)
    return (BufferedFunction(u.controller.step), BufferedFunction(plant_step(u.plant_model,
                                                                               substeps)),
            BufferedFunction(u.fk_world), "casadi")


# --------------------------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------------------------


class SimBackend:
    """The plant model advanced one control period per write: the default backend.

    Real time comes from the loop's deadlines; the plant itself integrates each period with the
    scenario's RK4 sub-steps, the same kernel as the as-fast-as-possible simulation.
    """

    name = "sim"

    def __init__(self, setups: list[UnitSetup], period: float, substeps: int,
                 kernels: str = "c"):
        self.units = setups
        self.nq = sum(u.plant_model.nq for u in setups)
        self._steps = []
        self._spans = []  # per unit: its joints' slice of q and of qd in the system state
        start = 0
        for u in setups:
            f = unit_kernels(u, substeps, kernels)[1]
            f.inputs[2][...] = u.plant_params
            f.inputs[3][...] = u.friction
            f.inputs[4][...] = period
            f.inputs[0][...] = u.x0
            self._steps.append(f)
            n = u.plant_model.nq
            self._spans.append((n, slice(start, start + n),
                                slice(self.nq + start, self.nq + start + n)))
            start += n
        self.enabled = False
        self.last_io_time_s = 0.0
        self._read_time = 0.0

    def enable(self) -> None:
        self.enabled = True

    def read(self, x: np.ndarray) -> bool:
        t0 = time.perf_counter()
        for f, (n, q_span, qd_span) in zip(self._steps, self._spans):
            state = f.inputs[0]
            x[q_span] = state[:n]
            x[qd_span] = state[n:]
        self._read_time = time.perf_counter() - t0
        return True

    def write(self, tau: np.ndarray) -> bool:
        t0 = time.perf_counter()
        for f, (_, q_span, _) in zip(self._steps, self._spans):
            f.inputs[1][:] = tau[q_span] if self.enabled else 0.0
            f()
            f.inputs[0][:] = f.outputs[0]
        self.last_io_time_s = self._read_time + time.perf_counter() - t0
        return True

    def disable(self) -> None:
        self.enabled = False


# --------------------------------------------------------------------------------------------
# Supervisor
# --------------------------------------------------------------------------------------------


@dataclass
class Stop:
    rule: str
    time: float
    detail: str

    @property
    def code(self) -> int:
        return STOP_CODES[self.rule]


@dataclass
class Limits:
    """Everything the supervisor enforces, per joint of the whole system (SI)."""

    position_lo: np.ndarray
    position_hi: np.ndarray
    velocity: np.ndarray
    effort: np.ndarray
    joint_names: tuple[str, ...]
    joint_units: tuple[str, ...]
    keep_out_radius: float | None = None  # m, task-space runs only
    watchdog_misses: int = 20  # consecutive deadline misses
    watchdog_errors: int = 5  # consecutive backend failures


class Supervisor:
    """The safety rules of a run. Checks allocate nothing but their result on a violation."""

    def __init__(self, limits: Limits, setups: list[UnitSetup], keep_out_points):
        self.limits = limits
        self.setups = setups
        self.n = len(limits.position_lo)
        self._below = np.zeros(self.n, bool)  # scratch: the checks allocate nothing
        self._above = np.zeros(self.n, bool)
        self._speed = np.zeros(self.n)
        # keep_out_points: callables (q_all) -> list of (label, point, centre) for the rule
        self.keep_out_points = keep_out_points
        self.bounds = [u.bound for u in setups]

    def check_state(self, t: float, x: np.ndarray, q: np.ndarray, qd: np.ndarray
                    ) -> Stop | None:
        """``q``, ``qd``: views of ``x``, made once by the caller."""
        L = self.limits
        if not _finite(x):
            return Stop("non-finite", t, f"state = {_fmt(x)}")
        np.less(q, L.position_lo, out=self._below)
        np.greater(q, L.position_hi, out=self._above)
        np.logical_or(self._below, self._above, out=self._below)
        if self._below.any():
            j = int(np.argmax(self._below))
            return Stop("position-limit", t, f"{L.joint_names[j]} = {_show(q[j], L.joint_units[j])}"
                        f" outside [{_show(L.position_lo[j], L.joint_units[j])}, "
                        f"{_show(L.position_hi[j], L.joint_units[j])}]")
        np.abs(qd, out=self._speed)
        np.greater(self._speed, L.velocity, out=self._above)
        if self._above.any():
            j = int(np.argmax(self._above))
            unit = "rad/s" if L.joint_units[j] == "rad" else "m/s"
            return Stop("velocity-limit", t, f"{L.joint_names[j]} speed = {qd[j]:.4g} {unit}, "
                        f"limit {L.velocity[j]:.4g} {unit}")
        if L.keep_out_radius is not None:
            for label, point, centre in self.keep_out_points(q):
                r = math.hypot(point[0] - centre[0], point[1] - centre[1])
                if r < L.keep_out_radius:
                    return Stop("keep-out", t, f"{label} at ({point[0]:.4f}, {point[1]:.4f}) m "
                                f"is {r * 1000:.1f} mm from the centre "
                                f"({centre[0]:.4f}, {centre[1]:.4f}) m, inside the keep-out "
                                f"radius {L.keep_out_radius * 1000:.1f} mm")
        return None

    def check_command(self, t: float, tau: np.ndarray, estimates: list[np.ndarray]
                      ) -> Stop | None:
        if not _finite(tau):
            return Stop("non-finite", t, f"command = {_fmt(tau)}")
        for u, p, bound in zip(self.setups, estimates, self.bounds):
            square = float(p @ p)
            if not math.isfinite(square):
                return Stop("non-finite", t, f"{u.name} estimate = {_fmt(p)}")
            if square > (bound * (1 + 1e-9)) ** 2:
                norm = math.sqrt(square)
                return Stop("estimate-bound", t, f"{u.name} |p_hat| = {norm:.4g}, bound "
                            f"{bound:.4g}")
        return None

    def saturate(self, tau: np.ndarray) -> None:
        np.clip(tau, -self.limits.effort, self.limits.effort, out=tau)


def _finite(v: np.ndarray) -> bool:
    """All finite, without a temporary array (a NaN or infinity makes the sum of squares so)."""
    return math.isfinite(float(v @ v))


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v).ravel()) + "]"


def _show(value: float, unit: str) -> str:
    return f"{math.degrees(value):.2f} deg" if unit == "rad" else f"{value:.4f} m"


# --------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------


@dataclass
class LoopTiming:
    """Per-period timing, s: start lateness, wall time since the previous start, compute."""

    start: np.ndarray
    period: np.ndarray
    compute: np.ndarray
    backend: np.ndarray

    def summary(self, nominal_period: float, rows: int) -> dict:
        wall = self.period[1:rows]
        compute = self.compute[:rows]
        backend = self.backend[:rows]
        # A deadline is missed when a period's work ends after the next period should start.
        finish = self.start[:rows] + compute
        misses = int(np.sum(finish > np.arange(1, rows + 1) * nominal_period))
        pct = lambda a, p: float(np.percentile(a, p)) if a.size else float("nan")  # noqa: E731
        return {
            "unit": "s",
            "nominal_period": nominal_period,
            "period_mean": float(wall.mean()) if wall.size else float("nan"),
            "period_std": float(wall.std()) if wall.size else float("nan"),
            "period_p50": pct(wall, 50), "period_p99": pct(wall, 99),
            "period_max": float(wall.max()) if wall.size else float("nan"),
            "deadline_misses": misses,
            "deadline_miss_fraction": misses / max(rows, 1),
            "compute_p50": pct(compute, 50), "compute_p99": pct(compute, 99),
            "backend_mean": float(backend.mean()) if rows else float("nan"),
            "backend_p99": pct(backend, 99),
        }


#: Priority of the loop under SCHED_FIFO: above every normal process, below the kernel's own
#: real-time threads (Linux runs those at 50 and up).
FIFO_PRIORITY = 40


def _realtime_priority() -> str:
    """Run the calling thread under SCHED_FIFO if allowed (root or CAP_SYS_NICE), so other
    processes cannot delay a period; the loop sleeps most of each period, and the kernel's
    real-time throttling keeps 5 % of the CPU for everything else. Returns what was obtained."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        return f"SCHED_FIFO {FIFO_PRIORITY}"
    except (AttributeError, PermissionError, OSError):
        return "normal (SCHED_FIFO not permitted)"


def _normal_priority() -> None:
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, PermissionError, OSError):
        pass


class _LogWriter(threading.Thread):
    """Appends finished rows of the period buffer to ``log.bin`` behind the loop."""

    def __init__(self, buffer: np.ndarray, path: Path, interval: float = 0.2):
        super().__init__(name="cochlea-log-writer", daemon=True)
        self.buffer, self.path, self.interval = buffer, path, interval
        self.done_rows = 0  # rows the loop has finished (written by the loop only)
        self.written = 0
        self.finished = threading.Event()

    def run(self) -> None:
        with open(self.path, "wb") as f:
            while not self.finished.wait(self.interval):
                self._flush(f)
            self._flush(f)

    def _flush(self, f) -> None:
        end = self.done_rows
        if end > self.written:
            self.buffer[self.written:end].tofile(f)
            f.flush()
            self.written = end

    def close(self) -> None:
        self.finished.set()
        self.join()


class _Status(threading.Thread):
    """A one-line live status, refreshed a few times a second from the loop's counters."""

    def __init__(self, loop: "RealTimeLoop", interval: float = 0.25, stream=sys.stderr):
        super().__init__(name="cochlea-status", daemon=True)
        self.loop, self.interval, self.stream = loop, interval, stream
        self.finished = threading.Event()

    def run(self) -> None:
        while not self.finished.wait(self.interval):
            self.stream.write("\r" + self.loop.status_line() + " " * 4)
            self.stream.flush()
        self.stream.write("\r" + self.loop.status_line() + "\n")
        self.stream.flush()

    def close(self) -> None:
        self.finished.set()
        self.join()


class RealTimeLoop:
    """Runs a scenario's units against a backend at the control rate.

    ``realtime=False`` runs the same periods back to back (no sleeping): the loop's logic with
    the timing taken out, which the tests use to inject faults quickly.
    """

    def __init__(self, setups: list[UnitSetup], backend: Backend, supervisor: Supervisor,
                 period: float, steps: int, realtime: bool = True, kernels: str = "c",
                 substeps: int = 1):
        self.setups, self.backend, self.supervisor = setups, backend, supervisor
        self.h, self.steps, self.realtime = period, steps, realtime
        self.time = np.arange(steps) * period
        self.n = sum(u.controller_model.nq for u in setups)
        self.stop: Stop | None = None
        self.rows = 0
        self._signal: str | None = None
        self.scheduling = "normal"

        # Per unit: the fused step through buffers, its slice of the joint vector, the desired
        # samples of the whole run (exact, precomputed), and the column layout of the log.
        self.kernels, self.slices, self.desired = [], [], []
        self.kernel_source = "c"
        start = 0
        for u in setups:
            k, _, _, source = unit_kernels(u, substeps, kernels)
            if source != "c":
                self.kernel_source = source
            k.inputs[5][...] = u.p_hat0
            k.inputs[6][...] = u.gains
            k.inputs[7][...] = u.gamma
            k.inputs[8][...] = u.bound
            k.inputs[9][...] = period
            self.kernels.append(k)
            n = u.controller_model.nq
            self.slices.append(slice(start, start + n))
            start += n
            xd, xd_dot, xd_ddot = u.desired.map(steps)(self.time)
            self.desired.append((np.array(xd).T.copy(), np.array(xd_dot).T.copy(),
                                 np.array(xd_ddot).T.copy()))

        # One row per period: t, x (all), tau (all), then per unit errors and p_hat, then timing.
        widths = [1, 2 * self.n, self.n]
        for u in setups:
            widths += [u.controller.n_desired + u.controller_model.nq, u.controller.n_params]
        widths += [4]
        self.offsets = np.concatenate([[0], np.cumsum(widths)])
        self.buffer = np.full((steps, int(self.offsets[-1])), np.nan)
        self.x = np.zeros(2 * self.n)
        self.tau = np.zeros(self.n)
        self.zero = np.zeros(self.n)

    # ---- the loop ----------------------------------------------------------------------------

    def _on_signal(self, signum, frame) -> None:  # noqa: ARG002
        self._signal = "user-stop" if signum == signal.SIGINT else "terminated"

    def status_line(self) -> str:
        k = self.rows
        if k == 0:
            return "waiting for the first period"
        t = self.time[min(k, self.steps) - 1]
        err = self.buffer[k - 1, self.offsets[3]:self.offsets[3] + 3]
        timing = self.buffer[:k, self.offsets[-2]:self.offsets[-1]]
        p99 = float(np.percentile(timing[-2000:, 1], 99)) if k > 2 else float("nan")
        return (f"t = {t:6.2f} s  |e| = {np.abs(err).max():.2e}  period p99 = "
                f"{p99 * 1e3:.3f} ms  misses = {self.misses}")

    def run(self, log_path: Path | None = None, status: bool = False) -> Stop:
        previous = {s: signal.signal(s, self._on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        writer = _LogWriter(self.buffer, log_path) if log_path else None
        status_thread = _Status(self) if status else None
        self.misses = 0
        try:
            self.backend.enable()
            if writer:
                writer.start()
            if status_thread:
                status_thread.start()
            self.scheduling = _realtime_priority() if self.realtime else "normal"
            gc.disable()  # no collector pauses inside the loop
            # Hand the GIL back to the loop within 0.1 ms when it wakes (default: 5 ms), so the
            # writer and status threads cannot delay a period.
            switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(1e-4)
            try:
                self.stop = self._loop(writer)
            finally:
                sys.setswitchinterval(switch_interval)
        finally:
            gc.enable()
            # The safe sequence, whatever happened: zero effort, drives off.
            try:
                self.backend.write(self.zero)
            finally:
                self.backend.disable()
            # Only threads that started can be joined: enable() may have failed before them.
            if writer and writer.is_alive():
                writer.close()
            if status_thread and status_thread.is_alive():
                status_thread.close()
            for s, handler in previous.items():
                signal.signal(s, handler)
            _normal_priority()
        return self.stop

    def _views(self):
        """Views made once, so the period only copies into existing arrays."""
        n, x, tau, off = self.n, self.x, self.tau, self.offsets
        row = np.zeros(self.buffer.shape[1])  # the period's row, copied into the log at its end
        units = []
        for i, (kern, sl, desired) in enumerate(zip(self.kernels, self.slices, self.desired)):
            ne = len(kern.outputs[2])
            units.append((kern, kern.inputs, x[sl], x[n + sl.start:n + sl.stop], tau[sl],
                          desired, row[int(off[3 + 2 * i]):int(off[3 + 2 * i]) + ne],
                          row[int(off[4 + 2 * i]):int(off[5 + 2 * i])]))
        timing = row[int(off[-2]):int(off[-1])]
        return row, row[1:1 + 2 * n], row[1 + 2 * n:1 + 3 * n], timing, units

    def _loop(self, writer) -> Stop:
        h_ns = int(round(self.h * 1e9))
        misses = errors = 0
        sup, backend, x, tau, buf = (self.supervisor, self.backend, self.x, self.tau,
                                     self.buffer)
        n = self.n
        q_view, qd_view = x[:n], x[n:]
        row, row_x, row_tau, row_timing, units = self._views()
        estimates = [kern.outputs[1] for kern in self.kernels]
        clock = time.perf_counter_ns
        t0 = clock()
        previous_start = t0
        for k in range(self.steps):
            t = self.time[k]
            if self.realtime:
                deadline = t0 + k * h_ns
                while True:  # sleep until SPIN before the deadline, then spin
                    remaining = deadline - clock()
                    if remaining <= 0:
                        break
                    if remaining > SPIN_NS:
                        time.sleep((remaining - SPIN_NS) * 1e-9)
            start = clock()
            if self._signal:
                return Stop(self._signal, t, "signal received")
            ok = backend.read(x)
            errors = 0 if ok else errors + 1
            if errors > sup.limits.watchdog_errors:
                return Stop("watchdog", t, f"{errors} consecutive backend read failures")
            row[0] = t
            row_x[:] = x
            stop = sup.check_state(t, x, q_view, qd_view) if ok else None
            if stop:  # nothing was commanded in this period
                row[1 + 2 * n:] = np.nan
                buf[k] = row
                self.rows = k + 1
                return stop
            for kern, kin, q_u, qd_u, tau_u, (xd, xd_dot, xd_ddot), row_err, row_p in units:
                kin[0][:] = q_u
                kin[1][:] = qd_u
                kin[2][:] = xd[k]
                kin[3][:] = xd_dot[k]
                kin[4][:] = xd_ddot[k]
                kern()
                tau_u[:] = kern.outputs[0]
                row_err[:] = kern.outputs[2]
                row_p[:] = kin[5]  # the estimate used in this period
                kin[5][:] = kern.outputs[1]  # next period's estimate
            stop = sup.check_command(t, tau, estimates)
            if stop:  # the refused command is logged as computed; it was never written
                row_tau[:] = tau
                row_timing[:] = np.nan
                buf[k] = row
                self.rows = k + 1
                return stop
            sup.saturate(tau)
            if not backend.write(tau):
                errors += 1
            row_tau[:] = tau
            end = clock()
            row_timing[0] = (start - t0) * 1e-9 - t
            row_timing[1] = (start - previous_start) * 1e-9
            row_timing[2] = (end - start) * 1e-9
            row_timing[3] = backend.last_io_time_s
            buf[k] = row
            previous_start = start
            if self.realtime and end - t0 > (k + 1) * h_ns:
                misses += 1
                self.misses += 1
                if misses > sup.limits.watchdog_misses:
                    self.rows = k + 1
                    return Stop("watchdog", t, f"{misses} consecutive deadline misses "
                                f"(last period took {(end - start) * 1e-6:.3f} ms of compute)")
            else:
                misses = 0
            self.rows = k + 1
            if writer:
                writer.done_rows = k + 1
        return Stop("completed", self.time[-1] + self.h if self.steps else 0.0, "")

    # ---- results -------------------------------------------------------------------------

    def result(self, scenario) -> SimulationResult:
        """The log as a :class:`SimulationResult`, so the report writes it like any run."""
        rows = self.rows
        buf, off, n = self.buffer[:rows], self.offsets, self.n
        logs = []
        for i, (u, sl, (xd, xd_dot, _)) in enumerate(zip(self.setups, self.slices,
                                                         self.desired)):
            q = buf[:, 1 + sl.start:1 + sl.stop]
            qd = buf[:, 1 + n + sl.start:1 + n + sl.stop]
            errors = buf[:, int(off[3 + 2 * i]):int(off[4 + 2 * i])]
            p_hat = buf[:, int(off[4 + 2 * i]):int(off[5 + 2 * i])]
            tau = buf[:, 1 + 2 * n + sl.start:1 + 2 * n + sl.stop]
            pose = np.array(u.fk_world.map(rows)(np.nan_to_num(q).T)).T if rows else \
                np.zeros((0, len(u.task_names)))
            logs.append(UnitLog(u.name, scenario.space, q, qd, xd[:rows], xd_dot[:rows], errors,
                                tau, p_hat, pose, u))
        result = SimulationResult(scenario, self.time[:rows], logs)
        timing = buf[:, int(off[-2]):int(off[-1])]
        result.timing = {"start_lateness_s": timing[:, 0], "wall_period_s": timing[:, 1],
                         "compute_s": timing[:, 2], "backend_io_s": timing[:, 3]}
        return result

    def timing_summary(self) -> dict:
        off = self.offsets
        t = self.buffer[:self.rows, int(off[-2]):int(off[-1])]
        timing = LoopTiming(start=self.time[:self.rows] + t[:, 0], period=t[:, 1],
                            compute=t[:, 2], backend=t[:, 3])
        return {**timing.summary(self.h, self.rows), "scheduling": self.scheduling}


def raw_columns(loop: RealTimeLoop) -> list[str]:
    """Names (with units) of the columns of ``log.bin``, the raw period buffer."""
    joints, units = [], []
    for u in loop.setups:
        joints += [f"{u.name}.{j.name}" for j in u.controller_model.joints]
        units += list(u.joint_units)
    rate = {"rad": "rad_s", "m": "m_s"}
    effort = {"rad": "Nm", "m": "N"}
    names = ["time_s"] + [f"q.{j}_{un}" for j, un in zip(joints, units)]
    names += [f"qd.{j}_{rate[un]}" for j, un in zip(joints, units)]
    names += [f"tau.{j}_{effort[un]}" for j, un in zip(joints, units)]
    for u in loop.setups:
        first, second = u.controller.error_names
        names += [f"{u.name}.{first}[{i}]_SI" for i in range(u.controller.n_desired)]
        names += [f"{u.name}.{second}[{i}]_SI" for i in range(u.controller_model.nq)]
        names += [f"{u.name}.p_hat.{p}_SI" for p in u.controller_model.param_names]
    return names + ["start_lateness_s", "wall_period_s", "compute_s", "backend_io_s"]


def write_raw_columns(path: Path, loop: RealTimeLoop) -> None:
    """``log.columns.json``: how to read ``log.bin`` (float64 rows) if the run was killed."""
    path.write_text(json.dumps({"dtype": "float64", "row_length": int(loop.offsets[-1]),
                                "columns": raw_columns(loop)}, indent=1) + "\n")


def build_supervisor(setups: list[UnitSetup], space: str, keep_out_radius: float | None,
                     watchdog_misses: int = 20, watchdog_errors: int = 5,
                     kernels: str = "c", substeps: int = 1) -> Supervisor:
    """Limits from the descriptions of every unit's joints; the keep-out circle for task-space
    runs around each unit's centre (serial: the cochlea centre; parallel: the slider pivot S,
    which moves with d1) for each of its tool points."""
    joints = [j for u in setups for j in u.controller_model.joints]
    limits = Limits(
        position_lo=np.array([j.position_limits[0] for j in joints]),
        position_hi=np.array([j.position_limits[1] for j in joints]),
        velocity=np.array([j.velocity_limit for j in joints]),
        effort=np.array([j.effort_limit for j in joints]),
        joint_names=tuple(f"{u.name}.{j.name}" for u in setups for j in u.controller_model.joints),
        joint_units=tuple(un for u in setups for un in u.joint_units),
        keep_out_radius=keep_out_radius if space == "task" else None,
        watchdog_misses=watchdog_misses, watchdog_errors=watchdog_errors)
    fks, slices, start = [], [], 0
    for u in setups:
        fks.append(unit_kernels(u, substeps, kernels)[2])
        slices.append(slice(start, start + u.controller_model.nq))
        start += u.controller_model.nq

    def keep_out_points(q):
        points = []
        for u, fk, sl in zip(setups, fks, slices):
            fk.inputs[0][...] = q[sl]
            fk()
            pose = fk.outputs[0]
            centre = u.keep_out_centre(q[sl])
            for label, (iu, iv) in u.tool_points:
                points.append((f"{u.name} {label}", (pose[iu], pose[iv]), centre))
        return points

    return Supervisor(limits, setups, keep_out_points)
