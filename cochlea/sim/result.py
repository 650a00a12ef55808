"""What a run leaves in memory: one log per controlled unit, one row per control period (SI).

The as-fast simulation (CasADi or C) and the real-time loop both return a
:class:`SimulationResult`; the report, the CSV and the figures read only this.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .scenario import Scenario
from .setup import UnitSetup


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
