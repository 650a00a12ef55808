"""The real-time loop: absolute deadlines, a safety supervisor, and a log written behind it.

Each period reads the state from a backend, runs every unit's fused controller step, passes the
command through the :class:`Supervisor`, writes it, and records the period into preallocated
arrays. Nothing in the period allocates, formats or touches the disk: a writer thread appends
finished rows to ``log.bin`` behind the loop, and the CSV, summary and figures are produced
after the loop has stopped -- whatever stopped it.

Memory does not grow with the run's length: with a log file the periods go through a ring of
:data:`RING_SECONDS` that the writer empties, the desired samples are evaluated
:data:`DESIRED_CHUNK` periods at a time in the slack after a period's work, and the timing
statistics and the report read ``log.bin`` back in chunks. If the writer fails (a full disk)
or falls a whole ring behind, the loop stops safely with its own rule, ``log-failure``.

On any supervisor rule the loop commands zero effort and disables the drives in the same
period, then finishes the log and reports the rule, its time and values.
"""

from __future__ import annotations

import ctypes
import errno
import gc
import json
import math
import os
import resource
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import log_schema
from ..errors import CochleaError
from ..kernels.bind import BufferedFunction
from ..sim.compiled import period_kernels
from ..sim.result import SimulationResult, StreamedResult, UnitLog
from ..sim.setup import MIRROR_RULE, UnitSetup
from . import log_writer as _log_writer
from .backend import Backend
from .log_writer import LogWriter
from .supervisor import OVERRUN_POLICY, SIGNAL_STOPS, OverrunWatch, Stop, Supervisor

#: The loop sleeps until this long before each deadline, then spins: the OS wakes a sleeping
#: thread late by up to a few hundred microseconds on a loaded machine.
SPIN_NS = 500_000

#: With a log file, the periods the loop keeps in memory (s): the writer empties the ring every
#: 0.2 s, so a ring of seconds absorbs a slow disk; a writer a whole ring behind is a failure.
RING_SECONDS = 4.0
#: Desired samples evaluated at once, in the slack after a period's work: a CasADi call costs
#: about 100 us plus 1-2 us a sample, so 100 samples fit in a 1 kHz period's slack.
DESIRED_CHUNK = 100
#: Rows read back from ``log.bin`` at a time (a few MB), for the timing and the report.
READ_CHUNK = 1 << 13
#: The timing columns of each row (s), after the controllers' blocks.
TIMING_COLUMNS = log_schema.TIMING_COLUMNS


# --------------------------------------------------------------------------------------------
# The run's rows, read back in chunks
# --------------------------------------------------------------------------------------------


class RowSource:
    """The rows of a run, read a chunk at a time: from the in-memory buffer of a run without a
    log file, or from ``log.bin`` (the rows the writer wrote; the ring holds only the last few
    seconds). Nothing reads the whole run at once."""

    def __init__(self, width: int, rows: int, buffer: np.ndarray | None = None,
                 path: Path | None = None):
        self.width, self.buffer, self.path = width, buffer, path
        if path is not None:  # a failed writer may have left fewer rows, or a partial one
            on_disk = path.stat().st_size // (8 * width) if path.exists() else 0
            rows = min(rows, on_disk)
        self.rows = rows

    def read(self, start: int, stop: int, step: int = 1) -> np.ndarray:
        stop = min(stop, self.rows)
        if stop <= start:
            return np.zeros((0, self.width))
        if self.buffer is not None:
            return self.buffer[start:stop:step]
        if step == 1:
            return self._file_rows(start, stop)
        # Decimated: read a chunk at a time, keep a copy of every step-th row (a view would
        # keep the whole chunk alive, and with it the whole run).
        size = max(READ_CHUNK // step, 1) * step
        return np.concatenate([self._file_rows(a, min(a + size, stop))[::step].copy()
                               for a in range(start, stop, size)])

    def _file_rows(self, start: int, stop: int) -> np.ndarray:
        return np.fromfile(self.path, dtype=np.float64, count=(stop - start) * self.width,
                           offset=start * self.width * 8).reshape(-1, self.width)

    def chunks(self, size: int | None = None):
        """``(first row, rows)`` pairs covering the run in order."""
        size = size or READ_CHUNK
        for start in range(0, self.rows, size):
            yield start, self.read(start, start + size)


#: Bins of each narrowing pass of :func:`chunked_percentiles`, and the count of values in the
#: final bin below which they are gathered and selected exactly.
_BINS = 4096
_EXACT = 1 << 16


def _order_statistic(columns, k: int, lo: float, hi: float) -> float:
    """The ``k``-th smallest value (0-based) of the column that ``columns()`` yields in chunks,
    all finite in ``[lo, hi]``: a histogram narrows the range to the bin holding it until that
    bin is small enough to select in memory."""
    hi_open = False  # after the first pass the range is a half-open bin [lo, hi)
    while True:
        if lo == hi or (hi_open and np.nextafter(lo, np.inf) >= hi):
            return float(lo)  # a single representable value left
        edges = np.linspace(lo, hi, _BINS + 1)
        counts = np.zeros(_BINS, np.int64)
        below = 0
        for c in columns():
            below += int(np.count_nonzero(c < lo))
            inside = c[(c >= lo) & ((c < hi) if hi_open else (c <= hi))]
            index = np.clip(np.searchsorted(edges, inside, side="right") - 1, 0, _BINS - 1)
            counts += np.bincount(index, minlength=_BINS)
        cumulative = below + np.cumsum(counts)
        b = int(np.searchsorted(cumulative, k, side="right"))
        lo_b, hi_b = float(edges[b]), float(edges[b + 1])
        last = b == _BINS - 1 and not hi_open  # the top bin of a closed range is closed
        if counts[b] <= _EXACT:
            values = np.concatenate([c[(c >= lo_b) & ((c <= hi_b) if last else (c < hi_b))]
                                     for c in columns()] or [np.zeros(0)])
            rank = k - int(cumulative[b] - counts[b])
            return float(np.partition(values, rank)[rank])
        lo, hi, hi_open = lo_b, hi_b, not last


def chunked_percentiles(columns, percents) -> list[float]:
    """numpy's default (linear) percentiles of a column read in chunks by ``columns()`` (a
    callable returning an iterator of 1-D arrays), in memory bounded by the chunk rather than
    the column; NaN when the column is empty or holds a NaN, as ``np.percentile``."""
    n, lo, hi, nan = 0, np.inf, -np.inf, False
    for c in columns():
        if c.size:
            n += c.size
            nan = nan or bool(np.isnan(c).any())
            lo, hi = min(lo, float(np.min(c))), max(hi, float(np.max(c)))
    if n == 0 or nan or not (np.isfinite(lo) and np.isfinite(hi)):
        return [float("nan")] * len(percents)
    out = []
    for p in percents:
        q = p / 100
        virtual = n * q + (1 + q * (1 - 1 - 1)) - 1  # numpy's "linear" method, term for term
        i = int(np.floor(virtual))
        gamma = virtual - i
        a = _order_statistic(columns, min(i, n - 1), lo, hi)
        b = a if gamma == 0 or i + 1 > n - 1 else _order_statistic(columns, i + 1, lo, hi)
        diff = b - a
        out.append(float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma))
    return out


class _Moments:
    """Count, mean and spread of a column seen in chunks (Chan et al.'s merge)."""

    def __init__(self):
        self.n, self.mean, self.m2, self.max = 0, 0.0, 0.0, -np.inf

    def add(self, values: np.ndarray) -> None:
        if not values.size:
            return
        n, mean = values.size, float(np.mean(values))
        m2 = float(np.sum((values - mean) ** 2))
        if not self.n:  # the first chunk as numpy computes it
            self.n, self.mean, self.m2 = n, mean, m2
            self.max = float(np.max(values))
            return
        total = self.n + n
        delta = mean - self.mean
        self.mean += delta * n / total
        self.m2 += m2 + delta * delta * self.n * n / total
        self.n = total
        self.max = float(np.maximum(self.max, np.max(values)))  # NaN propagates, as np.max

    @property
    def std(self) -> float:
        return math.sqrt(self.m2 / self.n) if self.n else float("nan")


def timing_of(source: RowSource, first: int, nominal_period: float) -> dict:
    """The timing summary of a run from its rows (column ``first`` on: start lateness, wall
    period, compute, backend I/O; s), read in chunks."""
    rows = source.rows
    wall, compute, backend = _Moments(), _Moments(), _Moments()
    misses = 0
    for start, block in source.chunks():
        timing = block[:, first:first + 4]
        wall.add(timing[1:, 1] if start == 0 else timing[:, 1])
        compute.add(timing[:, 2])
        backend.add(timing[:, 3])
        # A deadline is missed when a period's work ends after the next period should start.
        finish = block[:, 0] + timing[:, 0] + timing[:, 2]
        due = np.arange(start + 1, start + len(block) + 1) * nominal_period
        misses += int(np.sum(finish > due))

    def column(index, skip_first=False):
        def chunks():
            for start, block in source.chunks():
                yield block[1 if skip_first and start == 0 else 0:, first + index]
        return chunks

    period_p50, period_p99 = chunked_percentiles(column(1, True), (50, 99))
    compute_p50, compute_p99 = chunked_percentiles(column(2), (50, 99))
    backend_p99, = chunked_percentiles(column(3), (99,))
    nan = float("nan")
    return {
        "unit": "s",
        "nominal_period": nominal_period,
        "period_mean": wall.mean if wall.n else nan,
        "period_std": wall.std,
        "period_p50": period_p50, "period_p99": period_p99,
        "period_max": wall.max if wall.n else nan,
        "deadline_misses": misses,
        "deadline_miss_fraction": misses / max(rows, 1),
        "compute_p50": compute_p50, "compute_p99": compute_p99,
        "backend_mean": backend.mean if rows else nan,
        "backend_p99": backend_p99,
    }


#: Priority of the loop under SCHED_FIFO: above every normal process, below the kernel's own
#: real-time threads (Linux runs those at 50 and up).
FIFO_PRIORITY = 40

#: The scheduling policies ``--sched`` offers, by name.
POLICIES = {"fifo": "SCHED_FIFO", "rr": "SCHED_RR", "other": "SCHED_OTHER"}
_MCL_CURRENT, _MCL_FUTURE = 1, 2  # <sys/mman.h> on Linux


@dataclass(frozen=True)
class RealtimeOptions:
    """How the loop's thread runs (``cochlea-run --mlockall --cpu --sched --priority``).

    The defaults are what the loop always did: SCHED_FIFO 40 when permitted, the CPUs the
    process was given, memory not locked. ``mlockall`` locks the process's pages for the loop
    (no page fault can stall a period; unlocked again when the loop ends, before the report);
    ``cpu`` pins the loop's thread to one core (the log writer and status threads stay free).
    """

    mlockall: bool = False
    cpu: int | None = None
    policy: str = "fifo"
    priority: int | None = None  # fifo and rr: default FIFO_PRIORITY; other: none

    @property
    def level(self) -> int:
        """The priority asked for: SCHED_OTHER's is 0."""
        if self.policy == "other":
            return 0
        return FIFO_PRIORITY if self.priority is None else self.priority

    def as_dict(self) -> dict:
        return {"mlockall": self.mlockall, "cpu": self.cpu, "policy": self.policy,
                "priority": self.level}


def check_realtime_options(options: RealtimeOptions) -> None:
    """The user's mistakes in ``options``, refused before anything moves (the option named)."""
    if options.policy not in POLICIES:
        raise CochleaError(f"--sched: expected one of {', '.join(POLICIES)}, got "
                           f"{options.policy!r}")
    if options.policy == "other":
        if options.priority is not None:
            raise CochleaError("--priority goes with --sched fifo or rr (SCHED_OTHER has no "
                               "real-time priority)")
    else:
        lo, hi = _priority_range(options.policy)
        if not lo <= options.level <= hi:
            raise CochleaError(f"--priority must be between {lo} and {hi} for --sched "
                               f"{options.policy}, got {options.level}")
    if options.cpu is not None:
        allowed = _allowed_cpus()
        if allowed is not None and options.cpu not in allowed:
            raise CochleaError(f"--cpu {options.cpu} is not a CPU this process may use: expected "
                               f"one of {_cpu_list(allowed)}")


def _priority_range(policy: str) -> tuple[int, int]:
    try:
        value = getattr(os, POLICIES[policy])
        return os.sched_get_priority_min(value), os.sched_get_priority_max(value)
    except (AttributeError, OSError):
        return 1, 99  # Linux's range, where the OS cannot say


def _allowed_cpus() -> set[int] | None:
    try:
        return set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def _cpu_list(cpus) -> str:
    return ", ".join(str(c) for c in sorted(cpus))


def _policy_now() -> tuple[str, int]:
    """The calling thread's scheduling policy (by ``POLICIES`` name) and priority."""
    try:
        value = os.sched_getscheduler(0)
        priority = os.sched_getparam(0).sched_priority
    except (AttributeError, OSError):
        return "unknown", 0
    names = {getattr(os, v, None): k for k, v in POLICIES.items()}
    return names.get(value, f"policy {value}"), priority


def _libc():
    return ctypes.CDLL(None, use_errno=True)


class _Applied:
    """What :func:`apply_realtime` changed, to undo it when the loop ends."""

    def __init__(self):
        self.locked = False
        self.affinity: set[int] | None = None
        self.policy: tuple[int, int] | None = None

    def undo(self) -> None:
        if self.locked:
            try:
                _libc().munlockall()
            except (AttributeError, OSError):
                pass
        if self.affinity is not None:
            try:
                os.sched_setaffinity(0, self.affinity)
            except OSError:
                pass
        if self.policy is not None:
            try:
                os.sched_setscheduler(0, self.policy[0], os.sched_param(self.policy[1]))
            except OSError:
                pass


def apply_realtime(options: RealtimeOptions) -> tuple[dict, list[str], _Applied]:
    """Apply ``options`` to the calling thread (and ``mlockall`` to the process): ``(obtained,
    problems, undo)``. A setting the OS refuses (no permission, a locked-memory limit) is a
    problem, not an error: the run goes on with what it got, and ``obtained`` says what."""
    problems = []
    applied = _Applied()
    if options.mlockall:
        try:
            if _libc().mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
                applied.locked = True
            else:
                error = ctypes.get_errno()
                limit = ""
                if error in (errno.ENOMEM, errno.EPERM):
                    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
                    limit = "; RLIMIT_MEMLOCK is " + ("unlimited" if soft == resource.RLIM_INFINITY
                                                      else f"{soft / 2**20:g} MiB")
                problems.append(f"mlockall failed ({os.strerror(error)}{limit}: raise memlock "
                                "in /etc/security/limits.conf or run with CAP_IPC_LOCK)")
        except (AttributeError, OSError) as exc:
            problems.append(f"mlockall not available ({exc})")
    if options.cpu is not None:
        before = _allowed_cpus()
        try:
            os.sched_setaffinity(0, {options.cpu})
            applied.affinity = before
        except (AttributeError, OSError) as exc:
            problems.append(f"CPU affinity {options.cpu} refused ({exc})")
    try:
        previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
        value = getattr(os, POLICIES[options.policy])
        if previous != (value, options.level):
            os.sched_setscheduler(0, value, os.sched_param(options.level))
            applied.policy = previous
    except (AttributeError, PermissionError, OSError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        problems.append(f"{POLICIES[options.policy]} {options.level} not permitted "
                        f"({reason}: run as root, with CAP_SYS_NICE or an rtprio limit)")
    policy, priority = _policy_now()
    cpus = _allowed_cpus()
    obtained = {"mlockall": applied.locked,
                "cpu": sorted(cpus) if cpus is not None else None,
                "policy": policy, "priority": priority}
    return obtained, problems, applied


def _scheduling_text(options: RealtimeOptions, obtained: dict) -> str:
    """The loop's scheduling in words (``timing.scheduling`` of ``summary.json``)."""
    if obtained["policy"] in ("fifo", "rr"):
        return f"{POLICIES[obtained['policy']]} {obtained['priority']}"
    if options.policy != "other":
        return f"normal ({POLICIES[options.policy]} not permitted)"
    return "normal"


class _Status(threading.Thread):
    """A one-line live status, refreshed a few times a second from the loop's counters."""

    def __init__(self, loop: RealTimeLoop, interval: float = 0.25, stream=None):
        super().__init__(name="cochlea-status", daemon=True)
        # sys.stderr as it is now (the program's closed-terminal-tolerant stream), not as it
        # was when this module was imported.
        self.stream = sys.stderr if stream is None else stream
        self.loop, self.interval = loop, interval
        self.finished = threading.Event()

    def run(self) -> None:
        try:
            while not self.finished.wait(self.interval):
                self.stream.write("\r" + self.loop.status_line() + " " * 4)
                self.stream.flush()
            self.stream.write("\r" + self.loop.status_line() + "\n")
            self.stream.flush()
        except OSError:
            # The terminal is gone (a hang-up: EIO): the status has no reader; the loop, its
            # safe stop and its log go on without it.
            self.finished.wait()

    def close(self) -> None:
        self.finished.set()
        self.join()


class RealTimeLoop:
    """Runs a scenario's units against a backend at the control rate.

    ``realtime=False`` runs the same periods back to back (no sleeping): the loop's logic with
    the timing taken out, which the tests use to inject faults quickly.

    Without a log file, :meth:`run` keeps every period in ``buffer`` (short runs, tests); with
    one, ``buffer`` is a ring of :data:`RING_SECONDS` that the writer streams to the file, and
    :meth:`result` and :meth:`timing_summary` read the file back in chunks.
    """

    def __init__(self, setups: list[UnitSetup], backend: Backend, supervisor: Supervisor,
                 period: float, steps: int, realtime: bool = True, kernels: str = "c",
                 substeps: int = 1, options: RealtimeOptions | None = None,
                 warn=None, clock=None, sleep=None):
        self.setups, self.backend, self.supervisor = setups, backend, supervisor
        self.h, self.steps, self.realtime = period, steps, realtime
        self.n = sum(u.controller_model.nq for u in setups)
        self.stop: Stop | None = None
        self.rows = 0
        self.misses = 0  # overruns so far (the status line's count)
        self._signal: tuple[str, str] | None = None  # (rule, detail) of SIGNAL_STOPS
        self.scheduling = "normal"
        #: ``--mlockall``, ``--cpu``, ``--sched``, ``--priority``: applied when the loop starts
        #: (real time only); ``realtime_report`` says what was asked and obtained.
        self.options = options or RealtimeOptions()
        self.realtime_report: dict | None = None
        self._warn = warn or (lambda text: print(f"warning: {text}", file=sys.stderr,
                                                 flush=True))
        # The loop's clock and sleep (ns, s); tests give a synthetic pair to place a stall
        # exactly, whatever the machine's own timing.
        self._clock = clock or time.perf_counter_ns
        self._sleep = sleep or time.sleep
        self.watch = OverrunWatch(int(round(period * 1e9)), supervisor.limits.watchdog_misses)
        self.log_path: Path | None = None

        # Per unit: the fused step through buffers, its slice of the joint vector, the desired
        # samples of the current chunk of periods, and the column layout of the log.
        self.kernels, self.slices, self.desired = [], [], []
        self._desired_maps = []
        # mirror = "measured": per follower (unit index), its rule's step through buffers, the
        # chunk of its time-only inputs and their map (cochlea.sim.setup.Follow).
        self._follows: list[tuple] = []
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
            for i, value in enumerate(u.robust_inputs, start=10):  # ROBUST_INPUTS
                k.inputs[i][...] = value
            self.kernels.append(k)
            n = u.controller_model.nq
            self.slices.append(slice(start, start + n))
            start += n
            nd = u.controller.n_desired
            self.desired.append(tuple(np.zeros((DESIRED_CHUNK, nd)) for _ in range(3)))
            if u.follow is None:
                self._desired_maps.append(u.desired.map(DESIRED_CHUNK))
            else:  # its desired rows are the rule's, each period: the time-only part ahead
                self._desired_maps.append(None)
                w = np.zeros((DESIRED_CHUNK, u.follow.timed.size1_out(0)))
                self._follows.append((len(self.kernels) - 1, u.follow,
                                      BufferedFunction(u.follow.step), w,
                                      u.follow.timed.map(DESIRED_CHUNK)))
        self._chunk_times = np.arange(DESIRED_CHUNK, dtype=float)
        self._fill_desired(0)

        # One row per period: t, x (all), tau (all), then per unit errors and p_hat, then timing
        # (``offsets`` marks these blocks), then the measured current of every joint (A,
        # only when the backend measures it), appended last so every earlier column keeps its
        # place in logs read by position.
        widths = [1, 2 * self.n, self.n]
        for u in setups:
            widths += [u.controller.n_desired + u.controller_model.nq, u.controller.n_params]
        widths += [len(TIMING_COLUMNS)]
        self.offsets = np.concatenate([[0], np.cumsum(widths)])
        self.current_at = int(self.offsets[-1])
        #: The backend's measured joint currents, copied into each row (None: not measured).
        self.measured_current = getattr(backend, "joint_current_A", None)
        #: The plant's true state at each read, copied into each row (None: not known, as on
        #: the motors; see Backend.true_state).
        self.true_state = getattr(backend, "true_state", None)
        # Then, only where the backend knows it (the simulated robot), the plant's true state
        # [q (all), qd (all)], appended last for the same reason: a run on the motors keeps
        # the rows the embedded runtime writes too.
        # The current block is there only when the drives measure it (log.csv's current
        # columns likewise: one schema, cochlea.log_schema).
        self.true_at = self.current_at + (0 if self.measured_current is None else self.n)
        self.width = self.true_at + (0 if self.true_state is None else 2 * self.n)
        self.buffer = np.full((0, self.width), np.nan)  # sized by run(): whole run or ring
        self.x = np.zeros(2 * self.n)
        self.tau = np.zeros(self.n)
        self.zero = np.zeros(self.n)

    def _allocate(self, log_path: Path | None) -> np.ndarray:
        """The period buffer: the whole run without a log file, else a ring of a few seconds."""
        rows = self.steps
        if log_path is not None:
            rows = min(rows, max(int(math.ceil(RING_SECONDS / self.h)), 16))
        return np.full((max(rows, 1), self.width), np.nan)

    def _fill_desired(self, chunk: int) -> None:
        """The desired samples of periods ``chunk * DESIRED_CHUNK`` on, at the times the rows
        log (``k * h``, bit for bit)."""
        k0 = chunk * DESIRED_CHUNK
        t = (k0 + self._chunk_times) * self.h
        for f, arrays in zip(self._desired_maps, self.desired):
            for target, value in zip(arrays, f(t) if f is not None else ()):
                target[...] = np.asarray(value).T
        for _, _, _, w, timed in self._follows:
            w[...] = np.asarray(timed(t)).T

    def desired_samples(self, unit: int, start: int, stop: int) -> tuple[np.ndarray, ...]:
        """``(xd, xd_dot, xd_ddot)`` of periods ``start..stop - 1`` for the report: the same
        function at the same times as the loop's chunks."""
        t = np.arange(start, stop) * self.h
        if not len(t):
            nd = self.setups[unit].controller.n_desired
            return tuple(np.zeros((0, nd)) for _ in range(3))
        if self.setups[unit].follow is not None:
            return self._followed(unit, self.rows_source().read(start, stop), t)
        return tuple(np.array(v).T.copy()
                     for v in self.setups[unit].desired.map(len(t))(t))

    def _followed(self, unit: int, rows: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, ...]:
        """A follower's desired samples at logged ``rows`` (times ``t``): its rule on the
        leader's logged measured state, what the period computed (NaN where it failed: the
        safe stop's row, or a row whose state was never measured)."""
        follow = self.setups[unit].follow
        lead, n = self.slices[follow.leader], self.n
        seen = np.hstack([rows[:, 1 + lead.start:1 + lead.stop],
                          rows[:, 1 + n + lead.start:1 + n + lead.stop]])
        out, bad = follow.evaluate(seen, t)
        for o in out[:3]:
            o[bad] = np.nan
        return tuple(out[:3])

    # ---- the loop ----------------------------------------------------------------------------

    def on_signal(self, signum, frame) -> None:  # noqa: ARG002
        """SIGINT, SIGTERM or SIGHUP (a hang-up): the loop's safe stop at its next period
        (public: cochlea-run forwards the signals here while the motors start, before the loop
        installs it). The first signal names the stop."""
        if self._signal is None:
            self._signal = SIGNAL_STOPS.get(signum, SIGNAL_STOPS[signal.SIGTERM])

    def status_line(self) -> str:
        k = self.rows
        if k == 0:
            return "waiting for the first period"
        buf, ring = self.buffer, len(self.buffer)
        t = (min(k, self.steps) - 1) * self.h
        err = buf[(k - 1) % ring, self.offsets[3]:self.offsets[3] + 3]
        # The last periods still in the buffer (the ring's, or the last 2000 of a whole run).
        recent = buf[:min(k, ring), self.offsets[-2] + 1]
        if ring >= k:
            recent = recent[-2000:]
        p99 = float(np.percentile(recent, 99)) if k > 2 else float("nan")
        return (f"t = {t:6.2f} s  |e| = {np.abs(err).max():.2e}  period p99 = "
                f"{p99 * 1e3:.3f} ms  overruns = {self.misses}")

    def run(self, log_path: Path | None = None, status: bool = False) -> Stop:
        self.log_path = log_path
        self.buffer = self._allocate(log_path)
        # Opened before anything moves: a log that cannot be written stops nothing.
        writer = LogWriter(self.buffer, log_path) if log_path else None
        previous = {s: signal.signal(s, self.on_signal) for s in SIGNAL_STOPS}
        status_thread = _Status(self) if status else None
        self.misses = 0
        applied = None
        try:
            self.backend.enable()
            if writer:
                writer.start()
            if status_thread:
                status_thread.start()
            if self.realtime:  # after the writer and status threads started: they stay normal
                applied = self._apply_options()
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
            if applied is not None:  # unlocked and back to normal before the report
                applied.undo()
            # The safe sequence, whatever happened: zero effort, drives off.
            try:
                self.backend.write(self.zero)
            finally:
                self.backend.disable()
            # Only threads that started can be joined: enable() may have failed before them.
            if writer:
                writer.done_rows = self.rows  # a stop's own row goes to the log too
                if writer.is_alive():
                    writer.close()
                else:
                    writer.discard()
            if status_thread and status_thread.is_alive():
                status_thread.close()
            for s, handler in previous.items():
                signal.signal(s, handler)
        if writer and writer.error is not None and self.stop.rule != "log-failure":
            # The writer failed while the last rows were flushed, after the loop had stopped.
            self.stop = Stop("log-failure", self.stop.time, self._log_failure(writer))
        return self.stop

    def _apply_options(self):
        obtained, problems, applied = apply_realtime(self.options)
        self.scheduling = _scheduling_text(self.options, obtained)
        self.realtime_report = {"requested": self.options.as_dict(), "obtained": obtained,
                                "problems": problems}
        if problems:  # once, before the first period: the run goes on with what it got
            self._warn("real-time settings not all obtained: " + "; ".join(problems)
                       + f"; running {self.scheduling}, memory "
                       + ("locked" if obtained["mlockall"] else "not locked")
                       + f", CPUs {_cpu_list(obtained['cpu'] or [])}")
        return applied

    def _log_failure(self, writer) -> str:
        if writer.error is not None:
            reason = writer.error.strerror or str(writer.error)
            what = f"the log writer failed: {reason} ({self.log_path})"
        elif self.realtime:
            what = (f"the log writer fell {len(self.buffer)} periods "
                    f"({len(self.buffer) * self.h:g} s) behind the loop")
        else:
            what = f"the log writer wrote nothing for {_log_writer.WRITER_STALL_S:g} s"
        return (f"{what}; log.bin holds the first {writer.written} of {self.rows} periods: "
                "free the disk or choose another --out")

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
        current = row[self.current_at:self.current_at + n]
        current[:] = np.nan  # stays NaN unless the backend measures current
        true = row[self.true_at:self.width]  # empty unless the backend knows the true state
        return row, row[1:1 + 2 * n], row[1 + 2 * n:1 + 3 * n], timing, current, true, units

    def _loop(self, writer) -> Stop:
        h_ns = int(round(self.h * 1e9))
        errors = 0
        watch = self.watch
        watch.reset()
        sup, backend, x, tau, buf = (self.supervisor, self.backend, self.x, self.tau,
                                     self.buffer)
        ring = len(buf)
        n = self.n
        q_view, qd_view = x[:n], x[n:]
        row, row_x, row_tau, row_timing, row_current, row_true, units = self._views()
        measured, true_state = self.measured_current, self.true_state
        estimates = [kern.outputs[1] for kern in self.kernels]
        clock, sleep = self._clock, self._sleep
        if self.rows:  # a second run of the same loop starts from the first chunk again
            self._fill_desired(0)
        self.rows = 0
        # Nothing measured yet: a failed first read leaves NaN here, never a state the robot is
        # not in (zeros computed a full-effort command on the slider once), and the loop
        # commands zero effort until its first good read (see the period below).
        x[:] = np.nan
        measured_once = False
        nan_errors = [np.full(len(kern.outputs[2]), np.nan) for kern in self.kernels]
        t0 = clock()
        previous_start = t0
        for k in range(self.steps):
            t = k * self.h
            j = k % DESIRED_CHUNK
            slot = k % ring
            deadline = t0 + k * h_ns
            if self.realtime:
                while True:  # sleep until SPIN before the deadline, then spin
                    remaining = deadline - clock()
                    if remaining <= 0:
                        break
                    if remaining > SPIN_NS:
                        sleep((remaining - SPIN_NS) * 1e-9)
            start = clock()
            if self._signal:
                rule, detail = self._signal
                return Stop(rule, t, detail)
            if self.realtime:
                # Too far behind to catch up: stop before this period commands anything.
                late = watch.started(deadline, start)
                if late:
                    return Stop("watchdog", t, late)
            # The log must keep up: a failed writer, or one that has not yet written the row
            # this period would overwrite, stops the run before anything else is commanded.
            if writer is not None and (writer.error is not None or k - writer.written >= ring):
                # As fast as possible, nothing is late: wait for the disk rather than stop.
                if self.realtime or not writer.wait_for(k - ring + 1):
                    return Stop("log-failure", t, self._log_failure(writer))
            ok = backend.read(x)
            errors = 0 if ok else errors + 1
            if errors > sup.limits.watchdog_errors:
                # A hardware backend knows why (a motor's alert, a timeout): the stop says so.
                cause = getattr(backend, "failure_detail", None)
                return Stop("watchdog", t, f"{errors} consecutive backend read failures"
                            + (f": {cause()}" if cause else ""))
            row[0] = t
            row_x[:] = x
            if measured is not None:  # the last good read's, like x after a failed read
                row_current[:] = measured
            if true_state is not None:  # the plant's state at this read (simulated robot)
                row_true[:] = true_state
            stop = sup.check_state(t, x, q_view, qd_view) if ok else None
            if stop:  # nothing was commanded in this period
                row[1 + 2 * n:self.current_at] = np.nan
                buf[slot] = row
                self.rows = k + 1
                return stop
            measured_once = measured_once or ok
            for i, follow, step, w, _ in (self._follows if measured_once else ()):
                # The rule on the leader's fresh measurement, into this period's desired row.
                lead = self.slices[follow.leader]
                x_lead = step.inputs[0]
                half = len(x_lead) // 2
                x_lead[:half] = x[lead]
                x_lead[half:] = x[n + lead.start:n + lead.stop]
                step.inputs[1][:] = w[j]
                step()
                if not follow.ok(step.outputs):  # nothing commanded in this period
                    row[1 + 2 * n:self.current_at] = np.nan
                    buf[slot] = row
                    self.rows = k + 1
                    failure = follow.failure(k, t, x_lead.copy(), step.outputs)
                    return Stop(MIRROR_RULE, t, failure.detail)
                for target, value in zip(self.desired[i], step.outputs):
                    target[j] = value
            if not measured_once:
                # No state measured yet: command nothing (zero effort keeps the drives' Bus
                # Watchdog fed and their torque off), step no controller, count the failure.
                tau[:] = 0.0
                for (_, kin, *_, row_err, row_p), nan in zip(units, nan_errors):
                    row_err[:] = nan
                    row_p[:] = kin[5]
            for kern, kin, q_u, qd_u, tau_u, (xd, xd_dot, xd_ddot), row_err, row_p in (
                    units if measured_once else ()):
                kin[0][:] = q_u
                kin[1][:] = qd_u
                kin[2][:] = xd[j]
                kin[3][:] = xd_dot[j]
                kin[4][:] = xd_ddot[j]
                kern()
                tau_u[:] = kern.outputs[0]
                row_err[:] = kern.outputs[2]
                row_p[:] = kin[5]  # the estimate used in this period
                kin[5][:] = kern.outputs[1]  # next period's estimate
            stop = sup.check_command(t, tau, estimates)
            if stop:  # the refused command is logged as computed; it was never written
                row_tau[:] = tau
                row_timing[:] = np.nan
                buf[slot] = row
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
            buf[slot] = row
            previous_start = start
            if self.realtime:
                overrun = watch.finished(deadline, end)
                self.misses = watch.overruns
                if overrun:
                    self.rows = k + 1
                    return Stop("watchdog", t, overrun)
            self.rows = k + 1
            if writer:
                writer.done_rows = k + 1
            if j == DESIRED_CHUNK - 1:  # the next chunk, in this period's slack
                self._fill_desired((k + 1) // DESIRED_CHUNK)
        return Stop("completed", (self.steps - 1) * self.h + self.h if self.steps else 0.0, "")

    # ---- results -------------------------------------------------------------------------

    def rows_source(self) -> RowSource:
        """The run's rows: ``log.bin`` when the run streamed to it, else the buffer."""
        if self.log_path is not None:
            return RowSource(self.width, self.rows, path=self.log_path)
        return RowSource(self.width, self.rows, buffer=self.buffer)

    def chunk_result(self, scenario, source: RowSource, start: int, stop: int,
                     step: int = 1) -> SimulationResult:
        """Periods ``start:stop:step`` of the run as an in-memory :class:`SimulationResult`."""
        buf, off, n = source.read(start, stop, step), self.offsets, self.n
        index = np.arange(start, start + len(buf) * step, step)
        logs = []
        for i, (u, sl) in enumerate(zip(self.setups, self.slices)):
            q = buf[:, 1 + sl.start:1 + sl.stop]
            qd = buf[:, 1 + n + sl.start:1 + n + sl.stop]
            errors = buf[:, int(off[3 + 2 * i]):int(off[4 + 2 * i])]
            p_hat = buf[:, int(off[4 + 2 * i]):int(off[5 + 2 * i])]
            tau = buf[:, 1 + 2 * n + sl.start:1 + 2 * n + sl.stop]
            # log.csv carries the current only when the run measured it: a simulated run's
            # log keeps its columns.
            current = None if self.measured_current is None else \
                buf[:, self.current_at + sl.start:self.current_at + sl.stop]
            rows = len(buf)

            def pose_of(joints, u=u, rows=rows):
                return np.array(u.fk_world.map(rows)(np.nan_to_num(joints).T)).T if rows else \
                    np.zeros((0, len(u.task_names)))

            pose = pose_of(q)
            true_q = true_qd = true_x = None
            if self.true_state is not None:  # the simulated robot's true state, as logged
                at = self.true_at
                true_q = buf[:, at + sl.start:at + sl.stop]
                true_qd = buf[:, at + n + sl.start:at + n + sl.stop]
                true_x = pose_of(true_q)
            if step == 1 or u.follow is not None:
                xd, xd_dot, _ = (self.desired_samples(i, start, start + rows) if step == 1 else
                                 self._followed(i, buf, index * self.h))
            else:
                t = index * self.h
                xd, xd_dot = (np.array(v).T.copy() for v in u.desired.map(rows)(t)[:2]) \
                    if rows else self.desired_samples(i, 0, 0)[:2]
            logs.append(UnitLog(u.name, scenario.space, q, qd, xd, xd_dot, errors, tau, p_hat,
                                pose, u, current, true_q, true_qd, true_x))
        result = SimulationResult(scenario, index * self.h, logs)
        timing = buf[:, int(off[-2]):int(off[-1])]
        result.timing = {"start_lateness_s": timing[:, 0], "wall_period_s": timing[:, 1],
                         "compute_s": timing[:, 2], "backend_io_s": timing[:, 3]}
        return result

    def result(self, scenario) -> SimulationResult:
        """The log as a :class:`SimulationResult`, so the report writes it like any run: in
        memory for a run without a log file, else read back from ``log.bin`` a chunk at a time
        (:class:`~cochlea.sim.result.StreamedResult`)."""
        source = self.rows_source()
        if self.log_path is None:
            return self.chunk_result(scenario, source, 0, source.rows)
        head = self.chunk_result(scenario, source, 0, 0)
        return StreamedResult(scenario, head.units, source.rows, timing=head.timing,
                              read=lambda a, b, step=1: self.chunk_result(scenario, source, a, b,
                                                                          step))

    def timing_summary(self) -> dict:
        watch = self.watch
        return {**timing_of(self.rows_source(), int(self.offsets[-2]), self.h),
                "overruns": watch.overruns if self.realtime else 0,
                "lateness_max": watch.worst_lateness_ns * 1e-9,
                "overrun_policy": OVERRUN_POLICY,
                "stall_limit": watch.stall_ns * 1e-9,
                "lateness_limit": watch.max_lateness_ns * 1e-9,
                "scheduling": self.scheduling,
                "watchdog_misses_allowed": self.supervisor.limits.watchdog_misses}


def raw_columns(loop: RealTimeLoop) -> list[str]:
    """Names (with units) of the columns of ``log.bin``, the raw period buffer: the one
    schema's (:func:`cochlea.log_schema.raw_columns`)."""
    return log_schema.raw_columns([log_schema.LogUnit.of_setup(u, u.controller.space)
                                   for u in loop.setups],
                                  current=loop.measured_current is not None,
                                  true_state=loop.true_state is not None)


def write_raw_columns(path: Path, loop: RealTimeLoop) -> None:
    """``log.columns.json``: how to read ``log.bin`` (float64 rows) if the run was killed."""
    document = log_schema.columns_document(
        [log_schema.LogUnit.of_setup(u, u.controller.space) for u in loop.setups],
        current=loop.measured_current is not None, true_state=loop.true_state is not None,
        row_length=loop.width)
    path.write_text(json.dumps(document, indent=1) + "\n")
