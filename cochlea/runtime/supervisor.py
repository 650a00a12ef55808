"""The safety supervisor of a run: every rule that stops the motors, and the exit code of each.

Each period the loop asks :meth:`Supervisor.check_state` about the measured state and
:meth:`Supervisor.check_command` about the command and the estimates; the first rule broken
returns a :class:`Stop`, and the loop then commands zero effort and disables the drives in the
same period. The checks allocate nothing unless a rule is broken.
"""

from __future__ import annotations

import contextlib
import math
import os
import signal
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..kernels import library as ckernels
from ..sim.compiled import period_kernels
from ..sim.result import SimulationResult
from ..sim.setup import MIRROR_RULE, UnitSetup

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
    "terminated": 16,  # SIGTERM, or SIGHUP (a hang-up: the terminal or session closed)
    "log-failure": 17,  # the log writer failed (full disk) or fell a whole ring behind
    # mirror = "measured": a follower's rule gave a pose out of its reach, or not finite (18 is
    # cochlea-run's lost report)
    MIRROR_RULE: 19,
}

#: The stop a signal asks for: its rule (so its exit code) and the detail summary.json and the
#: stop line give. A hang-up (SIGHUP: the terminal or SSH session that started the run closed)
#: is SIGTERM's safe stop and exit code 16, its detail naming the hang-up; the embedded
#: program (embedded/posix/main.c) words the three the same.
SIGNAL_STOPS = {
    signal.SIGINT: ("user-stop", "SIGINT received (Ctrl-C)"),
    signal.SIGTERM: ("terminated", "SIGTERM received"),
    signal.SIGHUP: ("terminated", "SIGHUP received: the terminal or session hung up"),
}


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
    keep_out_radius: float | None = None  # m; None: no keep-out circle
    watchdog_misses: int = 20  # consecutive overruns; also a stall's length in periods
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
        # keep_out_points: (q_all) -> the tool points and their centres, one preallocated
        # array written in place (KeepOutPoints), its rows named by .labels
        self.keep_out_points = keep_out_points
        self.bounds = [u.bound for u in setups]
        self._effort_lo = np.empty_like(limits.effort)  # scratch: saturate's lower side

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
            points = self.keep_out_points(q)
            for i in range(len(points)):
                pu, pv, cu, cv = points[i, 0], points[i, 1], points[i, 2], points[i, 3]
                r = math.hypot(pu - cu, pv - cv)
                if r < L.keep_out_radius:
                    return Stop("keep-out", t, f"{self.keep_out_points.labels[i]} at "
                                f"({pu:.4f}, {pv:.4f}) m is {r * 1000:.1f} mm from the centre "
                                f"({cu:.4f}, {cv:.4f}) m, inside the keep-out radius "
                                f"{L.keep_out_radius * 1000:.1f} mm")
        return None

    def check_command(self, t: float, tau: np.ndarray, estimates: list[np.ndarray]
                      ) -> Stop | None:
        """A command with a NaN or an infinity stops the run as ``non-finite``, and so does one
        whose sum of squares overflows (a joint's effort beyond about 1e154: a controller that
        has blown up, stopped rather than clipped to the effort limit); an estimate that is
        finite but beyond its bound stops it as ``estimate-bound`` however large it is."""
        if not math.isfinite(float(tau @ tau)):
            return Stop("non-finite", t, f"command = {_fmt(tau)}")
        for u, p, bound in zip(self.setups, estimates, self.bounds):
            square = float(p @ p)
            if not math.isfinite(square) and not _finite(p):
                return Stop("non-finite", t, f"{u.name} estimate = {_fmt(p)}")
            if square > (bound * (1 + 1e-9)) ** 2:
                # finite values whose squares overflow: the norm taken without overflow
                norm = math.sqrt(square) if math.isfinite(square) else math.hypot(*p.tolist())
                return Stop("estimate-bound", t, f"{u.name} |p_hat| = {norm:.4g}, bound "
                            f"{bound:.4g}")
        return None

    def saturate(self, tau: np.ndarray) -> None:
        """Each joint's command clipped to its effort limit, in place (np.clip's values).
        The lower side is negated again every call, into scratch: limits changed in place
        (a test does) must bind both ways, never leave an old -effort below. np.clip made a
        fresh -effort and went through its wrapper each period: 2.3x the time of these three."""
        effort = self.limits.effort
        lo = self._effort_lo
        if lo.shape != effort.shape:  # the limits replaced by others: new scratch
            lo = self._effort_lo = np.empty_like(effort)
        np.negative(effort, out=lo)
        np.minimum(np.maximum(tau, lo, out=tau), effort, out=tau)


#: The least the loop may fall behind its absolute deadlines before the watchdog stops it (s);
#: more when ``--watchdog-misses`` periods are longer (see :class:`OverrunWatch`).
MAX_LATENESS_S = 0.1

#: The overrun policy in one sentence, for ``summary.json`` (docs/runtime.md states it in full).
OVERRUN_POLICY = (
    "period k is due at t0 + k h; it overruns when its own work -- from its deadline or the "
    "previous period's end, whichever is later, to its end -- takes longer than h; late periods "
    "that catch up within h each are late, not overruns. The watchdog stops the run on "
    "N consecutive overruns (--watchdog-misses N), on one period whose own work exceeds N "
    "periods (a stall), or when a period starts more than max(N h, 0.1 s) late")


class OverrunWatch:
    """The deadline watchdog: a lateness-based overrun rule (the policy: ``OVERRUN_POLICY``).

    Measured against absolute deadlines, a stall of one period followed by catch-up periods is
    one overrun, not as many misses as the periods it delays: the catch-up periods run back to
    back, each within a period, and the lateness falls. Three stops remain: ``misses``
    overruns in a row (a loop slower than its rate), one period stuck for more than ``misses``
    periods (a stall), and a lateness beyond ``max(misses periods, MAX_LATENESS_S)`` (overruns
    that come faster than the loop catches up, never ``misses`` in a row). Times in integer
    nanoseconds of one clock; nothing allocates unless a rule is broken."""

    def __init__(self, period_ns: int, misses: int):
        self.h = int(period_ns)
        self.misses = int(misses)
        self.stall_ns = self.misses * self.h
        self.max_lateness_ns = max(self.stall_ns, int(round(MAX_LATENESS_S * 1e9)))
        self.reset()

    def reset(self) -> None:
        self.consecutive = 0
        self.overruns = 0  # periods whose own work overran, in the whole run
        self.worst_lateness_ns = 0
        self._previous_end: int | None = None

    def started(self, deadline: int, start: int) -> str | None:
        """Before a period does anything: its lateness against its deadline."""
        lateness = start - deadline
        if lateness > self.worst_lateness_ns:
            self.worst_lateness_ns = lateness
        if lateness > self.max_lateness_ns:
            return (f"the loop fell {lateness * 1e-6:.1f} ms behind its deadlines (at most "
                    f"{self.max_lateness_ns * 1e-6:g} ms: max({self.misses} periods, "
                    f"{MAX_LATENESS_S * 1e3:g} ms)); it did not catch up")
        return None

    def finished(self, deadline: int, end: int) -> str | None:
        """After a period's command was written: whether its own work overran."""
        previous, self._previous_end = self._previous_end, end
        begin = deadline if previous is None or previous < deadline else previous
        own = end - begin
        if own <= self.h:
            self.consecutive = 0
            return None
        self.overruns += 1
        self.consecutive += 1
        if own > self.stall_ns:
            return (f"the loop stalled: one period took {own * 1e-6:.1f} ms, more than "
                    f"{self.misses} periods of {self.h * 1e-6:g} ms")
        if self.consecutive > self.misses:
            return (f"{self.consecutive} consecutive deadline misses: each period's own work "
                    f"overran its {self.h * 1e-6:g} ms (the last took {own * 1e-6:.3f} ms)")
        return None


def _finite(v: np.ndarray) -> bool:
    """Every value finite (neither NaN nor infinite), however large: no array made, and
    faster than a sum of squares at a loop's few values (whose overflow would also call
    finite values non-finite)."""
    return all(map(math.isfinite, v.tolist()))


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v).ravel()) + "]"


def _show(value: float, unit: str) -> str:
    shown, suffix, places = (math.degrees(value), "deg", ".2f") if unit == "rad" else \
        (value, "m", ".4f")
    # beyond any joint's travel (a wrong measurement): digits, not a 200-digit number
    return f"{shown:{'.4g' if abs(shown) >= 1e9 else places}} {suffix}"


class KeepOutPoints:
    """Every unit's keep-out tool points and their centres at a joint position of the whole
    system (SI), written each call into one array made here: a row a point, ``(u, v)`` of the
    point then of its centre (m, world frame), the rows named by :attr:`labels`. A period
    builds no list or tuple and no array's data (the supervisor's checks allocate nothing)."""

    def __init__(self, setups: list[UnitSetup], fks: list):
        self.labels = tuple(f"{u.name} {label}" for u in setups for label, _ in u.tool_points)
        self.points = np.zeros((len(self.labels), 4))
        self._units = []
        start = 0
        for u, fk in zip(setups, fks):
            n = u.controller_model.nq
            cu, cv, joint = u.keep_out_reference()  # the centre's rule: UnitSetup's
            moving = None if joint is None else start + joint
            self._units.append((fk, slice(start, start + n),
                                tuple(uv for _, uv in u.tool_points), (cu, cv), moving))
            start += n

    def __call__(self, q: np.ndarray) -> np.ndarray:
        points = self.points
        row = 0
        for fk, joints, tools, (cu, cv), moving in self._units:
            fk.inputs[0][...] = q[joints]
            fk()
            pose = fk.outputs[0]
            if moving is not None:  # on a joint: the parallel mechanism's slider, S = (0, d1)
                cv = cv + q[moving]
            for iu, iv in tools:
                points[row, 0] = pose[iu]
                points[row, 1] = pose[iv]
                points[row, 2] = cu
                points[row, 3] = cv
                row += 1
        return points


#: Pose kernels bound for the keep-out rule (:func:`build_supervisor` with ``cache``), kept
#: per process and thread: a sweep's worker binds its structure's once, not once a sample.
POSE_KERNEL_CACHE_SIZE = 16
_POSE_KERNELS: OrderedDict[tuple, tuple] = OrderedDict()


def _pose_kernel(u: UnitSetup, substeps: int, kernels: str):
    """:func:`period_kernels`' pose kernel of ``u``, bound once per thread for the same
    Functions, kernels and library (the Functions kept with it, so their ids stay theirs).
    Per thread: a kernel is called through its own buffers, and a ``dask worker`` may run
    several samples at once on its threads. A C library that cannot run them falls back to
    CasADi with its warning every time, as without the cache."""
    key = (threading.get_ident(), kernels, substeps, os.environ.get(ckernels.ENVIRONMENT),
           id(u.fk_world), id(u.controller), id(u.plant_model), u.drive is not None, u.gearbox)
    hit = _POSE_KERNELS.get(key)
    if hit is not None:
        with contextlib.suppress(KeyError):  # another thread's eviction may come first
            _POSE_KERNELS.move_to_end(key)
        return hit[-1]
    *_, pose, source = period_kernels(u, substeps, kernels)
    if source == kernels:
        _POSE_KERNELS[key] = (u.fk_world, u.controller, u.plant_model, pose)
        while len(_POSE_KERNELS) > POSE_KERNEL_CACHE_SIZE:
            with contextlib.suppress(KeyError):  # emptied by another thread meanwhile
                _POSE_KERNELS.popitem(last=False)
    return pose


def build_supervisor(setups: list[UnitSetup], keep_out_radius: float | None,
                     watchdog_misses: int = 20, watchdog_errors: int = 5,
                     kernels: str = "c", substeps: int = 1, cache: bool = False) -> Supervisor:
    """Limits from the descriptions of every unit's joints; the keep-out circle (None: none)
    around each unit's centre (serial: the cochlea centre; parallel: the slider pivot S, which
    moves with d1) for each of its tool points, in joint-space runs as in task-space ones: the
    circle protects what is around the centre whatever coordinates the controller tracks.
    ``cache``: the pose kernels bound once per process (a sweep's samples; the same kernels,
    so the same verdicts), else bound here."""
    joints = [j for u in setups for j in u.controller_model.joints]
    limits = Limits(
        position_lo=np.array([j.position_limits[0] for j in joints]),
        position_hi=np.array([j.position_limits[1] for j in joints]),
        velocity=np.array([j.velocity_limit for j in joints]),
        effort=np.array([j.effort_limit for j in joints]),
        joint_names=tuple(f"{u.name}.{j.name}" for u in setups for j in u.controller_model.joints),
        joint_units=tuple(un for u in setups for un in u.joint_units),
        keep_out_radius=keep_out_radius,
        watchdog_misses=watchdog_misses, watchdog_errors=watchdog_errors)
    fks = [_pose_kernel(u, substeps, kernels) if cache else period_kernels(u, substeps, kernels)[2]
           for u in setups]
    return Supervisor(limits, setups, KeepOutPoints(setups, fks))


def first_violation(result: SimulationResult, supervisor: Supervisor,
                    reductions: list[LogReductions] | None = None) -> Stop | None:
    """The rule a real-time run of the same periods would have stopped on, and when: the
    supervisor's checks applied to a logged run (an as-fast simulation, which does not stop).

    Period k is checked as the loop checks it: the state it measures at its start (positions,
    velocities, keep-out circle, finite), then the command and the estimate it produces for
    period k + 1. The loop sees the robot through its measurement, so the state checked is the
    one the loop would read: the logged measured state, what the controller saw (delayed,
    noisy, on the encoder and velocity-register grids where the plant has them;
    :func:`measured_states`). A run that breaks no rule is told by each unit's whole-log
    extremes (:func:`_nothing_flagged`); else the rows are screened at once with numpy and the
    flagged ones passed through the supervisor itself, in order, so the rule and its message
    are the loop's own (the keep-out circle is screened last, on the periods before the first
    stop the other rules found: a pose the run did not log is computed there only).
    ``reductions``: each unit's :func:`log_reductions` of this result, when the caller has
    them (the summary reads them too); the same verdict either way.
    """
    logs = result.units
    rows = len(result.time)
    if rows == 0:
        return None
    if _nothing_flagged(result, supervisor, reductions):
        return None
    L = supervisor.limits
    limits = [(bound * (1 + 1e-9)) ** 2 for bound in supervisor.bounds]
    n = sum(u.q.shape[1] for u in logs)

    def screen(a: int, b: int):
        """Periods a..b-1 stacked (measured states, efforts, the estimates they hand on: the
        next row's, the last row's own at the end) and which of them the screen flags."""
        q = np.hstack([u.q[a:b] for u in logs])
        qd = np.hstack([u.qd[a:b] for u in logs])
        tau = np.hstack([u.tau[a:b] for u in logs])
        estimates = [np.vstack([u.p_hat[a + 1:b + 1]] + ([u.p_hat[-1:]] if b == rows else []))
                     for u in logs]
        with np.errstate(invalid="ignore", over="ignore"):
            flagged = ~np.isfinite(q).all(axis=1) | ~np.isfinite(qd).all(axis=1)
            flagged |= ((q < L.position_lo) | (q > L.position_hi)).any(axis=1)
            flagged |= (np.abs(qd) > L.velocity).any(axis=1)
            flagged |= ~np.isfinite(tau).all(axis=1)
            for p, limit in zip(estimates, limits):
                square = np.einsum("ij,ij->i", p, p)
                flagged |= ~np.isfinite(square) | (square > limit)
        return q, qd, tau, estimates, flagged

    # A run the gate sends here mostly broke a rule early (a gain or a plant the controller
    # cannot hold): the periods are screened a block at a time, from the start, up to the
    # block of the first stop, not the whole run stacked and screened for one early period.
    blocks = []  # (start, q, qd, tau, estimates) of each block screened

    def check(k: int) -> Stop | None:
        """Period k (in a block screened) as the loop checks it."""
        a, q, qd, tau, estimates = next(block for block in reversed(blocks) if block[0] <= k)
        t = float(result.time[k])
        x = np.concatenate([q[k - a], qd[k - a]])
        stop = supervisor.check_state(t, x, x[:n], x[n:])
        if stop is None:
            stop = supervisor.check_command(t, tau[k - a].copy(), [p[k - a] for p in estimates])
        return stop

    first, stop, flags = rows, None, []
    for a, b in _screen_blocks(rows):
        q, qd, tau, estimates, flagged = screen(a, b)
        blocks.append((a, q, qd, tau, estimates))
        flags.append(flagged)
        for k in np.flatnonzero(flagged) + a:
            stop = check(int(k))
            if stop is not None:
                first = int(k)
                break
        if stop is not None:
            break
    flagged = np.concatenate(flags)

    if L.keep_out_radius is None or first == 0:
        return stop
    # The keep-out circle, on the periods before that stop only (the pose of the measured
    # state is computed there if the run did not log it): screened on the logged pose, which
    # the supervisor's own kernel may compute a last bit differently, so with a margin, and
    # confirmed exactly. A period the screen above flagged was checked whole already.
    with np.errstate(invalid="ignore"):
        near = _near_keep_out(logs, first, L.keep_out_radius + _KEEP_OUT_SCREEN)
    for k in np.flatnonzero(near & ~flagged[:first]):
        earlier = check(k)
        if earlier is not None:
            return earlier
    return stop


#: The periods :func:`first_violation` screens at once: the first blocks end here (each a
#: multiple of 64 periods, so each period's row sits where it sat in one array of them all).
_SCREEN_ENDS = (256, 4096)


def _screen_blocks(rows: int):
    """``(start, stop)`` of each block of periods :func:`first_violation` screens, in order."""
    start = 0
    for end in (*[e for e in _SCREEN_ENDS if e < rows], rows):
        yield start, end
        start = end


def _near_keep_out(logs, rows: int, radius: float) -> np.ndarray:
    """Per period of the first ``rows``, whether a measured tool point of any unit is within
    ``radius`` (m) of its keep-out centre."""
    near = np.zeros(rows, bool)
    for u in logs:
        s = u.setup
        q = u.q[:rows]
        if u.x is not None:
            pose = u.x[:rows]
        else:  # the pose of the measured state, as UnitLog.pose computes it, on these rows
            pose = np.array(s.fk_world.map(rows)(q.T)).T
        cu, cv = s.keep_out_centre(q)
        for _, (iu, iv) in s.tool_points:
            near |= np.hypot(pose[:, iu] - cu, pose[:, iv] - cv) < radius
    return near


def _nothing_flagged(result: SimulationResult, supervisor: Supervisor,
                     reductions: list[LogReductions] | None = None) -> bool:
    """Whether the row-by-row screen of :func:`first_violation` would flag no row, from
    whole-run reductions of each unit's own log (a column's extremes, the largest estimate),
    nothing stacked or copied: the common case, a run that breaks no rule, for a fraction of
    the screen's time (a sweep judges every sample). Each test here holding implies its screen
    flags nothing; one that fails sends the run through the screen as before, so the verdict
    is the same either way."""
    L = supervisor.limits
    first = 0  # the unit's first joint in the limits
    reductions = own_reductions(reductions, result.units)
    with np.errstate(invalid="ignore", over="ignore"):
        for i, (u, bound) in enumerate(zip(result.units, supervisor.bounds)):
            joints = slice(first, first + u.q.shape[1])
            first = joints.stop
            # A column's extremes are finite only when all of it is (a NaN makes both NaN, an
            # infinity one of them infinite), and inside the rule's bounds only when all of it
            # is: a position within its limits, a speed |qd| within its limit.
            reduced = reductions[i]
            if reduced is not None and reduced.state_low is not None:
                within = _extremes_within(reduced.state_low, reduced.state_high,
                                          L.position_lo[joints], L.position_hi[joints],
                                          L.velocity[joints])
            else:
                within = _state_within(u.q, u.qd, L.position_lo[joints], L.position_hi[joints],
                                       L.velocity[joints])
            if not within:
                return False
            if reduced is None:
                if not (math.isfinite(u.tau.min(initial=0.0))
                        and math.isfinite(u.tau.max(initial=0.0))):
                    return False
            elif not (np.isfinite(reduced.tau_low).all() and np.isfinite(reduced.tau_high).all()):
                return False
            # The estimate each period hands on is the next row's (the last row's own at the
            # end): every row but the first. |p|^2 <= n max|p_i|^2, or the rows' squares summed
            # in another order, settle most runs without einsum's norm a row (the slack covers
            # the sums' rounding); NaN fails every test.
            p = u.p_hat[1:] if len(u.p_hat) > 1 else u.p_hat
            limit = (bound * (1 + 1e-9)) ** 2
            if reduced is None:
                # max |p_i| from the extremes, without an array of |p| (a NaN makes both NaN).
                peak = max(p.max(initial=0.0), -p.min(initial=0.0))
                screened = p.shape[1] * peak * peak * (1 + 1e-12) <= limit
            else:
                screened = reduced.square_later * (1 + 1e-12) <= limit
            if not screened:
                largest = np.einsum("ij,ij->i", p, p).max(initial=0.0)
                if not largest <= limit:
                    return False
        if L.keep_out_radius is not None and not _clear_of_keep_out(result, L.keep_out_radius,
                                                                    reductions):
            return False
    return True


@dataclass(frozen=True)
class LogReductions:
    """One unit log's whole-run reductions that the verdict and the summary both read
    (:func:`log_reductions`): each read once, while the log is still near in the caches, not
    once by each rule that needs it, or gathered by the C driver as it wrote the log. They
    describe the log as it was when computed."""

    rows: int  # the rows they describe
    tau_low: np.ndarray  # each effort column's min (NaN where the column has one)
    tau_high: np.ndarray  # and max
    #: The largest estimate row sum of squares (row_squares, or the driver's sum in column
    #: order: the screens allow for the order): over every row, and over the rows after the
    #: first, the estimates the periods hand on (the first alone when it is the only row);
    #: NaN where a row's is.
    square_all: float
    square_later: float
    #: Each measured state column's ``[q, qd]`` min and max, when the driver gathered them
    #: (None: the verdict reads the log).
    state_low: np.ndarray | None = None
    state_high: np.ndarray | None = None
    #: The smallest squared distance (m^2) of a keep-out tool point to its centre over the
    #: rows' true poses (``true_x``), when the driver gathered it.
    keep_out_nearest: float | None = None

    def describes(self, u) -> bool:
        """Whether these can be ``u``'s: as many rows, columns of effort and of state."""
        return (self.rows == len(u.p_hat) == len(u.tau) == len(u.q)
                and self.tau_low.shape == u.tau.shape[1:]
                and (self.state_low is None or self.state_low.shape == (2 * u.q.shape[1],)))


def own_reductions(reductions: list[LogReductions | None] | None, units
                   ) -> list[LogReductions | None]:
    """Per unit log, the caller's reductions where they can be its own, else None (each
    reader then reduces the log itself)."""
    if reductions is None or len(reductions) != len(units):
        return [None] * len(units)
    return [r if r is not None and r.describes(u) else None for r, u in zip(reductions, units)]


def log_reductions(u) -> LogReductions:
    """:class:`LogReductions` of a unit's log (a :class:`~cochlea.sim.result.UnitLog`): what
    its C driver gathered while writing it where it still holds those arrays, else read from
    the log (the same extremes; the largest squares summed in another order for many
    columns)."""
    gathered = u.gathered.of(u) if getattr(u, "gathered", None) is not None else None
    if gathered is not None:
        return LogReductions(gathered.rows, gathered.tau_low, gathered.tau_high,
                             gathered.square_all, gathered.square_later, gathered.state_low,
                             gathered.state_high, gathered.keep_out_nearest)
    low, high = column_extremes(u.tau)
    squares = row_squares(u.p_hat)
    later = squares[1:] if len(squares) > 1 else squares
    return LogReductions(len(u.p_hat), low, high, float(squares.max(initial=0.0)),
                         float(later.max(initial=0.0)))


#: Up to this many columns, :func:`row_squares` adds column after column (einsum beyond).
_COLUMN_SUMS = 8


def row_squares(p: np.ndarray) -> np.ndarray:
    """Each row's sum of squares, for screens that allow for the sum's rounding (einsum's
    order differs): of a few columns, the squares added a column at a time into one scratch
    row, several times faster than einsum's row by row, and in the order np.linalg.norm adds
    them."""
    if not 0 < p.shape[1] <= _COLUMN_SUMS:
        return np.einsum("ij,ij->i", p, p)
    if p.shape[1] <= 3:  # a column at a time: two scratch rows, no array of every square
        total = np.multiply(p[:, 0], p[:, 0])
        square = np.empty_like(total)
        for j in range(1, p.shape[1]):
            total += np.multiply(p[:, j], p[:, j], out=square)
        return total
    # More columns: every square at once (one contiguous pass), then the columns added in
    # order: the same products and sums as squaring a column at a time, in fewer strided
    # passes (a sweep's worker: the parallel mechanism's estimates, 1.5 -> 1.1 ms a verdict).
    squares = np.square(p)
    total = squares[:, 0].copy()
    for j in range(1, p.shape[1]):
        total += squares[:, j]
    return total


#: Rows a block of :func:`column_extremes` holds: the block's columns are reduced across the
#: blocks with whole rows of SIMD work, then within the block.
_EXTREMES_BLOCK = 256
#: A block's rows are folded this many at a time (twice: 16 x 16 = 256).
_EXTREMES_FOLD = 16


def column_extremes(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each column's ``(min, max)`` of a C-contiguous 2-D log (``+inf``, ``-inf`` for no
    rows), exactly (a NaN in a column makes both NaN), in two passes over the memory: numpy
    reduces a C-ordered log along its rows element by element (several times slower than a
    column alone), so the rows go in blocks whose every column is reduced at once. The rows
    past the last whole block are reduced as the log's last block (a minimum or maximum
    may read a row twice), and a block's rows folded 16 at a time (a reduction of 256 short
    rows costs more than the pass itself)."""
    n, m = a.shape
    full = n // _EXTREMES_BLOCK * _EXTREMES_BLOCK
    if not full or not m:
        low, high = np.full(m, np.inf), np.full(m, -np.inf)
        if n:
            low, high = np.minimum(low, a.min(axis=0)), np.maximum(high, a.max(axis=0))
        return low, high
    blocks = a[:full].reshape(-1, _EXTREMES_BLOCK * m)  # a view: whole rows per block
    low = np.minimum.reduce(blocks, axis=0)
    high = np.maximum.reduce(blocks, axis=0)
    if full < n:
        last = a[n - _EXTREMES_BLOCK:].reshape(-1)
        np.minimum(low, last, out=low)
        np.maximum(high, last, out=high)
    folded = _EXTREMES_FOLD * m
    low = np.minimum.reduce(low.reshape(-1, folded), axis=0)
    high = np.maximum.reduce(high.reshape(-1, folded), axis=0)
    return (np.minimum.reduce(low.reshape(_EXTREMES_FOLD, m), axis=0),
            np.maximum.reduce(high.reshape(_EXTREMES_FOLD, m), axis=0))


def _side_by_side(q: np.ndarray, qd: np.ndarray) -> np.ndarray | None:
    """``[q, qd]`` as one C-contiguous array without a copy when they are the two halves of
    each row of one (a simulated log's measured state), else None."""
    rows, n = q.shape
    item = q.itemsize
    if (qd.shape != (rows, n) or q.dtype != np.float64 or qd.dtype != np.float64 or rows < 2
            or q.strides != (2 * n * item, item) or qd.strides != q.strides):
        return None
    start = q.ctypes.data
    if qd.ctypes.data != start + n * item:
        return None
    # The same memory q and qd cover together: every row's 2 n values, in order. Most often
    # that is the first rows of the array they were cut from (a simulated log's state): a
    # slice of it costs a fraction of a strided view built anew.
    base = q.base
    if (isinstance(base, np.ndarray) and base.dtype == np.float64 and base.ndim == 2
            and base.strides == q.strides and base.shape[1] == 2 * n and len(base) >= rows
            and base.ctypes.data == start):
        state = base[:rows]
        state.flags.writeable = False
        return state
    return np.lib.stride_tricks.as_strided(q, (rows, 2 * n), q.strides, writeable=False)


def _state_within(q: np.ndarray, qd: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                  speed: np.ndarray) -> bool:
    """Every position of ``q`` finite and within its ``[lo, hi]``, every speed |qd| within
    its ``speed`` (and finite): :func:`_columns_within` of both, from the extremes of the
    array they share when they share one (:func:`column_extremes`, a pass for all columns)."""
    state = _side_by_side(q, qd)
    if state is None:
        return _columns_within(q, lo, hi) and _columns_within(qd, -speed, speed)
    return _extremes_within(*column_extremes(state), lo, hi, speed)


def _extremes_within(low: np.ndarray, high: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     speed: np.ndarray) -> bool:
    """From each ``[q, qd]`` column's extremes (a NaN in a column makes them NaN): every
    position finite and within its ``[lo, hi]``, every speed |qd| within its ``speed``."""
    n = len(lo)
    with np.errstate(invalid="ignore"):
        return bool(np.isfinite(low).all() and np.isfinite(high).all()
                    and (low[:n] >= lo).all() and (high[:n] <= hi).all()
                    and (low[n:] >= -speed).all() and (high[n:] <= speed).all())


def _columns_within(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Every column of ``a`` (rows of a log) finite and within its ``[lo, hi]``, from its
    extremes, one column at a time (numpy reduces a column, a strided view, several times
    faster than a block along its rows)."""
    for j in range(a.shape[1]):
        column = a[:, j]
        low, high = column.min(initial=np.inf), column.max(initial=-np.inf)
        if not (math.isfinite(low) and math.isfinite(high) and low >= lo[j] and high <= hi[j]):
            return False
    return True


def _clear_of_keep_out(result: SimulationResult, radius: float,
                       reductions: list[LogReductions | None] | None = None) -> bool:
    """No measured tool point of any unit near the keep-out circle: the pose of the measured
    state where the run has it. Else (an as-fast run that measured through a delay or a grid
    and did not compute that pose) the true pose: where the positions were measured exactly
    (no grid, no noise) each measured position is a true one of an earlier period, with its
    centre, so the true poses' nearest approach bounds the measured ones'; on a grid, with a
    margin no grid rounding crosses (a few encoder counts of any joint move a tool by far
    less). With position noise, the measured pose itself. ``reductions``: each unit's
    (:func:`own_reductions`), whose nearest approach the driver gathered over the true poses
    is read where the true poses are the ones judged."""
    noisy = result.scenario.plant.noise_q_std > 0
    reductions = own_reductions(reductions, result.units)
    for u, reduced in zip(result.units, reductions):
        s = u.setup
        n = u.q.shape[1]
        if u.x is None and u.has_true_state and not noisy:
            exact = s.quantum is None or not np.any(s.quantum[:n] > 0)
            pose, joints = u.true_x, u.true_q
            margin = _KEEP_OUT_SCREEN if exact else _GRID_SCREEN
        else:
            pose, joints, margin = u.pose, u.q, _KEEP_OUT_SCREEN
        limit = ((radius + margin) * (1 + 1e-9)) ** 2
        if reduced is not None and reduced.keep_out_nearest is not None and pose is u.true_x:
            # The true poses (the measured ones where the plant measures exactly: the same
            # array), each tool point's distance summed as below.
            if not reduced.keep_out_nearest >= limit:
                return False
            continue
        cu, cv = s.keep_out_centre(joints)
        for _, (iu, iv) in s.tool_points:
            # Squared, without hypot's cost; the relative slack covers its rounding. In place:
            # two arrays of a column, not five.
            du, dv = np.subtract(pose[:, iu], cu), np.subtract(pose[:, iv], cv)
            du *= du
            dv *= dv
            du += dv
            nearest = du.min(initial=np.inf)
            if not nearest >= limit:
                return False
    return True


#: How far outside the keep-out circle (m) a logged pose is still screened: the logged pose
#: of the measured state and the supervisor's own pose kernel (C or CasADi) agree but for
#: round-off; the screen only needs to be that much wider.
_KEEP_OUT_SCREEN = 1e-9
#: How far outside the circle (m) the whole-run gate keeps a true pose when the measured one
#: was not computed: a few encoder counts of any joint move a tool by far less.
_GRID_SCREEN = 0.005


def measured_states(result: SimulationResult) -> tuple[np.ndarray, np.ndarray]:
    """``(q, qd)`` of every period as the loop measures them (all units side by side, SI): the
    logged measured state, what the controller saw (the true state ``delay_periods`` earlier,
    plus the run's own measurement noise, on each unit's measurement grid)."""
    return (np.hstack([u.q for u in result.units]), np.hstack([u.qd for u in result.units]))


def saturated_periods(result: SimulationResult, supervisor: Supervisor,
                      reductions: list[LogReductions] | None = None) -> int:
    """Periods whose command was clipped to a joint's effort limit or, with current
    quantisation, saturated by its drive (the logs hold the applied command, so a clipped one
    sits exactly on the largest effort the joint can get: its limit, or its drive's
    :attr:`~cochlea.sim.setup.EffortGrid.top`, the Current Limit's effort or the grid level
    the limit rounds to)."""
    top = supervisor.limits.effort
    if any(u.setup.effort_grid is not None for u in result.units):
        top = np.minimum(top, np.concatenate([
            u.setup.effort_limit if u.setup.effort_grid is None else u.setup.effort_grid.top
            for u in result.units]))
    with np.errstate(invalid="ignore"):
        # Most runs never reach a limit: each column's largest |effort| shows it without a
        # row count or a copy of the logs (a NaN goes on to the count), from its extremes.
        reductions = own_reductions(reductions, result.units)
        if not reductions or any(r is None for r in reductions):
            lowest = top.min()
            if all(max(u.tau.max(initial=0.0), -u.tau.min(initial=0.0)) < lowest
                   for u in result.units):
                return 0
            can_clip = np.ones(len(top), bool)
        else:
            peaks = np.concatenate([np.maximum(r.tau_high, -r.tau_low) for r in reductions])
            can_clip = ~(peaks < top)
            if not can_clip.any():
                return 0
        # The periods with any joint at its top: a column at a time into one row of flags
        # (what np.hstack and a reduction along each row count, without either), the columns
        # that never reach theirs left out.
        clipped = np.zeros(len(result.units[0].tau), bool)
        first = 0
        for u in result.units:
            for j in range(u.tau.shape[1]):
                if can_clip[first + j]:
                    clipped |= np.abs(u.tau[:, j]) >= top[first + j]
            first += u.tau.shape[1]
        return int(np.count_nonzero(clipped))


def verdict(result: SimulationResult, supervisor: Supervisor,
            reductions: list[LogReductions] | None = None) -> dict:
    """``summary.json``'s ``supervisor`` entry of an as-fast run: the first rule a real run
    would have stopped on (``"none"``: it would have run to the end) and the clipped periods.
    ``reductions``: each unit's :func:`log_reductions` of this result, when the caller has
    them (a sweep's worker, whose summary reads them too); the same entry either way."""
    stop = first_violation(result, supervisor, reductions)
    mirror = result.mirror_stop  # the logs end before it: any rule above came first
    if stop is None and mirror is not None:
        stop = Stop(mirror["rule"], mirror["time_s"], mirror["detail"])
    entry = {"rule": "none"} if stop is None else {
        "rule": stop.rule, "time_s": stop.time, "detail": stop.detail, "exit_code": stop.code}
    return {**entry, "saturated_periods": saturated_periods(result, supervisor, reductions)}
