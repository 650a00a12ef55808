"""What a run leaves in memory: one log per controlled unit, one row per control period (SI).

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


@dataclass
class UnitLog:
    """The log of one unit, one row per control period (SI)."""

    name: str
    space: str
    q: np.ndarray  # (N, n) true joint positions at the start of each period
    qd: np.ndarray
    desired: np.ndarray  # (N, nd) desired sample (joint or task space)
    desired_dot: np.ndarray
    errors: np.ndarray  # (N, 2 blocks) controller error signals
    tau: np.ndarray  # (N, n) commanded torque / force
    p_hat: np.ndarray  # (N, n_p) estimate used in the period
    x: np.ndarray  # (N, m) tool / task pose of the true state
    setup: UnitSetup = field(repr=False)
    #: (N, n) motor current measured by the drives (A, at the joint's sign); None when the run
    #: measured none (simulated runs).
    current: np.ndarray | None = None

    @property
    def tracking_error(self) -> np.ndarray:
        """Desired minus actual on the tracked coordinates (angles wrapped), SI."""
        n = self.setup.controller.n_desired
        block = self.errors[:, :n]
        # g defines e_g = x - x_d; report every controller as desired - actual.
        return -block if self.setup.controller.kind == "g" else block

    @property
    def tracked_names(self) -> tuple[str, ...]:
        if self.space == "joint":
            return tuple(j.name for j in self.setup.controller_model.joints)
        return self.setup.task_names

    @property
    def tracked_units(self) -> tuple[str, ...]:
        return self.setup.joint_units if self.space == "joint" else self.setup.task_units


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

    def unit(self, name: str) -> UnitLog:
        return next(u for u in self.units if u.name == name)

    @property
    def periods(self) -> int:
        return len(self.time)

    def rows(self, start: int, stop: int, step: int = 1) -> SimulationResult:
        """Periods ``start:stop:step`` as a result of their own (views, no copies)."""
        part = slice(start, stop, step)
        units = [dataclasses.replace(u, **{name: getattr(u, name)[part] for name in _ROW_FIELDS
                                           + (("current",) if u.current is not None else ())})
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
        return part
