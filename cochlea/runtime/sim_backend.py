"""The simulated robot as a backend of the real-time loop: the plant model advanced one control
period per write, on the same kernels as the as-fast simulation."""

from __future__ import annotations

import time

import numpy as np

from ..sim.compiled import period_kernels
from ..sim.setup import UnitSetup


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
        self._grids = []  # per unit: its drives' effort grid, or None
        self._spans = []  # per unit: its joints' slice of q and of qd in the system state
        start = 0
        for u in setups:
            f = period_kernels(u, substeps, kernels)[1]
            f.inputs[2][...] = u.plant_params
            f.inputs[3][...] = u.friction
            f.inputs[4][...] = period
            if u.coulomb is not None:  # the plant with dry friction has it as a last input
                f.inputs[5][...] = u.coulomb
            f.inputs[0][...] = u.x0
            self._steps.append(f)
            self._grids.append(u.effort_grid)
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
        """Advance the plant one period under ``tau``. With the drives' effort grid (scenario
        key ``current_quantisation``) the efforts applied are rounded to whole current LSBs and
        saturated, as the as-fast run applies them, and written back into ``tau`` so the loop
        logs them."""
        t0 = time.perf_counter()
        for f, (_, q_span, _), grid in zip(self._steps, self._spans, self._grids):
            applied = f.inputs[1]
            if self.enabled:
                applied[:] = tau[q_span]
                if grid is not None:
                    grid.apply(applied)
                    tau[q_span] = applied
            else:
                applied[:] = 0.0
            f()
            f.inputs[0][:] = f.outputs[0]
        self.last_io_time_s = self._read_time + time.perf_counter() - t0
        return True

    def disable(self) -> None:
        self.enabled = False
