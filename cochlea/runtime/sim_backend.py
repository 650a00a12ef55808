"""The simulated robot as a backend of the real-time loop: the plant model advanced one control
period per write, on the same kernels as the as-fast simulation, measured and driven as the
as-fast simulation measures and drives it."""

from __future__ import annotations

import time

import numpy as np

from ..errors import CochleaError
from ..sim.compiled import period_kernels
from ..sim.scenario import Plant
from ..sim.setup import (
    ENCODER_STREAM,
    JITTER_STREAM,
    MeasurementGrid,
    UnitSetup,
    disturbance_rng,
    uniform_integers,
)

#: Normals drawn at a time while skipping the earlier units' noise (bounded memory).
_SKIP_CHUNK = 1 << 16


class SimBackend:
    """The plant model advanced one control period per write: the default backend.

    Real time comes from the loop's deadlines; the plant itself integrates each period with the
    scenario's RK4 sub-steps, the same kernel as the as-fast-as-possible simulation.

    ``read`` reports the state as the as-fast run's controller sees it (period ``k`` is the
    ``k``-th read): the true state ``plant.delay_periods`` reads ago (plus, with
    ``delay_jitter_periods``, that read's jitter; the initial state before that), plus the
    plant's Gaussian noise and its whole encoder counts of noise (``encoder_noise_counts``),
    then on the units' measurement grid (encoder and velocity counts, ``UnitSetup.quantum``).
    The noise is the as-fast run's, number for number: drawn from ``plant.seed``, unit after
    unit, each unit's ``steps`` periods in turn, so ``steps`` (the run's periods) is needed
    when there is noise; past them the draws go on. The jitter and the encoder counts have
    their own streams of the seed, drawn one read at a time as the as-fast run draws them up
    front (:func:`cochlea.sim.setup.delay_ages`, :func:`cochlea.sim.setup.encoder_noise`).
    ``write`` applies the drives' effort grid (``UnitSetup.effort_grid``) and gives the plant
    the applied effort times the unit's ``torque_scale``. Without ``plant`` there is no delay
    and no noise; the grids come with the setups. ``read`` and ``write`` allocate nothing.
    """

    name = "sim"
    #: The simulated drives measure no current (the applied effort is logged as ``tau``).
    joint_current_A = None

    def __init__(self, setups: list[UnitSetup], period: float, substeps: int,
                 kernels: str = "c", plant: Plant | None = None, steps: int | None = None):
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
            if u.drive is not None:  # dry friction, or the gear's drive: a last input
                f.inputs[5][...] = u.drive
            f.inputs[0][...] = u.plant_x0  # with the gearbox [q, qd, theta, theta_dot]
            self._steps.append(f)
            self._grids.append(u.effort_grid)
            n = u.plant_model.nq
            self._spans.append((n, slice(start, start + n),
                                slice(self.nq + start, self.nq + start + n)))
            start += n
        self._measurement_model(plant or Plant(), steps)
        self.enabled = False
        self.last_io_time_s = 0.0
        self._read_time = 0.0

    def _measurement_model(self, plant: Plant, steps: int | None) -> None:
        """Everything ``read`` needs, allocated once: the delay line of true states, the
        noise streams, the measurement grid in the system's layout."""
        nx = 2 * self.nq
        self.delay = plant.delay_periods
        self.jitter = plant.delay_jitter_periods
        # True states, a ring of the oldest delay + 1.
        self._history = np.empty((self.delay + self.jitter + 1, nx))
        self._jitter = None  # (generator, one draw) of the jittering delay
        if self.jitter:
            self._jitter = (disturbance_rng(plant, JITTER_STREAM), np.empty(1))
        # Whole encoder counts of position noise: (generator, one row of the system's joints,
        # per unit its joints' counts times their encoder quantum).
        self._counts = None
        if plant.encoder_noise_counts:
            self._counts = (disturbance_rng(plant, ENCODER_STREAM), np.empty(self.nq),
                            plant.encoder_noise_counts,
                            [(u.quantum[:n], np.empty(n))
                             for u, (n, _, _) in zip(self.units, self._spans)])
        #: The plant's true state at the last read (Backend.true_state), before the delay, the
        #: noise and the grid: the loop logs it beside the measurement.
        self.true_state = np.zeros(nx)
        self._reads = 0
        # Unit by unit, as the as-fast run draws them: 2n normals per period and unit.
        self._noise = []  # per unit: (generator, std [q..., qd...], buffer) or None
        if plant.noise_q_std or plant.noise_qd_std:
            if steps is None and len(self.units) > 1:
                raise CochleaError("the simulated robot draws its measurement noise as the "
                                   "as-fast run does, unit after unit over the whole run: give "
                                   "SimBackend the run's number of periods (steps)")
            skip = 0
            for u in self.units:
                n = u.plant_model.nq
                rng = np.random.default_rng(plant.seed)
                left = skip
                while left:  # the earlier units' periods, drawn and dropped
                    rng.standard_normal(min(left, _SKIP_CHUNK))
                    left -= min(left, _SKIP_CHUNK)
                std = np.concatenate([np.full(n, plant.noise_q_std),
                                      np.full(n, plant.noise_qd_std)])
                self._noise.append((rng, std, np.empty(2 * n)))
                skip += 2 * n * (steps or 0)
        # The grid where a unit has one; a zero quantum keeps a coordinate continuous.
        quantum, offset = np.zeros(nx), np.zeros(nx)
        for u, (n, q_span, qd_span) in zip(self.units, self._spans):
            if u.quantum is not None:
                for span, part in ((q_span, slice(0, n)), (qd_span, slice(n, 2 * n))):
                    quantum[span] = u.quantum[part]
                    offset[span] = u.grid_offset[part]
        self._grid = MeasurementGrid(quantum, offset) if (quantum > 0).any() else None

    def enable(self) -> None:
        self.enabled = True

    def read(self, x: np.ndarray) -> bool:
        t0 = time.perf_counter()
        ring = len(self._history)
        now = self._history[self._reads % ring]
        for f, (n, q_span, qd_span) in zip(self._steps, self._spans):
            state = f.inputs[0]  # the encoder is on the link: [q, qd] of the plant's state
            now[q_span] = state[:n]
            now[qd_span] = state[n:2 * n]
        self.true_state[:] = now
        age = self.delay
        if self._jitter is not None:
            rng, draw = self._jitter
            rng.random(out=draw)
            age += int(uniform_integers(draw, 0, self.jitter)[0])
        x[:] = self._history[max(self._reads - age, 0) % ring]
        self._reads += 1
        if self._counts is not None:  # this read's counts, every joint of the system
            rng, row, counts, units = self._counts
            rng.random(out=row)
            uniform_integers(row, -counts, counts)
            for (quantum, counted), (_, q_span, _) in zip(units, self._spans):
                np.multiply(row[q_span], quantum, out=counted)
        for i, (n, q_span, qd_span) in enumerate(self._spans):
            # As the as-fast run's noise array: the Gaussian draw plus the counts, then added.
            counted = None if self._counts is None else self._counts[3][i][1]
            if self._noise:
                rng, std, draw = self._noise[i]
                rng.standard_normal(out=draw)
                np.multiply(std, draw, out=draw)
                if counted is not None:
                    draw[:n] += counted
                x[q_span] += draw[:n]
                x[qd_span] += draw[n:]
            elif counted is not None:
                x[q_span] += counted
        if self._grid is not None:  # in encoder and velocity counts, as the C driver
            self._grid.apply(x)
        self._read_time = time.perf_counter() - t0
        return True

    def write(self, tau: np.ndarray) -> bool:
        """Advance the plant one period under ``tau``. With the drives' effort grid (scenario
        key ``current_quantisation``) the efforts applied are rounded to whole current LSBs and
        saturated, as the as-fast run applies them, and written back into ``tau`` so the loop
        logs them."""
        t0 = time.perf_counter()
        for f, (_, q_span, _), grid, u in zip(self._steps, self._spans, self._grids,
                                              self.units):
            applied = f.inputs[1]
            if self.enabled:
                applied[:] = tau[q_span]
                if grid is not None:
                    grid.apply(applied)
                    tau[q_span] = applied
                if u.torque_scale is not None:  # the motor's torque-constant error
                    np.multiply(u.torque_scale, applied, out=applied)
            else:
                applied[:] = 0.0
            f()
            f.inputs[0][:] = f.outputs[0]
        self.last_io_time_s = self._read_time + time.perf_counter() - t0
        return True

    def disable(self) -> None:
        self.enabled = False
