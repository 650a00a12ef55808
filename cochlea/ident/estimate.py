"""Base parameters from logged motion and effort: filtering, the stacked regressor, least squares.

The steps, as a robotics researcher runs them on a real arm (Gautier and Khalil; Swevers et al.):

1. **Filter** each log's positions and efforts with the same zero-phase low-pass Butterworth
   filter (``scipy.signal.filtfilt``, order :data:`FILTER_ORDER`, cut-off ``cutoff_hz``): the
   same filter on both sides keeps torque and motion in phase and equally attenuated.
   The efforts are first read ``effort_lag`` control periods earlier (default half a period:
   each command is held over its period; see :data:`DEFAULT_EFFORT_LAG`; ``auto``:
   :func:`estimate_lag`). A log recorded over a hardware backend is first placed at the
   times its timing columns record (:data:`SAMPLE_TIMES`): positions interpolated back onto
   the grid from their reads, each command held from its write.
2. **Differentiate** the filtered positions twice (central differences) for velocity and
   acceleration. The logged velocity is not used: on the motors it is the Present Velocity
   register, 0.024 rad/s a count, coarser than what differentiating the 1.5 mrad encoder
   counts gives after the filter, and the embedded and simulated logs then all go through
   one path.
3. **Drop the ends** the filter spoils (:func:`edge_rows`) and **decimate** (every
   ``decimate``-th row: the filtered signals hold nothing above the cut-off, and residuals
   of nearby rows would otherwise be correlated, making the standard errors optimistic).
4. **Stack** the base regressor ``Y(q, qd, qd, qdd)`` of the model built with
   ``parameterisation="base", actuators="all"``, so ``tau = Y beta`` holds row by row with the
   armature and the viscous and Coulomb friction the description declares.
4b. **Parallel filtering** (``parallel_cutoff_hz``, default :data:`DEFAULT_PARALLEL_CUTOFF_HZ`):
   the same zero-phase low-pass again on every column of ``Y`` and on the efforts, then a
   second decimation. ``tau = Y beta`` is linear in beta, so the filtered equation holds
   exactly; the cut-off can go down to just above the excitation's band, which the states'
   filter cannot (Y is nonlinear in the states), and removes what double differentiation of
   encoder counts leaves. Samples within ``guard_s`` of one where a joint moves slower than
   ``min_speed`` (a stuck joint: static friction no term predicts) are left out.
5. **Solve** ordinary least squares, then weighted least squares with one weight per joint,
   ``1 / sigma_j`` from the OLS residuals of that joint (the classic scheme: the joints'
   efforts differ in size and noise). Each estimate's standard error is
   ``sqrt(diag(s^2 (W^T W)^-1))`` of the (weighted) regressor with ``s^2`` the residual
   variance; the relative standard error is it over ``|beta|`` in %.
6. **Validate** on data held out from the fit: the effort the estimate predicts against the
   one logged, per joint, as an NRMS error: ``RMS(tau - Y beta) / RMS(tau)`` in %.

With motor current in the logs, joints whose current-to-torque line is unknown (a placeholder
fit) are fitted with it (:mod:`cochlea.ident.current`): their logged effort is only what the
placeholder line promised, so their rows become ``Y_j beta - a_j I_j - b_j s_j = 0`` and the
measured current goes through the effort's lag (one period less: Present Current is read at
the start of the period that follows the command), filter and parallel filter.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

# scipy.signal and scipy.optimize are imported by the functions that use them: at the top they
# cost every cochlea-identify start (a --help, a refused file) some 2 s.
from ..errors import CochleaError
from ..robots import RobotModel
from .current import CurrentFitError, Line, offset_shape
from .logs import TIMING, LogError, RunLog

#: Butterworth order of the zero-phase filter (filtfilt doubles it).
FILTER_ORDER = 4
#: Default cut-off of the filter (Hz): above a Fourier excitation's highest harmonic (a few
#: Hz on these robots), far below the 1 kHz loop's noise.
DEFAULT_CUTOFF_HZ = 20.0
#: Default lag of the logged effort behind the motion it causes, in control periods: a command
#: is held over its period (zero-order hold), so on average it acts half a period after the
#: row's state was sampled. Measured on the simulated ideal plant: without the half period the
#: armature and first-moment estimates are biased by 2-7 %, with it below 1 %.
DEFAULT_EFFORT_LAG = 0.5
#: ``--effort-lag auto``: the lag that minimises the fit's residual (:func:`estimate_lag`).
AUTO = "auto"
#: The lags searched by :func:`estimate_lag` (control periods): a grid, then a bounded
#: search between the best point's neighbours to this tolerance. Three periods cover a
#: held command (0.5), a write at the end of a slow period and a period of bus delay.
LAG_GRID = np.arange(0.0, 3.0 + 1e-9, 0.25)
LAG_TOLERANCE = 0.01
#: The residual curve is refused as flat when its whole range over the grid changes the
#: residual's RMS by less than this fraction (the lag is then not observable in the data),
#: and as ambiguous when another local minimum further than :data:`LAG_SEPARATION` periods
#: from the best lies within :data:`LAG_AMBIGUOUS` of the curve's range above it.
LAG_FLAT = 1e-3
LAG_SEPARATION = 0.5
LAG_AMBIGUOUS = 0.1
#: ``--sample-times``: where a log's samples and commands are placed in time. ``logged``: at
#: the times its timing columns record (a period's start for the state it reads, the end of
#: its work for the command it writes); ``nominal``: on the grid ``time_s``; ``auto`` (the
#: default): logged for a log recorded over a hardware backend (one that carries measured
#: current and the timing columns), nominal otherwise (a simulated plant steps on the grid).
SAMPLE_TIMES = ("auto", "logged", "nominal")
LOGGED, NOMINAL = "logged", "nominal"
#: A period whose bus transfers (backend_io_s) took longer than this many periods means the
#: chain answered late: it was held up itself (on the shared machine the emulator loses the
#: processor for milliseconds and then catches up, or skips, plant time), so when it sampled
#: the state and applied the commands around then is unknown. Measured over the emulated
#: bus (five 8 s runs, bus time 0.3 ms typically, up to 4.8-8.2 ms): one run's stall in its
#: held-out part left 8.2 % NRMS, 1.3 % with its samples left out; at 3 periods up to 95 %
#: of the samples went on a loaded machine.
DEFAULT_MAX_BUS_PERIODS = 5.0
#: The reach of the parallel filter either side of a disturbance, in periods of its cut-off
#: (0.2 s at 3 Hz): where its impulse response (order 4, forwards and backwards) has decayed.
SLOW_GUARD_CYCLES = 0.6
#: Default cut-off of the parallel filter (Hz) on the regressor's columns and the efforts:
#: above an excitation's highest harmonic (a few Hz), and low enough that the encoder's
#: quantisation (1.5 mrad a count), twice differentiated, averages out. Measured on the
#: simulated serial arm (harmonics up to 1.5 Hz) with encoder-quantised positions: the
#: held-out NRMS is 12-18 % with the states' 20 Hz filter alone, 0.1-0.2 % with this one, and
#: the well-excited estimates' bias grows with the cut-off (errors-in-variables: 0.7 % at
#: 2 Hz, 1.6 % at 3 Hz, 1.9 % at 4 Hz). Set it just above the excitation's highest harmonic.
DEFAULT_PARALLEL_CUTOFF_HZ = 3.0
#: Default guard band (s) around a stuck sample: about the parallel filter's impulse response.
DEFAULT_GUARD_S = 0.1
#: Default fraction of each log held out for validation when no --validate log is given.
DEFAULT_HOLDOUT = 0.25
#: Largest condition number of the column-scaled regressor accepted: beyond it some base
#: parameter is hardly excited and its estimate is noise. Scaling each column to unit norm
#: makes the number independent of the parameters' units.
DEFAULT_MAX_CONDITION = 1e4
#: Default of ``min_speed`` (rad/s): five times the model's Coulomb smoothing (0.02 rad/s)
#: and above the filter's smearing of the friction's sign change at a reversal.
DEFAULT_MIN_SPEED = 0.1
#: A prismatic joint's speed threshold relative to a revolute joint's (m/s per rad/s): the
#: model's own ratio of Coulomb smoothings (0.0004 m/s against 0.02 rad/s).
PRISMATIC_SPEED_RATIO = 0.02
#: Rows of the regressor evaluated per CasADi map call (bounds the memory of one call).
CHUNK = 4096
#: The knee of a fitted current-to-torque line is searched on a grid of this many currents,
#: between those with these fractions of the fitted samples beyond them (a knee above
#: nearly every current leaves a and b one slope; one below nearly every current, the offset
#: one sign), and over this many sweeps when several lines are fitted.
KNEE_GRID = 41
KNEE_BEYOND_MIN, KNEE_BEYOND_MAX = 0.01, 0.95
KNEE_SWEEPS = 2
#: Relative tolerance of the knee's bounded search.
KNEE_TOLERANCE = 1e-4
#: The fit needs at least this many equations (a sample gives one per joint) per base
#: parameter, after the ends are dropped and the log decimated.
EQUATIONS_PER_PARAMETER = 10
#: Bounds of the options, refused up front (docs/identification.md, "Files and exit codes"):
#: a held-out part of at least 5 % (below it the validation may hold no moving sample) and at
#: most 95 %; decimation by at most 1000; cut-offs of at least 0.1 Hz (states) and 0.01 Hz
#: (parallel filtering; an excitation of 600 s periods has its 20th harmonic at 0.033 Hz).
MIN_HOLDOUT, MAX_HOLDOUT = 0.05, 0.95
MAX_DECIMATE = 1000
MIN_CUTOFF_HZ = 0.1
MIN_PARALLEL_CUTOFF_HZ = 0.01


class NotExcitedError(LogError):
    """The logs do not excite every base parameter: the regressor is (nearly) rank-deficient."""


@dataclass(frozen=True)
class Settings:
    cutoff_hz: float = DEFAULT_CUTOFF_HZ
    decimate: int | None = None  # None: rate / (10 cutoff)
    holdout: float = DEFAULT_HOLDOUT
    max_condition: float = DEFAULT_MAX_CONDITION
    #: Rows of a joint moving slower than this (rad/s, and a fiftieth of it in m/s at a
    #: prismatic joint) are left out: see :func:`moving_rows`.
    min_speed: float = DEFAULT_MIN_SPEED
    #: Control periods (a number), or AUTO: estimated from the data (estimate_lag).
    effort_lag: float | str = DEFAULT_EFFORT_LAG
    #: The low-pass on the regressor's columns and the efforts (Hz), None: none.
    parallel_cutoff_hz: float | None = DEFAULT_PARALLEL_CUTOFF_HZ
    #: Samples within this many seconds of a stuck one are left out (with parallel filtering).
    guard_s: float = DEFAULT_GUARD_S
    sample_times: str = SAMPLE_TIMES[0]
    #: With logged sample times, samples within the filters' reach (slow_guard_s) of a
    #: period whose bus transfers took longer than this many periods are left out (None:
    #: none).
    max_bus_periods: float | None = DEFAULT_MAX_BUS_PERIODS

    def slow_guard_s(self) -> float:
        """How far (s) a period of unknown timing spoils the filtered samples: the parallel
        filter's reach, :data:`SLOW_GUARD_CYCLES` of its cut-off, or ``guard_s`` without it."""
        if self.parallel_cutoff_hz is None:
            return self.guard_s
        return max(self.guard_s, SLOW_GUARD_CYCLES / self.parallel_cutoff_hz)

    def decimation(self, rate_hz: float) -> int:
        if self.decimate is not None:
            return self.decimate
        return max(1, int(rate_hz / (10.0 * self.cutoff_hz)))


def edge_rows(rate_hz: float, cutoff_hz: float) -> int:
    """Rows dropped at each end of a filtered log: two periods of the cut-off frequency, where
    filtfilt's start-up transient and the one-sided differences live."""
    return int(math.ceil(2.0 * rate_hz / cutoff_hz)) + 2


@dataclass(frozen=True)
class Samples:
    """Filtered, differentiated and decimated samples of one log (SI), with the base regressor
    filtered like the efforts (parallel filtering) and which samples to fit."""

    time: np.ndarray  # (N,)
    q: np.ndarray  # (N, n)
    qd: np.ndarray
    qdd: np.ndarray
    tau: np.ndarray
    Y: np.ndarray  # (N, n, n_b): tau[k] = Y[k] @ beta
    moving: np.ndarray  # (N,) bool: every joint moving, away from a stuck episode
    #: With lines to fit: the measured current (A), (N, n), lagged and filtered as the
    #: efforts are; ``shape_of(knees)`` the offset's shape s(I) for knees (A, per joint)
    #: through the same lag and filters, and ``shape`` the one of the knees last chosen.
    current: np.ndarray | None = None
    shape_of: object = None
    shape: np.ndarray | None = None

    def rows(self, part: slice) -> Samples:
        def cut(x):
            return None if x is None else x[part]

        of = self.shape_of
        return Samples(self.time[part], self.q[part], self.qd[part], self.qdd[part],
                       self.tau[part], self.Y[part], self.moving[part], cut(self.current),
                       None if of is None else (lambda knees: of(knees)[part]),
                       cut(self.shape))

    def with_knees(self, knees: np.ndarray) -> Samples:
        return dataclasses.replace(self, shape=self.shape_of(knees))


def _mapped_regressor(model: RobotModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
                      ) -> np.ndarray:
    """``Y(q, qd, qd, qdd)`` of every row, ``(N, n, n_b)``, with ``Y.map`` a chunk at a time
    (one CasADi call per chunk, not per sample)."""
    n, n_b = model.nq, len(model.parameters.names)
    total = len(q)
    out = np.empty((total, n, n_b))
    mapped = {}
    for start in range(0, total, CHUNK):
        stop = min(start + CHUNK, total)
        size = stop - start
        if size not in mapped:
            mapped[size] = model.Y.map(size)
        v = qd[start:stop].T
        block = np.array(mapped[size](q[start:stop].T, v, v, qdd[start:stop].T))
        out[start:stop] = block.reshape(n, size, n_b).transpose(1, 0, 2)
    return out


def _stuck(model: RobotModel, qd: np.ndarray, min_speed: float) -> np.ndarray:
    """Per row, whether some joint moves slower than ``min_speed`` (a fiftieth of it in m/s at
    a prismatic joint: the model's own ratio of Coulomb smoothings)."""
    limit = np.array([min_speed * (1.0 if j.type == "revolute" else PRISMATIC_SPEED_RATIO)
                      for j in model.joints])
    return (np.abs(qd) < limit).any(axis=1)


def _dilate(mask: np.ndarray, rows: int) -> np.ndarray:
    """``mask`` widened by ``rows`` on each side."""
    if rows <= 0 or not mask.any():
        return mask
    kernel = np.ones(2 * rows + 1)
    return np.convolve(mask.astype(float), kernel, mode="same") > 0.5


def sample_times(log: RunLog, settings: Settings) -> bool:
    """Whether ``log``'s samples and commands are placed at the times its timing columns
    record (True) or on the nominal grid ``time_s`` (False); see :data:`SAMPLE_TIMES`."""
    choice = settings.sample_times
    if choice == NOMINAL:
        return False
    if choice == LOGGED:
        if log.timing is None:
            raise LogError(f"{log.file}: --sample-times logged needs the loop's timing columns "
                           f"{', '.join(TIMING)} (written by cochlea-run and cochlea-embedded); "
                           "give --sample-times nominal")
        return True
    # auto: a log that carries measured current was recorded over a hardware backend (the
    # motors or the emulator), whose periods start and write at the wall clock's times; a
    # simulated run's plant steps on the nominal grid whatever its wall-clock timing.
    return log.timing is not None and log.current is not None


def _held_mean(values: np.ndarray, breaks: np.ndarray, time: np.ndarray, dt: float
               ) -> np.ndarray:
    """The mean over ``[t - dt/2, t + dt/2]`` of each ``t`` in ``time`` of the commands
    ``values[k]`` (rows), each held from ``breaks[k]`` to ``breaks[k + 1]`` (the last for
    ``dt``): the zero-order hold a drive applies, averaged over the period a state sample
    stands for. With ``breaks = time + (lag - 0.5) dt`` on a uniform grid this is the linear
    interpolation of ``values`` at ``t - lag dt``."""
    edges = np.append(breaks, breaks[-1] + dt)
    area = np.vstack([np.zeros((1, values.shape[1])),
                      np.cumsum(np.diff(edges)[:, None] * values, axis=0)])
    lo = np.column_stack([np.interp(time - dt / 2, edges, a) for a in area.T])
    hi = np.column_stack([np.interp(time + dt / 2, edges, a) for a in area.T])
    return (hi - lo) / dt


@dataclass
class Prepared:
    """One log through the states' side of the pipeline (filter, differentiation, regressor,
    parallel filter, decimation), which the effort lag does not touch; :meth:`samples` adds
    the efforts (and currents) for a lag. The lag search re-lags the efforts only."""

    log: RunLog
    model: RobotModel
    dt: float
    logged: bool  # samples and commands at the logged times (sample_times)
    writes: np.ndarray  # (N,) s: when each period's command went out (nominal: t)
    time: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    Y: np.ndarray
    moving: np.ndarray
    filters: tuple  # (b, a, keep, b2, a2, keep2): the efforts' filters and decimations

    def like_tau(self, series: np.ndarray) -> np.ndarray:
        """``series`` (full rate) through the efforts' filters and decimations."""
        from scipy import signal  # noqa: PLC0415 (start-up time: see the imports)
        b, a, keep, b2, a2, keep2 = self.filters
        out = signal.filtfilt(b, a, series, axis=0)[keep]
        if b2 is not None:
            out = signal.filtfilt(b2, a2, out, axis=0)[keep2]
        return out

    def held(self, values: np.ndarray, lag: float) -> np.ndarray:
        """Commands ``values`` (one row per period) as the motion saw them, at full rate: each
        held from its write plus ``lag - 0.5`` periods (on the nominal grid: read ``lag``
        periods earlier), averaged over each sample's period."""
        return _held_mean(values, self.writes + (lag - 0.5) * self.dt, self.log.time, self.dt)

    def samples(self, lag: float, with_current: bool = False) -> Samples:
        tau = self.like_tau(self.held(self.log.tau, lag))
        current = shape_of = None
        if with_current:
            # Present Current is read at the start of the period after the command it
            # measures (it is that command's Goal Current): row k + 1 holds command k.
            cur = self.log.current
            command = np.vstack([cur[1:], cur[-1:]])
            raw = self.held(command, lag)
            current = self.like_tau(raw)

            # The shape is nonlinear in the current: taken at the full rate, before the
            # filters (the equation a I + b s = Y beta holds at every instant, then filtered).
            def shape_of(knees: np.ndarray) -> np.ndarray:
                return self.like_tau(offset_shape(raw, knees))
        return Samples(self.time, self.q, self.qd, self.qdd, tau, self.Y, self.moving,
                       current, shape_of)


def process(log: RunLog, settings: Settings, model: RobotModel,
            with_current: bool = False) -> Samples:
    """``log`` filtered, differentiated, its regressor stacked and parallel-filtered, its
    ends dropped and decimated, with a numeric ``settings.effort_lag``: see the module
    docstring and :func:`prepare`."""
    return prepare(log, settings, model).samples(float(settings.effort_lag), with_current)


def prepare(log: RunLog, settings: Settings, model: RobotModel) -> Prepared:
    """The states' side of :func:`process`. Refuses a log too short for the filters and the
    parameters (one line)."""
    from scipy import signal  # noqa: PLC0415 (start-up time: see the imports)
    n_parameters = len(model.parameters.names)
    rate = log.rate_hz
    dt = 1.0 / rate
    nyquist = rate / 2.0
    if not 0.0 < settings.cutoff_hz < nyquist:
        raise CochleaError(f"--cutoff-hz {settings.cutoff_hz:g} must lie between 0 and the "
                           f"log's Nyquist frequency {nyquist:g} Hz ({log.file})")
    step = settings.decimation(rate)
    edge = edge_rows(rate, settings.cutoff_hz)
    parallel = settings.parallel_cutoff_hz
    if parallel is not None and not 0.0 < parallel < settings.cutoff_hz:
        raise CochleaError(f"--parallel-cutoff-hz {parallel:g} must lie between 0 and "
                           f"--cutoff-hz {settings.cutoff_hz:g}")
    rate2 = rate / step
    step2 = 1 if parallel is None else max(1, int(rate2 / (10.0 * parallel)))
    edge2 = 0 if parallel is None else edge_rows(rate2, parallel)
    samples = math.ceil(EQUATIONS_PER_PARAMETER * n_parameters / model.nq)
    needed = 2 * edge + step * (2 * edge2 + step2 * samples)
    if log.rows < needed:
        raise LogError(f"{log.file}: too short to identify from: {log.rows} rows "
                       f"({log.rows * dt:.3g} s at {rate:.4g} Hz); at least {needed} rows "
                       f"({needed * dt:.3g} s) are needed for {n_parameters} base parameters "
                       f"with --cutoff-hz {settings.cutoff_hz:g}"
                       + (f" and --parallel-cutoff-hz {parallel:g}" if parallel else "")
                       + ": record a longer excitation")
    logged = sample_times(log, settings)
    q, writes = log.q, log.time
    if logged:
        # A real-time period reads the state when it starts (its deadline plus its
        # lateness) and writes its command when its work ends; a late period (the shared
        # machine loses milliseconds at once) and the ones that catch up after it are
        # crowded together in wall time while time_s stays on the grid. Placing them where
        # they happened: the positions interpolated back onto the grid, the commands held
        # from their writes. A period without timing (a stop) is taken as on time.
        late = np.nan_to_num(log.timing[:, 0], nan=0.0)
        work, bus = (np.where(np.isfinite(x), x, np.nanmedian(x) if np.isfinite(x).any()
                              else 0.0) for x in log.timing[:, 1:3].T)
        reads = np.maximum.accumulate(log.time + late)
        q = np.column_stack([np.interp(log.time, reads, col) for col in log.q.T])
        writes = np.maximum.accumulate(log.time + late + work)
    b, a = signal.butter(FILTER_ORDER, settings.cutoff_hz / nyquist)
    q = signal.filtfilt(b, a, q, axis=0)
    # A chain that answers late was itself held up (another process had the processor, or
    # the bus): when it sampled the state and applied the commands around then is unknown
    # to the host, so the samples within the filters' reach of such a period are left out.
    slow = np.zeros(log.rows, bool)
    if logged and settings.max_bus_periods is not None:
        slow = _dilate(bus > settings.max_bus_periods * dt,
                       int(math.ceil(settings.slow_guard_s() * rate)))
    qd = np.gradient(q, dt, axis=0)
    qdd = np.gradient(qd, dt, axis=0)
    keep = slice(edge, log.rows - edge, step)
    time, q, qd, qdd = log.time[keep], q[keep], qd[keep], qdd[keep]
    Y = _mapped_regressor(model, q, qd, qdd)
    stuck = _stuck(model, qd, settings.min_speed)
    slow = slow[keep]
    b2 = a2 = keep2 = None
    if parallel is not None:
        # Parallel filtering: the same low-pass on the regressor's columns and the efforts.
        # tau = Y beta holds row by row, so it holds filtered as well, exactly, whatever the
        # filter; the states' own filter could not go this low without distorting Y, whose
        # columns are nonlinear in them. What it removes is the encoder noise and the
        # controller's chatter that the double differentiation amplifies.
        b2, a2 = signal.butter(FILTER_ORDER, parallel / (rate2 / 2.0))
        Y = signal.filtfilt(b2, a2, Y, axis=0)
        keep2 = slice(edge2, len(time) - edge2, step2)
        # A stuck row spoils every filtered row its filter reaches: the guard band.
        stuck = _dilate(stuck, int(math.ceil(settings.guard_s * rate2)))
        time, q, qd, qdd, Y, stuck, slow = (x[keep2] for x in
                                            (time, q, qd, qdd, Y, stuck, slow))
    stuck = stuck | slow
    return Prepared(log, model, dt, logged, writes, time, q, qd, qdd, Y, ~stuck,
                    (b, a, keep, b2, a2, keep2))


class LagError(LogError):
    """The effort's lag cannot be told from the logs (``--effort-lag auto``)."""


@dataclass(frozen=True)
class LagEstimate:
    """What :func:`estimate_lag` found: the lag, the residual curve behind it, its sharpness."""

    lag: float  # control periods
    grid: np.ndarray  # lags searched (periods)
    rms_ratio: np.ndarray  # the fit's residual RMS at each, over the one at ``lag``
    #: How much the residual's RMS rises a quarter period either side of ``lag`` (%): a sharp
    #: minimum is a well-determined lag.
    rise_percent: float


def timing_lag(log: RunLog) -> float | None:
    """The mean lag (periods) the timing columns show on the nominal grid: half a period of
    hold plus the mean of each period's lateness and read-compute-write time. None without
    timing columns. A diagnostic: the logged times place each period on its own."""
    if log.timing is None:
        return None
    rows = np.isfinite(log.timing).all(axis=1)
    if not rows.any():
        return None
    return 0.5 + float(np.mean(log.timing[rows, :2].sum(axis=1))) * log.rate_hz


def estimate_lag(model: RobotModel, prepared: list[Prepared], cuts: list[int],
                 settings: Settings, where: str) -> LagEstimate:
    """The effort lag (periods) that minimises the fit's residual on the fitted rows (the
    first ``cuts[i]`` samples of each log). The regressor depends on the states only, so it
    is stacked once; each candidate lag re-lags and re-filters the efforts and solves OLS,
    then WLS with per-joint weights from it. The criterion is the mean over the joints of
    the log of their residual's mean square (the weighted fit's likelihood with one variance
    per joint: no joint's units dominate). A grid over :data:`LAG_GRID`, then a bounded
    search between the best point's neighbours. Refuses a flat curve (the lag does not show
    in the data), a best lag at either end of the grid, and two separated minima of about the
    same depth."""
    from scipy import optimize  # noqa: PLC0415 (start-up time: see the imports)
    n = model.nq
    W = np.vstack([p.Y[:cut].reshape(-1, p.Y.shape[2]) for p, cut in zip(prepared, cuts)])
    keep = np.concatenate([np.repeat(p.moving[:cut], n) for p, cut in zip(prepared, cuts)])
    joint = np.tile(np.arange(n), len(keep) // n)[keep]
    W = W[keep]
    # A robot that was not excited says so, not that its lag is flat.
    _check_excited(model, W, settings, where)
    pinv = np.linalg.pinv(W)

    def cost(lag: float) -> float:
        y = np.concatenate([p.like_tau(p.held(p.log.tau, lag))[:cut].ravel()
                            for p, cut in zip(prepared, cuts)])[keep]
        r = y - W @ (pinv @ y)
        sigma = np.array([np.sqrt(np.mean(r[joint == j] ** 2)) for j in range(n)])
        w = 1.0 / np.maximum(sigma, 1e-12 * max(sigma.max(), 1e-300))[joint]
        beta = np.linalg.lstsq(W * w[:, None], y * w, rcond=None)[0]
        r = y - W @ beta
        ms = np.array([np.mean(r[joint == j] ** 2) for j in range(n)])
        return float(np.mean(np.log(np.maximum(ms, 1e-300))))

    grid = LAG_GRID
    costs = np.array([cost(lag) for lag in grid])
    i = int(np.argmin(costs))
    span = float(costs.max() - costs.min())
    # The criterion is a mean log mean square: a change d scales the residual's RMS by
    # exp(d / 2).
    if span < 2.0 * math.log1p(LAG_FLAT):
        raise LagError(f"{where}: --effort-lag auto: the fit's residual hardly depends on the "
                       f"lag (it changes by {100 * math.expm1(span / 2):.2g} % over "
                       f"{grid[0]:g}..{grid[-1]:g} periods): give --effort-lag (0.5 for a "
                       "command held over its period)")
    if i == len(grid) - 1:
        raise LagError(f"{where}: --effort-lag auto: the fit's residual still falls at "
                       f"{grid[-1]:g} periods, the end of the search: the log's efforts lag "
                       "more than a held command on a bus should; check the run's timing or "
                       "give --effort-lag")
    minima = [j for j in range(len(grid))
              if (j == 0 or costs[j] <= costs[j - 1]) and
              (j == len(grid) - 1 or costs[j] <= costs[j + 1])]
    rivals = [j for j in minima if abs(grid[j] - grid[i]) > LAG_SEPARATION and
              costs[j] - costs[i] < LAG_AMBIGUOUS * span]
    if rivals:
        raise LagError(f"{where}: --effort-lag auto: the fit's residual has minima of about "
                       f"the same depth at {grid[i]:g} and {grid[rivals[0]]:g} periods: the "
                       "lag is ambiguous in these logs; give --effort-lag")
    lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
    best = optimize.minimize_scalar(cost, bounds=(lo, hi), method="bounded",
                                    options={"xatol": LAG_TOLERANCE})
    lag, at = (float(best.x), float(best.fun)) if best.fun <= costs[i] else \
        (float(grid[i]), float(costs[i]))
    if lag < LAG_TOLERANCE:
        # A causal log's efforts act after they are logged: a residual least at no lag at
        # all (and rising towards it) says the columns are out of step.
        raise LagError(f"{where}: --effort-lag auto: the fit's residual is least at 0 periods, "
                       "the search's lower end: the logged efforts seem to act before they "
                       "were commanded (columns out of step?); check the log or give "
                       "--effort-lag")
    quarter = [cost(x) for x in (lag - 0.25, lag + 0.25) if x >= 0.0]
    rise = 100.0 * math.expm1((np.mean(quarter) - at) / 2.0)
    return LagEstimate(lag, grid.copy(), np.exp((costs - at) / 2.0), float(rise))

def regressor(model: RobotModel, samples: Samples) -> np.ndarray:
    """The stacked base regressor ``(N n, n_b)``: rows of sample k are ``k n .. k n + n - 1``,
    one per joint, so ``stacked @ beta`` is the efforts in the order of ``samples.tau.ravel()``."""
    return samples.Y.reshape(-1, samples.Y.shape[2])


def scaled_condition(W: np.ndarray) -> tuple[float, np.ndarray]:
    """The condition number of ``W`` with every column scaled to unit norm (inf when a column
    is zero or the columns are dependent), and the right singular vector of its smallest
    singular value (which parameters it mixes)."""
    norms = np.linalg.norm(W, axis=0)
    if (norms == 0).any():
        v = (norms == 0).astype(float)
        return math.inf, v / np.linalg.norm(v)
    _, s, vt = np.linalg.svd(W / norms, full_matrices=False)
    return (float(s[0] / s[-1]) if s[-1] > 0 else math.inf), vt[-1]


def moving_rows(model: RobotModel, samples: Samples) -> np.ndarray:
    """Which stacked rows (sample-major, see :func:`regressor`) to fit: every row of a sample
    whose joints all move at least ``min_speed``, and (with parallel filtering) no stuck
    sample within the guard band. The model's friction is ``Fv qd + Fc tanh(qd / v_s)``: a
    joint that sticks at a reversal is held by whatever static friction it takes, which no
    term predicts, and the filters smear it over their impulse response. The whole sample
    goes, not only the stuck joint's row: while one joint sticks the others' equations hold
    only if it is exactly at rest, which neither a real joint's micro-slip nor the simulated
    plant's stick-slip time-stepping (which re-places a stuck joint at rest each step)
    guarantees."""
    return np.repeat(samples.moving, model.nq)


@dataclass(frozen=True)
class LeastSquares:
    """One least-squares estimate with its statistics."""

    beta: np.ndarray
    std_error: np.ndarray
    residual_rms: np.ndarray  # per joint, N m or N

    @property
    def relative_std_error(self) -> np.ndarray:
        """Standard error over |estimate|, in % (inf for an estimate of zero)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(self.beta != 0, 100.0 * self.std_error / np.abs(self.beta), np.inf)


def _solve(W: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(beta, cov_unit)``: the least-squares solution and ``(W^T W)^-1`` through the SVD."""
    u, s, vt = np.linalg.svd(W, full_matrices=False)
    beta = vt.T @ ((u.T @ y) / s)
    cov_unit = (vt.T / s**2) @ vt
    return beta, cov_unit


def _per_joint_rms(r: np.ndarray, joint: np.ndarray, n_joints: int) -> np.ndarray:
    return np.array([np.sqrt(np.mean(r[joint == j] ** 2)) if (joint == j).any() else 0.0
                     for j in range(n_joints)])


def least_squares(W: np.ndarray, y: np.ndarray, joint: np.ndarray, n_joints: int,
                  weights: np.ndarray | None = None) -> LeastSquares:
    """Least squares of ``W beta = y`` (``joint``: the joint of each row), each row multiplied
    by ``weights`` when given."""
    m, n_b = W.shape
    w = np.ones(m) if weights is None else weights
    beta, cov_unit = _solve(W * w[:, None], y * w)
    r = y - W @ beta
    s2 = float(np.sum((r * w) ** 2)) / max(m - n_b, 1)
    std = np.sqrt(np.maximum(np.diag(cov_unit) * s2, 0.0))
    return LeastSquares(beta, std, _per_joint_rms(r, joint, n_joints))


def joint_weights(W: np.ndarray, y: np.ndarray, joint: np.ndarray, n_joints: int,
                  ols: LeastSquares) -> np.ndarray:
    """Per row, ``1 / sigma_j`` of its joint: ``sigma_j^2`` is the OLS residual variance of
    joint j's rows, the fit's degrees of freedom shared out in proportion to its rows."""
    m, n_b = W.shape
    r = y - W @ ols.beta
    sigma = np.ones(n_joints)
    for j in range(n_joints):
        rows = joint == j
        if rows.any():
            dof = max(rows.sum() * (m - n_b) / m, 1.0)
            sigma[j] = np.sqrt(np.sum(r[rows] ** 2) / dof)
    if not (np.isfinite(sigma).all() and sigma.max() > 0.0):
        # Every residual zero (an exact fit) or out of range: no joint to prefer, and 1/0
        # (or 1/inf) would poison the weighted fit; equal weights.
        return np.ones(len(joint))
    sigma = np.maximum(sigma, 1e-12 * sigma.max())  # an exact joint: no 1/0
    return 1.0 / sigma[joint]


def nrms(measured: np.ndarray, predicted: np.ndarray, mask: np.ndarray | None = None
         ) -> np.ndarray:
    """Per joint (columns), ``RMS(measured - predicted) / RMS(measured)`` in %, over the
    entries where ``mask`` (same shape) is true."""
    mask = np.ones(measured.shape, bool) if mask is None else mask
    out = np.full(measured.shape[1], np.inf)
    for j in range(measured.shape[1]):
        rows = mask[:, j]
        # Both RMS values in units of the largest effort: no square overflows.
        scale = float(np.max(np.abs(measured[rows, j]))) if rows.any() else 0.0
        if scale > 0 and math.isfinite(scale):
            size = np.sqrt(np.mean((measured[rows, j] / scale) ** 2))
            err = np.sqrt(np.mean(((measured[rows, j] - predicted[rows, j]) / scale) ** 2))
            out[j] = 100.0 * err / size
    return out


@dataclass
class Identification:
    """What :func:`identify` finds: the estimates, their statistics, the data behind them."""

    model: RobotModel
    ols: LeastSquares
    wls: LeastSquares
    weights: np.ndarray  # per fitted row
    W: np.ndarray  # the fit's stacked regressor (moving rows only)
    y: np.ndarray  # the fit's stacked efforts
    joint: np.ndarray  # the joint of each fitted row
    condition: float  # of W as it is (depends on the parameters' units)
    condition_scaled: float  # of W with unit-norm columns: the excitation's quality
    validation: list[Samples]  # the held-out samples
    W_validation: np.ndarray  # every held-out row, sample-major
    moving_validation: np.ndarray  # (N, n): the held-out entries of moving joints
    fit_rows: int  # stacked rows in the fit
    fit_samples: int  # samples (before leaving out slow joints' rows)
    held_out: str  # how the validation data was chosen
    settings: Settings
    #: The current-to-torque lines fitted with the base parameters (empty: none), their OLS
    #: and WLS estimates and standard errors (SI: N m per A and N m at the motor), ``(L, 2)``
    #: as ``[a, b]`` per line, and the knees (A) they were fitted with.
    lines: tuple[Line, ...] = ()
    line_ols: np.ndarray | None = None
    line_ols_std: np.ndarray | None = None
    line_wls: np.ndarray | None = None
    line_wls_std: np.ndarray | None = None
    knees: np.ndarray | None = None
    wls_full: np.ndarray | None = None  # with lines: WLS of beta and the lines together
    condition_with_lines: float | None = None  # column-scaled, with the lines' columns
    #: With --effort-lag auto, the search that chose settings.effort_lag.
    lag_search: LagEstimate | None = None
    #: Per log (fitted, then validation): placed at its logged times (sample_times).
    logged_times: list[bool] = dataclasses.field(default_factory=list)

    @property
    def beta(self) -> np.ndarray:
        """The estimate: weighted least squares."""
        return self.wls.beta

    def predict(self, beta: np.ndarray | None = None) -> np.ndarray:
        """Efforts the estimate predicts on the held-out samples, ``(N, n)``."""
        beta = self.wls.beta if beta is None else beta
        return (self.W_validation @ beta).reshape(-1, self.model.nq)

    @property
    def measured(self) -> np.ndarray:
        """Logged (filtered) efforts of the held-out samples, ``(N, n)``."""
        return np.vstack([s.tau for s in self.validation])

    @property
    def validation_time(self) -> np.ndarray:
        return np.concatenate([s.time for s in self.validation])

    def prediction_nrms(self, beta: np.ndarray | None = None, moving: bool = True
                        ) -> np.ndarray:
        """Per joint, the held-out NRMS error (%) of ``beta`` (default: WLS), over the moving
        joints' entries (the figure of merit) or over all of them (``moving=False``)."""
        return nrms(self.measured, self.predict(beta),
                    self.moving_validation if moving else None)


def _check_excited(model: RobotModel, W: np.ndarray, settings: Settings, where: str,
                   lines: tuple[Line, ...] = ()) -> float:
    cond, v = scaled_condition(W)
    if cond > settings.max_condition:
        names = list(model.parameters.names)
        meanings = list(model.parameters.meanings)
        for ln in lines:
            names += [f"{ln.name}.a"]
            meanings += [f"{ln.name} current-to-torque slope beyond its knee"]
        worst = np.argsort(-np.abs(v))[:3]
        mixed = ", ".join(f"{names[i]} ({meanings[i]})" for i in worst
                          if abs(v[i]) > 0.1)
        shown = "inf (rank-deficient)" if math.isinf(cond) else f"{cond:.3g}"
        raise NotExcitedError(
            f"{where}: the robot was not excited enough to identify its base parameters: "
            f"the scaled regressor's condition number is {shown}, above "
            f"{settings.max_condition:g}; least excited: {mixed}. Record a run of an "
            "excitation trajectory (cochlea-excite) or raise --max-condition")
    return cond


class NumericalError(LogError):
    """The fit of these logs is not a finite number (or its linear algebra failed): their
    numbers are out of the range least squares can take."""


def identify(model: RobotModel, logs: list[RunLog], validate: list[RunLog] | None = None,
             settings: Settings = Settings(), lines: tuple[Line, ...] | list[Line] = ()
             ) -> Identification:
    """OLS and WLS base parameters of ``model`` from ``logs``; validated on ``validate``, or
    without it on the last ``settings.holdout`` of every log (each log's own tail). With
    ``lines``, also those joints' current-to-torque lines (:mod:`cochlea.ident.current`).

    Refuses (:class:`NumericalError`, one line) a fit whose estimates, standard errors,
    residuals, weights or held-out predictions are not finite, or whose linear algebra fails
    (an SVD that does not converge): numpy's overflow warnings are not printed, the refusal
    says it once."""
    where = ", ".join(str(log.folder) for log in logs)
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore", under="ignore"):
            result = _identify_logs(model, logs, validate, settings, lines)
            check_finite(result, where)
    except np.linalg.LinAlgError as exc:
        raise NumericalError(f"{where}: the least-squares fit failed numerically ({exc}): "
                             "check the logs' units and that every joint moved") from None
    return result


def check_finite(result: Identification, where: str) -> None:
    """Refuse an identification with a non-finite estimate, standard error, residual, weight
    or held-out prediction (NaN, or an infinity an overflow left), naming the first."""
    names = list(result.model.parameters.names)
    checks = [("OLS estimate", result.ols.beta), ("OLS standard error", result.ols.std_error),
              ("WLS estimate", result.wls.beta), ("WLS standard error", result.wls.std_error)]
    if result.line_wls is not None:
        checks += [("current-to-torque line", result.line_wls.ravel()),
                   ("current-to-torque line's standard error", result.line_wls_std.ravel())]
    for what, values in checks:
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            i = int(bad[0])
            label = names[i] if what.startswith(("OLS", "WLS")) else f"#{i + 1}"
            raise NumericalError(f"{where}: the fit's {what} of {label} is {values[i]} "
                                 f"({bad.size} non-finite): the logs' numbers are out of the "
                                 "range least squares can take; check their units")
    joints = list(result.model.joint_names)
    for what, values in (("residual (OLS)", result.ols.residual_rms),
                         ("residual (WLS)", result.wls.residual_rms),
                         ("held-out NRMS (WLS)", result.prediction_nrms()),
                         ("held-out NRMS (OLS)", result.prediction_nrms(result.ols.beta)),
                         ("held-out NRMS (all samples)",
                          result.prediction_nrms(moving=False))):
        # A held-out NRMS is infinite by definition where the joint's held-out effort is all
        # zero (reported as null); NaN, or an infinite residual, is an overflow.
        bad = np.flatnonzero(np.isnan(values) if "NRMS" in what else ~np.isfinite(values))
        if bad.size:
            j = int(bad[0])
            raise NumericalError(f"{where}: the fit's {what} of {joints[j]} is {values[j]}: "
                                 "the logs' numbers are out of the range least squares can "
                                 "take; check their units")
    if not np.isfinite(result.weights).all():
        raise NumericalError(f"{where}: the fit's weights are not finite: the logs' numbers "
                             "are out of the range least squares can take; check their units")


def _identify_logs(model: RobotModel, logs: list[RunLog], validate: list[RunLog] | None,
                   settings: Settings, lines: tuple[Line, ...] | list[Line]
                   ) -> Identification:
    """:func:`identify` without its numerical checks."""
    from scipy import optimize  # noqa: PLC0415 (start-up time: see the imports)
    lines = tuple(lines)
    if validate is None and not MIN_HOLDOUT <= settings.holdout <= MAX_HOLDOUT:
        raise CochleaError(f"--holdout must lie between {MIN_HOLDOUT:g} and {MAX_HOLDOUT:g} "
                           f"(a fraction of each log), got {settings.holdout:g}")
    if not settings.min_speed >= 0.0:
        raise CochleaError(f"--min-speed must be a non-negative number (rad/s), got "
                           f"{settings.min_speed:g}")
    if lines:
        without = [log for log in logs + list(validate or []) if log.current is None]
        if without:
            raise CurrentFitError(f"{without[0].file}: no measured current (columns "
                                  "<unit>.current.<joint>_A) to fit the lines of "
                                  + ", ".join(ln.name for ln in lines)
                                  + ": every log must carry it (record over the bus), or give "
                                  "--fit-current off")
        if len(lines) == model.nq:
            raise CurrentFitError("every joint's current-to-torque line would be fitted: the "
                                  "torque's scale is not observable; calibrate one drive with "
                                  "cochlea-dxl calibrate --torque-fit")
    with_current = bool(lines)
    where = ", ".join(str(log.folder) for log in logs)
    prepared = [prepare(log, settings, model) for log in logs]
    prepared_val = [prepare(log, settings, model) for log in validate or []]
    cuts = [len(p.time) if validate is not None else
            int(round(len(p.time) * (1.0 - settings.holdout))) for p in prepared]
    lag_search = None
    if settings.effort_lag == AUTO:
        # On the plain fit (every joint's logged effort), also with lines to fit: a
        # placeholder line scales its joint's effort, it does not move it in time.
        lag_search = estimate_lag(model, prepared, cuts, settings, where)
        settings = dataclasses.replace(settings, effort_lag=lag_search.lag)
    lag = float(settings.effort_lag)
    fit_parts, val_parts = [], []
    for p, cut in zip(prepared, cuts):
        s = p.samples(lag, with_current)
        fit_parts.append(s.rows(slice(0, cut)))
        if validate is None:
            val_parts.append(s.rows(slice(cut, None)))
    if validate is not None:
        val_parts = [p.samples(lag, with_current) for p in prepared_val]
        held_out = "the validation logs (--validate)"
    else:
        held_out = f"the last {settings.holdout:.0%} of every log"
    timing = {"lag_search": lag_search,
              "logged_times": [p.logged for p in prepared + prepared_val]}
    if not lines:
        return dataclasses.replace(
            _identify(model, fit_parts, val_parts, settings, held_out, where, (), None),
            **timing)
    # The knee of each line's offset moves with (a, b). For given knees the problem is
    # linear; the knees are chosen by the fit's residual (with the joints' weights of the
    # fit at the description's knees, so that every knee is judged alike), over knees with
    # enough samples beyond them to tell a from b (inside the knee only the slope ramp /
    # knee shows). Most samples of a gentle excitation lie inside it, so the placeholder's
    # knee will not do: on the simulated arm it biased a by 5 % and b by 60 %.
    knees = np.full(model.nq, np.inf)
    for ln in lines:
        knees[ln.joint] = ln.knee(ln.a0, ln.b0)
    first = _identify(model, fit_parts, val_parts, settings, held_out, where, lines, knees)
    weights = first.weights
    magnitude = np.abs(np.concatenate([s.current for s in fit_parts]))
    grids = {}
    for ln in lines:
        lo, hi = np.percentile(magnitude[:, ln.joint], [100 * (1 - KNEE_BEYOND_MAX),
                                                          100 * (1 - KNEE_BEYOND_MIN)])
        grids[ln.joint] = np.geomspace(max(lo, 1e-6), max(hi, 2e-6), KNEE_GRID)

    def cost(trial: np.ndarray) -> float:
        r = _identify(model, fit_parts, val_parts, settings, held_out, where, lines, trial,
                      check=False, weights=weights)
        return float(np.sum((r.weights * (r.y - r.W @ r.wls_full)) ** 2))

    def at(joint: int, k: float) -> float:
        trial = knees.copy()
        trial[joint] = k
        return cost(trial)

    for _ in range(KNEE_SWEEPS if len(lines) > 1 else 1):
        for ln in lines:
            # The residual drops sharply at the true knee (a kink the data show): a grid to
            # find its basin, then a bounded search between the grid's neighbours.
            grid = grids[ln.joint]
            costs = [at(ln.joint, k) for k in grid]
            i = int(np.argmin(costs))
            if i == len(grid) - 1:
                raise NotExcitedError(
                    f"{where}: the current of {ln.name} goes beyond the knee of its "
                    f"current-to-torque line on too few samples to tell its slope from its "
                    f"offset (the fit's residual still falls at {grid[-1]:.3g} A, exceeded by "
                    f"{KNEE_BEYOND_MIN:.0%} of the samples): record an excitation with larger "
                    f"accelerations (a shorter period), or leave its fit out (--fit-current)")
            lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, len(grid) - 1)]
            best = optimize.minimize_scalar(lambda k, j=ln.joint: at(j, k), bounds=(lo, hi),
                                            method="bounded",
                                            options={"xatol": KNEE_TOLERANCE * grid[i]})
            knees[ln.joint] = best.x if best.fun <= costs[i] else grid[i]
    return dataclasses.replace(
        _identify(model, fit_parts, val_parts, settings, held_out, where, lines, knees),
        **timing)


def _line_columns(parts: list[Samples], lines: tuple[Line, ...], n: int, knees: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The lines' columns of the stacked equations and their right-hand side, sample-major
    like :func:`regressor`. At the knee the torque is the ramp (``a knee + b = ramp``, the
    rule of :class:`~cochlea.robots.motor_fit.Fit`), so ``b = ramp - a knee`` and a fitted
    joint's equation ``Y beta = (a I + b s) / r`` becomes ``Y beta - a (I - knee s) / r =
    ramp s / r``: one column per line, ``-(I - knee s) / r`` on its joint's rows."""
    current = np.concatenate([s.current.ravel() for s in parts])
    shape = np.concatenate([s.shape.ravel() for s in parts])
    joint = np.tile(np.arange(n), len(current) // n)
    out = np.zeros((len(current), len(lines)))
    rhs = np.zeros(len(current))
    for k, ln in enumerate(lines):
        on = joint == ln.joint
        knee = knees[ln.joint]
        out[on, k] = -(current[on] - knee * shape[on]) / ln.scale
        rhs[on] = ln.ramp * shape[on] / ln.scale
    return out, rhs


def _with_line_efforts(s: Samples, lines: tuple[Line, ...], ab: np.ndarray) -> Samples:
    """``s`` with the efforts of the fitted joints replaced by what their identified lines
    give for the measured current (the logged ones only echo the placeholder line)."""
    tau = s.tau.copy()
    for (a, b), ln in zip(ab, lines):
        tau[:, ln.joint] = (a * s.current[:, ln.joint] + b * s.shape[:, ln.joint]) / ln.scale
    return dataclasses.replace(s, tau=tau)


def _identify(model: RobotModel, fit_parts: list[Samples], val_parts: list[Samples],
              settings: Settings, held_out: str, where: str, lines: tuple[Line, ...],
              knees: np.ndarray | None, check: bool = True,
              weights: np.ndarray | None = None) -> Identification:
    n = model.nq
    n_b = len(model.parameters.names)
    if lines:
        fit_parts = [s.with_knees(knees) for s in fit_parts]
        val_parts = [s.with_knees(knees) for s in val_parts]
    keep = np.concatenate([moving_rows(model, s) for s in fit_parts])
    W = np.vstack([regressor(model, s) for s in fit_parts])
    y = np.concatenate([s.tau.ravel() for s in fit_parts])
    joint_all = np.tile(np.arange(n), len(keep) // n)
    if lines:
        columns, rhs = _line_columns(fit_parts, lines, n, knees)
        W = np.hstack([W, columns])
        fitted = np.isin(joint_all, [ln.joint for ln in lines])
        y = np.where(fitted, rhs, y)  # a fitted joint's logged effort is not used
    W, y, joint = W[keep], y[keep], joint_all[keep]
    cond_scaled = _check_excited(model, W, settings, where, lines) if check else math.nan
    cond = float(np.linalg.cond(W)) if check else math.nan
    ols = least_squares(W, y, joint, n)
    if weights is None:
        weights = joint_weights(W, y, joint, n, ols)
    wls = least_squares(W, y, joint, n, weights)
    extra = {}
    if lines:
        k = np.array([knees[ln.joint] for ln in lines])
        ramp = np.array([ln.ramp for ln in lines])

        def ab(est: LeastSquares) -> tuple[np.ndarray, np.ndarray]:
            a, sa = est.beta[n_b:], est.std_error[n_b:]
            return (np.column_stack([a, ramp - a * k]), np.column_stack([sa, sa * k]))

        (line_ols, line_ols_std), (line_wls, line_wls_std) = ab(ols), ab(wls)
        extra = {"lines": lines, "knees": knees, "wls_full": wls.beta,
                 "line_ols": line_ols, "line_ols_std": line_ols_std,
                 "line_wls": line_wls, "line_wls_std": line_wls_std,
                 "condition_with_lines": cond_scaled}
        if not check:  # a step of the knees' search: the lines are all it needs
            return Identification(model, ols, wls, weights, W, y, joint, cond, cond_scaled,
                                  val_parts, np.zeros((0, n_b)), np.zeros((0, n), bool),
                                  len(y), len(keep) // n, held_out, settings, **extra)
        # From here on the fitted joints' efforts are their identified lines' torques, so
        # the base parameters' consumers (validation, figures, --physical) see tau = Y beta.
        ab = extra["line_wls"]
        fit_parts = [_with_line_efforts(s, lines, ab) for s in fit_parts]
        val_parts = [_with_line_efforts(s, lines, ab) for s in val_parts]
        W = W[:, :n_b]
        y = np.concatenate([s.tau.ravel() for s in fit_parts])[keep]
        ols = LeastSquares(ols.beta[:n_b], ols.std_error[:n_b], ols.residual_rms)
        wls = LeastSquares(wls.beta[:n_b], wls.std_error[:n_b], wls.residual_rms)
        cond_scaled = scaled_condition(W)[0]
        cond = float(np.linalg.cond(W))
    W_val = np.vstack([regressor(model, s) for s in val_parts])
    moving_val = np.concatenate([moving_rows(model, s)
                                 for s in val_parts]).reshape(-1, n)
    return Identification(model, ols, wls, weights, W, y, joint, cond, cond_scaled, val_parts,
                          W_val, moving_val, len(y), len(keep) // n, held_out, settings,
                          **extra)
