"""What a run leaves in memory: one log per controlled unit, one row per control period (SI).

Every log holds the *measured* state, what the controller saw (``q``, ``qd`` and the pose
``x`` through them: delayed, noisy, on the encoder and velocity-register grids where the plant
has them), as a hardware run has it; a simulated run (as fast as possible, or the real-time
loop on the sim backend) also holds the plant's *true* state (``true_q``, ``true_qd``,
``true_x``), which a hardware run does not know (None). The tracking error a run is judged on
(:attr:`UnitLog.tracking_error`) is the true one where the run has it.

The as-fast simulation (CasADi or C) and the real-time loop both return a
:class:`SimulationResult`; the report, the CSV and the figures read only this, a chunk of
periods at a time (:meth:`SimulationResult.chunks`), so a long run streamed to disk
(:class:`StreamedResult`) is reported in memory that does not grow with its length.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .scenario import Scenario
from .setup import UnitSetup

#: Periods per chunk when a result is read in pieces (a few MB of rows).
CHUNK_ROWS = 1 << 13
_ROW_FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x")
#: The true state's fields, None in a run that does not know it (hardware).
_TRUE_FIELDS = ("true_q", "true_qd", "true_x")


@dataclass
class UnitLog:
    """The log of one unit, one row per control period (SI)."""

    name: str
    space: str
    q: np.ndarray  # (N, n) measured joint positions: what the controller saw in each period
    qd: np.ndarray  # (N, n) measured joint velocities
    desired: np.ndarray  # (N, nd) desired sample (joint or task space)
    desired_dot: np.ndarray
    errors: np.ndarray  # (N, 2 blocks) controller error signals (of the measured state)
    tau: np.ndarray  # (N, n) commanded torque / force
    p_hat: np.ndarray  # (N, n_p) estimate used in the period
    #: (N, m) tool / task pose of the measured joint positions; None until asked for when a
    #: simulated run measured something else than the true state (see :attr:`pose`).
    x: np.ndarray | None
    setup: UnitSetup = field(repr=False)
    #: (N, n) motor current measured by the drives (A, at the joint's sign); None when the run
    #: measured none (simulated runs).
    current: np.ndarray | None = None
    #: The plant's true state at the start of each period and its pose, (N, n), (N, n), (N, m);
    #: None when the run does not know it (a hardware run).
    true_q: np.ndarray | None = None
    true_qd: np.ndarray | None = None
    true_x: np.ndarray | None = None
    #: What the C driver gathered of these rows while it ran (:class:`Gathered`), for the
    #: verdict and the summary; None where no driver did, and once the rows are cut.
    gathered: Gathered | None = field(default=None, repr=False)

    @property
    def has_true_state(self) -> bool:
        return self.true_q is not None

    @property
    def pose(self) -> np.ndarray:
        """The pose of the measured joint positions (``x``), computed from ``q`` the first
        time it is asked for when the run did not log it (an as-fast run that measured
        through a delay, noise or a grid: a sweep judging its samples seldom needs it)."""
        if self.x is None:
            rows = len(self.q)
            self.x = np.array(self.setup.fk_world.map(rows)(self.q.T)).T if rows else \
                np.zeros((0, len(self.setup.task_names)))
        return self.x

    @property
    def measured_tracking_error(self) -> np.ndarray:
        """Desired minus measured on the tracked coordinates (angles wrapped), SI: the error
        the controller computed from what it saw."""
        n = self.setup.controller.n_desired
        block = self.errors[:, :n]
        # g defines e_g = x - x_d; report every controller as desired - actual.
        return -block if self.setup.controller.kind == "g" else block

    @property
    def true_tracking_error(self) -> np.ndarray | None:
        """Desired minus the plant's true state on the tracked coordinates (task angles
        wrapped to (-pi, pi] as the controllers wrap them), SI; None without a true state."""
        if self.true_q is None:
            return None
        actual = self.true_q if self.space == "joint" else self.true_x
        e = self.desired - actual
        if self.space == "task":
            for i in self.setup.task_angles:
                e[:, i] = np.arctan2(np.sin(e[:, i]), np.cos(e[:, i]))
        return e

    @property
    def tracking_error(self) -> np.ndarray:
        """The error a run is judged on: :attr:`true_tracking_error` where the run knows the
        true state (simulation), else :attr:`measured_tracking_error` (hardware)."""
        true = self.true_tracking_error
        return self.measured_tracking_error if true is None else true

    @property
    def tracked_names(self) -> tuple[str, ...]:
        if self.space == "joint":
            return tuple(j.name for j in self.setup.controller_model.joints)
        return self.setup.task_names

    @property
    def tracked_units(self) -> tuple[str, ...]:
        return self.setup.joint_units if self.space == "joint" else self.setup.task_units


@dataclass(frozen=True)
class Gathered:
    """A C driver's :class:`~cochlea.kernels.library.LoopReductions` and the log arrays they
    describe, made read-only when gathered: :meth:`of` hands them out only while a log still
    holds those very arrays (an array put in their place, a part of the log, is read again)."""

    reductions: object  # cochlea.kernels.library.LoopReductions
    q: np.ndarray
    qd: np.ndarray
    tau: np.ndarray
    p_hat: np.ndarray
    true_x: np.ndarray  # the pose log the keep-out approach is of

    def of(self, u: UnitLog):
        """The reductions, when ``u`` still holds the arrays they describe, else None."""
        if (u.q is self.q and u.qd is self.qd and u.tau is self.tau and u.p_hat is self.p_hat
                and u.true_x is self.true_x and self.reductions.rows == len(u.q)):
            return self.reductions
        return None


def simulated_log(u: UnitSetup, space: str, states: np.ndarray, measured: np.ndarray,
                  pose: np.ndarray, desired: np.ndarray, desired_dot: np.ndarray,
                  errors: np.ndarray, tau: np.ndarray, p_hat: np.ndarray,
                  gathered=None) -> UnitLog:
    """A simulated unit's log: ``states`` the plant's true ``[q, qd]`` of every period and
    ``pose`` its pose, ``measured`` what the controller saw (the same array when the plant
    measures exactly: no delay, noise or grid), whose pose is computed when first asked for
    (:attr:`UnitLog.pose`); ``gathered``: what the C driver gathered of these rows."""
    n = u.controller_model.nq
    seen_pose = pose if measured is states else None
    q, qd, true_q, true_qd = measured[:, :n], measured[:, n:], states[:, :n], states[:, n:]
    if gathered is not None:
        if gathered.rows != len(measured):
            gathered = None
        else:  # what they describe cannot change under them (the true state may be it)
            for array in (q, qd, tau, p_hat, true_q, true_qd, pose):
                array.flags.writeable = False
            gathered = Gathered(gathered, q, qd, tau, p_hat, pose)
    return UnitLog(u.name, space, q, qd, desired, desired_dot, errors, tau, p_hat, seen_pose, u,
                   true_q=true_q, true_qd=true_qd, true_x=pose, gathered=gathered)


def truncate(logs: list[UnitLog], rows: int) -> None:
    """Every log cut to its first ``rows`` periods (a run that diverged: every unit's log ends
    where the first one diverged)."""
    for u in logs:
        for key in _ROW_FIELDS + _TRUE_FIELDS + ("current",):
            if getattr(u, key) is not None:
                setattr(u, key, getattr(u, key)[:rows])


@dataclass
class SimulationResult:
    scenario: Scenario
    time: np.ndarray  # (N,) s
    units: list[UnitLog]
    diverged: dict[str, float] = field(default_factory=dict)  # unit -> time (s) it diverged
    #: Real-time runs: per-period timing arrays (s) by name, and how the run stopped.
    timing: dict[str, np.ndarray] | None = None
    stop: dict | None = None
    #: As-fast runs: the rule a real run's supervisor would have stopped on, if any (see
    #: :func:`cochlea.runtime.supervisor.verdict`).
    supervisor: dict | None = None
    #: The kernels the run actually used (:class:`cochlea.sim.compiled.KernelChoice`'s
    #: ``summary()``: ``used`` "c" with its ``library``, or "casadi" with the ``reason`` when
    #: C was asked for and could not run it), or None where nobody recorded it.
    kernels: dict | None = None
    #: Where the desired path came from when not the scenario's formulas (``cochlea-run
    #: --desired-topic``: the topic, the message's stamp and points), else None.
    desired_source: dict | None = None
    #: As-fast runs with ``mirror = "measured"``: the safe stop a follower's rule made (its
    #: pose out of reach or not finite; ``rule``, ``time_s``, ``detail``): the logs end just
    #: before that period, as a real run's would; None: none.
    mirror_stop: dict | None = None

    def unit(self, name: str) -> UnitLog:
        return next(u for u in self.units if u.name == name)

    @property
    def periods(self) -> int:
        return len(self.time)

    def rows(self, start: int, stop: int, step: int = 1) -> SimulationResult:
        """Periods ``start:stop:step`` as a result of their own (views, no copies)."""
        part = slice(start, stop, step)
        units = [dataclasses.replace(u, gathered=None,
                                     **{name: getattr(u, name)[part] for name in _ROW_FIELDS
                                        + _TRUE_FIELDS + ("current",)
                                        if getattr(u, name) is not None})
                 for u in self.units]
        timing = None if self.timing is None else {k: v[part] for k, v in self.timing.items()}
        return dataclasses.replace(self, time=self.time[part], units=units, timing=timing)

    def chunks(self, size: int | None = None):
        """The run in order, ``size`` periods at a time (default :data:`CHUNK_ROWS`)."""
        size = size or CHUNK_ROWS
        for start in range(0, self.periods, size):
            yield self.rows(start, min(start + size, self.periods))

    def decimated(self, points: int) -> SimulationResult:
        """At most about ``points`` periods, evenly spaced (every period of a short run), for
        figures: a line of a million points shows nothing more than one of twenty thousand."""
        step = max(1, math.ceil(self.periods / max(points, 1)))
        return self.rows(0, self.periods, step)


class StreamedResult(SimulationResult):
    """A run kept on disk, read back a chunk of periods at a time: ``units`` and ``timing``
    describe the columns but hold no rows (``time`` is empty); :meth:`rows` reads periods
    through ``read(start, stop, step)``, which returns them as an in-memory result."""

    def __init__(self, scenario: Scenario, units: list[UnitLog], periods: int, read,
                 timing: dict | None = None, stop: dict | None = None):
        super().__init__(scenario, np.zeros(0), units, timing=timing, stop=stop)
        self._periods, self._read = periods, read

    @property
    def periods(self) -> int:
        return self._periods

    def rows(self, start: int, stop: int, step: int = 1) -> SimulationResult:
        stop = min(stop, self._periods)
        part = self._read(start, max(start, stop), step)
        part.stop, part.diverged, part.supervisor = self.stop, self.diverged, self.supervisor
        part.mirror_stop = self.mirror_stop
        return part
