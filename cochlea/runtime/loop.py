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
import os
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..sim.compiled import period_kernels
from ..sim.result import SimulationResult, UnitLog
from ..sim.setup import UnitSetup
from .backend import Backend
from .log_writer import LogWriter
from .supervisor import Stop, Supervisor

#: The loop sleeps until this long before each deadline, then spins: the OS wakes a sleeping
#: thread late by up to a few hundred microseconds on a loaded machine.
SPIN_NS = 500_000


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


class _Status(threading.Thread):
    """A one-line live status, refreshed a few times a second from the loop's counters."""

    def __init__(self, loop: RealTimeLoop, interval: float = 0.25, stream=sys.stderr):
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
            k, _, _, source = period_kernels(u, substeps, kernels)
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
        writer = LogWriter(self.buffer, log_path) if log_path else None
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
                # A hardware backend knows why (a motor's alert, a timeout): the stop says so.
                cause = getattr(backend, "failure_detail", None)
                return Stop("watchdog", t, f"{errors} consecutive backend read failures"
                            + (f": {cause()}" if cause else ""))
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
        return {**timing.summary(self.h, self.rows), "scheduling": self.scheduling,
                "watchdog_misses_allowed": self.supervisor.limits.watchdog_misses}


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
