"""The safety supervisor of a run: every rule that stops the motors, and the exit code of each.

Each period the loop asks :meth:`Supervisor.check_state` about the measured state and
:meth:`Supervisor.check_command` about the command and the estimates; the first rule broken
returns a :class:`Stop`, and the loop then commands zero effort and disables the drives in the
same period. The checks allocate nothing unless a rule is broken.
"""

from __future__ import annotations

import math
import signal
from dataclasses import dataclass

import numpy as np

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
    """All finite, without a temporary array (a NaN or infinity makes the sum of squares so)."""
    return math.isfinite(float(v @ v))


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.4g}" for x in np.asarray(v).ravel()) + "]"


def _show(value: float, unit: str) -> str:
    return f"{math.degrees(value):.2f} deg" if unit == "rad" else f"{value:.4f} m"


def build_supervisor(setups: list[UnitSetup], keep_out_radius: float | None,
                     watchdog_misses: int = 20, watchdog_errors: int = 5,
                     kernels: str = "c", substeps: int = 1) -> Supervisor:
    """Limits from the descriptions of every unit's joints; the keep-out circle (None: none)
    around each unit's centre (serial: the cochlea centre; parallel: the slider pivot S, which
    moves with d1) for each of its tool points, in joint-space runs as in task-space ones: the
    circle protects what is around the centre whatever coordinates the controller tracks."""
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
    fks, slices, start = [], [], 0
    for u in setups:
        fks.append(period_kernels(u, substeps, kernels)[2])
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


def first_violation(result: SimulationResult, supervisor: Supervisor) -> Stop | None:
    """The rule a real-time run of the same periods would have stopped on, and when: the
    supervisor's checks applied to a logged run (an as-fast simulation, which does not stop).

    Period k is checked as the loop checks it: the state it measures at its start (positions,
    velocities, keep-out circle, finite), then the command and the estimate it produces for
    period k + 1. The loop sees the robot through its measurement, so the state checked is the
    one the loop would read: the logged measured state, what the controller saw (delayed,
    noisy, on the encoder and velocity-register grids where the plant has them;
    :func:`measured_states`). The rows are screened at once with numpy; the first flagged row
    is then passed through the supervisor itself, so the rule and its message are the loop's
    own.
    """
    logs = result.units
    rows = len(result.time)
    if rows == 0:
        return None
    q, qd = measured_states(result)
    tau = np.hstack([u.tau for u in logs])
    # The estimate each period hands on: the next row's (the last row's own at the end).
    estimates = [np.vstack([u.p_hat[1:], u.p_hat[-1:]]) for u in logs]
    L = supervisor.limits
    if _nothing_flagged(result, supervisor, q, qd, tau, estimates):
        return None
    with np.errstate(invalid="ignore", over="ignore"):
        flagged = ~np.isfinite(q).all(axis=1) | ~np.isfinite(qd).all(axis=1)
        flagged |= ((q < L.position_lo) | (q > L.position_hi)).any(axis=1)
        flagged |= (np.abs(qd) > L.velocity).any(axis=1)
        if L.keep_out_radius is not None:
            # Screened on the logged pose of the measured state, which the supervisor's own
            # kernel may compute a last bit differently: flagged with a margin, confirmed
            # exactly below.
            margin = _KEEP_OUT_SCREEN
            for u in logs:
                s = u.setup
                for _, (iu, iv) in s.tool_points:
                    if s.moving_centre_joint is None:
                        cu, cv = s.centre
                    else:
                        cu, cv = 0.0, u.q[:, s.moving_centre_joint]
                    pose = u.pose  # computed now if the run did not log it
                    flagged |= np.hypot(pose[:, iu] - cu, pose[:, iv] - cv) < \
                        L.keep_out_radius + margin
        flagged |= ~np.isfinite(tau).all(axis=1)
        for p, bound in zip(estimates, supervisor.bounds):
            square = np.einsum("ij,ij->i", p, p)
            flagged |= ~np.isfinite(square) | (square > (bound * (1 + 1e-9)) ** 2)
    n = q.shape[1]
    for k in np.flatnonzero(flagged):
        t = float(result.time[k])
        x = np.concatenate([q[k], qd[k]])
        stop = supervisor.check_state(t, x, x[:n], x[n:])
        if stop is None:
            stop = supervisor.check_command(t, tau[k].copy(), [p[k] for p in estimates])
        if stop is not None:
            return stop
    return None


def _nothing_flagged(result: SimulationResult, supervisor: Supervisor, q: np.ndarray,
                     qd: np.ndarray, tau: np.ndarray, estimates: list[np.ndarray]) -> bool:
    """Whether the row-by-row screen of :func:`first_violation` would flag no row, from
    whole-run reductions (a column's extremes, a sum): the common case, a run that breaks no
    rule, for a fraction of the screen's time (a sweep judges every sample). Each test here
    holding implies its screen flags nothing; one that fails sends the run through the screen
    as before, so the verdict is the same either way."""
    L = supervisor.limits
    with np.errstate(invalid="ignore", over="ignore"):
        # A NaN or an infinity anywhere makes the sum non-finite (so does a sum that
        # overflows, which the screen then settles).
        if not all(np.isfinite(a.sum()) for a in (q, qd, tau)):
            return False
        if not (_within(q, L.position_lo, L.position_hi)
                and _within(qd, -L.velocity, L.velocity)):  # |qd| > v is qd outside [-v, v]
            return False
        for p, bound in zip(estimates, supervisor.bounds):
            largest = np.einsum("ij,ij->i", p, p).max(initial=0.0)
            if not largest <= (bound * (1 + 1e-9)) ** 2:  # NaN fails too
                return False
        if L.keep_out_radius is not None:
            # No pose near the circle at all: the screen flags none. The pose of the measured
            # state where the run has it; else (an as-fast run measured through a delay or a
            # grid, not yet computed) the true pose, with a margin no grid rounding crosses: each
            # measured state is a delayed true one, a fraction of a count away. With noise,
            # the measured pose itself.
            noisy = result.scenario.plant.noise_q_std > 0
            for u in result.units:
                s = u.setup
                if u.x is None and u.has_true_state and not noisy:
                    pose, joints, margin = u.true_x, u.true_q, _GRID_SCREEN
                else:
                    pose, joints, margin = u.pose, u.q, _KEEP_OUT_SCREEN
                for _, (iu, iv) in s.tool_points:
                    if s.moving_centre_joint is None:
                        cu, cv = s.centre
                    else:
                        cu, cv = 0.0, joints[:, s.moving_centre_joint]
                    # Squared, without hypot's cost; the relative slack covers its rounding.
                    du, dv = pose[:, iu] - cu, pose[:, iv] - cv
                    nearest = (du * du + dv * dv).min(initial=np.inf)
                    if not nearest >= ((L.keep_out_radius + margin) * (1 + 1e-9)) ** 2:
                        return False
    return True


def _within(a: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Every element of ``a`` (rows of columns) within its column's ``[lo, hi]``: the whole
    array's extremes against the tightest bounds first (no temporaries; the common case where
    every joint has the same limits), else column by column. A NaN fails both."""
    if a.min() >= lo.max() and a.max() <= hi.min():
        return True
    return bool((a.min(axis=0) >= lo).all() and (a.max(axis=0) <= hi).all())


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


def saturated_periods(result: SimulationResult, supervisor: Supervisor) -> int:
    """Periods whose command was clipped to a joint's effort limit or, with current
    quantisation, saturated by its drive (the logs hold the applied command, so a clipped one
    sits exactly on the largest effort the joint can get: its limit, or its drive's
    :attr:`~cochlea.sim.setup.EffortGrid.top`, the Current Limit's effort or the grid level
    the limit rounds to)."""
    tau = np.hstack([u.tau for u in result.units])
    top = supervisor.limits.effort
    if any(u.setup.effort_grid is not None for u in result.units):
        top = np.minimum(top, np.concatenate([
            u.setup.effort_limit if u.setup.effort_grid is None else u.setup.effort_grid.top
            for u in result.units]))
    with np.errstate(invalid="ignore"):
        # Most runs never reach a limit: the columns' extremes show it without a row count.
        if len(tau) == 0 or np.abs(tau).max() < top.min():  # NaN goes on to the count
            return 0
        return int(np.sum((np.abs(tau) >= top).any(axis=1)))


def verdict(result: SimulationResult, supervisor: Supervisor) -> dict:
    """``summary.json``'s ``supervisor`` entry of an as-fast run: the first rule a real run
    would have stopped on (``"none"``: it would have run to the end) and the clipped periods."""
    stop = first_violation(result, supervisor)
    mirror = result.mirror_stop  # the logs end before it: any rule above came first
    if stop is None and mirror is not None:
        stop = Stop(mirror["rule"], mirror["time_s"], mirror["detail"])
    entry = {"rule": "none"} if stop is None else {
        "rule": stop.rule, "time_s": stop.time, "detail": stop.detail, "exit_code": stop.code}
    return {**entry, "saturated_periods": saturated_periods(result, supervisor)}
