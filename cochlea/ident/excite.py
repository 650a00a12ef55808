"""Excitation trajectories for identification: a finite Fourier series per joint, optimised
for the condition number of the stacked base regressor within the robot's limits, written as a
joint-space scenario that ``cochlea-run`` tracks (issue 14, ``cochlea-excite``).

The series is Swevers' form, per joint ``i`` with fundamental ``w = 2 pi / T``::

    q_i(t) = q0_i + sum_k a_ik / (w k) sin(w k t) - b_ik / (w k) cos(w k t),   k = 1..H
    qd_i(t) = sum_k a_ik cos(w k t) + b_ik sin(w k t)

It is periodic, so a run of whole periods ends where it began. It starts (and so ends every
period) at rest: ``qd_i(0) = sum_k a_ik = 0`` and ``qdd_i(0) = w sum_k k b_ik = 0``, imposed by
eliminating ``a_i1`` and ``b_i1``; the scenario's initial state is the series at t = 0, so the
run begins without a jump in position, velocity or acceleration. Two harmonics at least: with
one, the rest conditions leave only a constant.

The criterion is the condition number of the base regressor ``Y(q, qd, qd, qdd)`` of
``cochlea.model(robot, parameterisation="base", actuators="all")`` (armature, viscous and
Coulomb friction included), stacked over the samples of one period, in SI units (the number
the identification reports). Constraints, at the same samples: each joint within
``amplitude`` of its working pose and inside its position limits, velocity and torque (the
nominal inverse dynamics, drives included) within ``limit_fraction`` of their limits; serial
arms: every link segment outside the cochlea keep-out circle (with a margin) and clear of the
other arm, which holds still at its working pose; the parallel mechanism: each rod in its
sleeve (``min_pivot_distance <= |C - S| <= d3``, with margins), the slider within its stroke,
each pantograph on its branch away from its folded and stretched singularities. The result is
then checked at every control period of one period (1 kHz) against the limits themselves.

The optimiser is SLSQP (scipy) with exact gradients (CasADi), from a few random starts drawn
from ``numpy.random.default_rng(seed)``: the same options give the same trajectory.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.optimize import minimize

from ..dynamixel.control_table import MODELS
from ..errors import CochleaError
from ..robots import ROBOTS, ExcitationGeometry
from ..robots import robot as robot_adapter
from ..robots.urdf import starter_scenario
from ..sim.scenario import load as load_scenario
from ..text import comment, toml_string

#: The joint-space studies tuned for the realistic plant (each robot's
#: ``excitation_study``): their control settings and gains track the excitation too
#: (docs/excitation.md), and their initial joint angles are the units' working poses unless
#: the robot's excitation geometry says otherwise. The robot's own geometry (keep-out circle,
#: the other arm, the mechanism's sleeves and branches) is its adapter's
#: ``excitation_geometry`` (cochlea/robots/<kind>/excitation.py).
TRACKING_SCENARIOS = {name: r.excitation_study for name, r in ROBOTS.items()}
#: Sharpness of the soft minimum of each normalised constraint over the samples (its values
#: are fractions of the limit's range): it undershoots the true minimum by at most
#: log(samples) / 400 (1.5 % of the range at 400 samples), on the safe side.
AGGREGATION_SHARPNESS = 400.0
#: Samples per period of the criterion and the constraints (at least this many, and at least
#: 40 per period of the highest harmonic).
MIN_SAMPLES = 100
#: Rate (Hz) of the final check of the designed trajectory: cochlea-run's control rate.
CHECK_RATE_HZ = 1000.0
#: Smallest band a joint may be asked to move in (``--amplitude-deg``, ``--amplitude-mm``):
#: about ten encoder counts of a directly driven Dynamixel joint (0.088 deg a count); below
#: it the motion is mostly quantisation and no parameter is excited.
MIN_AMPLITUDE_RAD = math.radians(1.0)
MIN_AMPLITUDE_M = 0.001


@dataclass(frozen=True)
class ExcitationOptions:
    """What ``cochlea-excite`` asks for (SI)."""

    period: float = 5.0  # s, T of the fundamental
    harmonics: int = 5  # H
    amplitude_rad: float = math.radians(20.0)  # revolute joints: |q - working pose| bound
    amplitude_m: float = 0.02  # prismatic joints (the slider)
    periods: int = 4  # the run: whole periods, at rest at each end
    seed: int = 0
    starts: int = 4  # random starts of the optimiser
    iterations: int = 150  # SLSQP iterations per start
    limit_fraction: float = 0.8  # of the velocity and effort limits
    clearance: float = 0.02  # m, serial: between the excited arm and the other one


@dataclass
class FourierSeries:
    """Swevers' series for ``n`` joints: ``offset`` (n,), ``a`` and ``b`` (n, H); SI."""

    period: float
    offset: np.ndarray
    a: np.ndarray
    b: np.ndarray

    @property
    def omega(self) -> float:
        return 2.0 * math.pi / self.period

    @property
    def harmonics(self) -> int:
        return self.a.shape[1]

    def evaluate(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``q, qd, qdd`` at ``times``, each (n, len(times))."""
        t = np.asarray(times, float).ravel()
        wk = self.omega * np.arange(1, self.harmonics + 1)
        s, c = np.sin(np.outer(wk, t)), np.cos(np.outer(wk, t))
        q = self.offset[:, None] + (self.a / wk) @ s - (self.b / wk) @ c
        qd = self.a @ c + self.b @ s
        qdd = -(self.a * wk) @ s + (self.b * wk) @ c
        return q, qd, qdd

    def formula(self, i: int) -> str:
        """Joint ``i``'s position as a scenario formula in t (SI; exact to the last digit)."""
        w = self.omega
        terms = [repr(float(self.offset[i]))]
        for k in range(1, self.harmonics + 1):
            wk = w * k
            for coefficient, function in ((self.a[i, k - 1] / wk, "sin"),
                                          (-self.b[i, k - 1] / wk, "cos")):
                if coefficient != 0.0:
                    sign = "-" if coefficient < 0 else "+"
                    terms.append(f"{sign} {abs(float(coefficient))!r}*{function}({wk!r}*t)")
        return " ".join(terms)


def _reduced_basis(period: float, harmonics: int, times: np.ndarray):
    """Matrices ``P_q, P_qd, P_qdd`` (len(times), 1 + 2 (H - 1)) mapping one joint's free
    coefficients ``z = [q0, a_2..a_H, b_2..b_H]`` to its samples; ``a_1 = -sum a_k`` and
    ``b_1 = -sum k b_k`` (at rest at t = 0) are folded in. The series is linear in z: column
    j is the series of the j-th unit vector."""
    nz = 1 + 2 * (harmonics - 1)
    columns = [_series_of(period, harmonics, np.eye(nz)[j][None, :]).evaluate(times)
               for j in range(nz)]
    return tuple(np.column_stack([c[order][0] for c in columns]) for order in range(3))


def _series_of(period: float, harmonics: int, z: np.ndarray) -> FourierSeries:
    """The series of the free coefficients ``z`` (n, 1 + 2 (H - 1))."""
    H = harmonics
    offset = z[:, 0]
    a_rest, b_rest = z[:, 1:H], z[:, H:]
    k = np.arange(2, H + 1)
    a = np.column_stack([-a_rest.sum(axis=1), a_rest])
    b = np.column_stack([-(b_rest * k).sum(axis=1), b_rest])
    return FourierSeries(period, offset.copy(), a, b)


@dataclass
class Design:
    """A designed excitation and what it achieves."""

    robot: str
    unit: str  # the excited unit: "arm1", "arm2" or "mechanism"
    series: FourierSeries
    options: ExcitationOptions
    working_pose: np.ndarray  # SI, the band's centre
    amplitude: np.ndarray  # SI per joint
    condition: float  # of the stacked base regressor, SI
    scaled_condition: float  # the same with every column scaled to unit norm
    sine_condition: float  # the hand-picked sine of the same amplitude
    sine_scaled_condition: float
    #: Per joint: peak |qd| / limit and peak |tau| / limit over the 1 kHz check.
    peak_velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    peak_effort: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Serial: the smallest distance (m) of the excited arm to the cochlea centre and to the
    #: other arm over the check; the parallel mechanism: None.
    keep_out_distance: float | None = None
    clearance_distance: float | None = None
    #: Other units and the pose each holds (SI): the serial system's other arm.
    held: dict[str, np.ndarray] = field(default_factory=dict)
    #: The description excited (None: the robot's shipped one) and the tracking scenario.
    description: str | Path | None = None
    study: object = field(default=None, repr=False)
    study_label: str = ""
    #: Smallest distance (m) of the excited links to the description's keep-out volumes.
    keep_out_volume_distance: float | None = None


# --------------------------------------------------------------------------------------------
# The problem of one robot
# --------------------------------------------------------------------------------------------


@dataclass
class _Problem:
    robot: str
    unit: str
    model: object  # RobotModel, base parameters, actuators "all"
    centre: np.ndarray
    amplitude: np.ndarray
    low: np.ndarray  # the band inside the position limits, SI
    high: np.ndarray
    #: The robot's own geometry: its constraints (``q (n,) -> values``, >= 0 when satisfied)
    #: and the final check's.
    geometry: ExcitationGeometry
    held: dict = field(default_factory=dict)
    description: str | Path | None = None  # None: the robot's shipped description
    study: object = None  # the tracking scenario (tracking_study)
    study_label: str = ""

    @property
    def extra(self) -> ca.Function:
        return self.geometry.constraints


def _band(model, centre: np.ndarray, amplitude: np.ndarray, unit: str) -> tuple:
    low, high = centre - amplitude, centre + amplitude
    for j, c, lo, hi in zip(model.joints, centre, low, high):
        limit_lo, limit_hi = j.position_limits
        if lo < limit_lo or hi > limit_hi:
            if j.type == "revolute":
                scale, what = 180.0 / math.pi, "deg"
                option = "--amplitude-deg"
            else:
                scale, what = 1000.0, "mm"
                option = "--amplitude-mm"
            room = min(c - limit_lo, limit_hi - c) * scale
            raise CochleaError(
                f"{option} {(hi - c) * scale:g}: joint {j.name} of {unit} works around "
                f"{c * scale:.4g} {what} and can move only {room:.3g} {what} either way "
                f"inside its limits [{limit_lo * scale:g}, {limit_hi * scale:g}] {what}: give "
                f"at most {math.floor(room * 10) / 10:g}")
    return low, high


def _amplitudes(model, options: ExcitationOptions) -> np.ndarray:
    return np.array([options.amplitude_rad if j.type == "revolute" else options.amplitude_m
                     for j in model.joints])


def _same_file(a, b) -> bool:
    try:
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, TypeError):
        return False


def tracking_study(robot: str, system, tracking: str | Path | None = None):
    """``(scenario, how to name it)``: the joint-space scenario whose control settings and
    gains track the excitation:
    ``tracking`` where given (it must be a joint-space scenario running the same
    description); else the robot's
    :attr:`excitation_study` when the description is the one it was made for (or a copy:
    ``is_shipped``); else (a
    user's robot) the gentle starter scenario ``cochlea-urdf`` writes for the description
    (controller e, gains scaled to the arm's inertia)."""
    adapter = robot_adapter(robot)
    if tracking is not None:
        study = load_scenario(tracking)
        if study.space != "joint":
            # Its gains are for the task-space controller, and its units' initial states are
            # no joint poses: the excitation is tracked in joint space.
            raise CochleaError(f"--scenario {tracking}: a {study.space}-space scenario; the "
                               "excitation is tracked in joint space: give a joint-space "
                               "scenario (space = \"joint\") of the same description")
        if study.robot != robot or not (_same_file(study.system.path, system.path)
                                        or study.system.name == system.name):
            raise CochleaError(f"--scenario {tracking}: it runs {study.robot} "
                               f"{study.system.path}, not {robot} {system.path}: the tracking "
                               "scenario must run the excited description")
        return study, study.path.name
    study = load_scenario(adapter.excitation_study)
    if adapter.is_shipped(system):
        return study, study.path.name
    units = adapter.layout(system, "joint").units
    if not adapter.units_are_arms or len(units) != 1:  # the starter moves one serial arm
        raise CochleaError(f"{system.path}: give --scenario, a joint-space scenario of this "
                           "description whose settings and gains track the excitation (the "
                           "default, cochlea-urdf's starter, is for a single serial arm)")
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "tracking.toml"
        path.write_text(starter_scenario(system, str(Path(system.path).resolve())))
        return load_scenario(path), "the starter scenario cochlea-urdf writes for it"


def _problem(robot: str, arm: str | None, options: ExcitationOptions,
             description: str | Path | None = None,
             tracking: str | Path | None = None) -> _Problem:
    """The problem of ``robot``'s unit ``arm`` (None: the first; the others hold still at
    their working poses): its model, band and geometry (the robot's adapter). The working
    poses: those of the robot's excitation study for the description it was made for, else
    the adapter's :meth:`~cochlea.robots.adapter.RobotAdapter.excitation_pose` (the
    description's ``working_pose_deg``, or the middle of the joint limits)."""
    adapter = robot_adapter(robot)
    system = adapter.load(description)
    unit = adapter.unit(system, arm)
    study, label = tracking_study(robot, system, tracking)
    units = adapter.layout(system, "joint").units
    if adapter.is_shipped(system):
        poses = {u.name: np.asarray(u.initial_joint, float) for u in study.units}
    else:
        poses = {name: adapter.excitation_pose(system, name) for name in units}
    model = adapter.model(system, unit, parameterisation="base", actuators="all")
    amplitude = _amplitudes(model, options)
    held = {name: poses[name] for name in units if name != unit}
    geometry = adapter.excitation_geometry(system, unit, poses[unit], held, options.clearance)
    centre = geometry.working_pose
    low, high = _band(model, centre, amplitude, geometry.label)
    problem = _Problem(robot, unit, model, centre, amplitude, low, high, geometry, held,
                       description, study, label)
    geometry.check_start()
    return problem


# --------------------------------------------------------------------------------------------
# The optimisation
# --------------------------------------------------------------------------------------------


def samples_per_period(options: ExcitationOptions) -> int:
    return max(MIN_SAMPLES, 40 * options.harmonics)


def _stacked(model, q, qd, qdd) -> np.ndarray:
    """The base regressor stacked over samples (columns of q, qd, qdd): (n N) x p."""
    N = q.shape[1]
    Y = np.array(model.Y.map(N)(q, qd, qd, qdd))  # n x (N p)
    p = len(model.param_names)
    return np.vstack([Y[:, k * p:(k + 1) * p] for k in range(N)])


def conditions(model, q, qd, qdd) -> tuple[float, float]:
    """Condition number of the stacked base regressor at the samples: as is (SI) and with
    every column scaled to unit norm."""
    Y = _stacked(model, q, qd, qdd)
    norms = np.linalg.norm(Y, axis=0)
    return float(np.linalg.cond(Y)), float(np.linalg.cond(Y / np.where(norms > 0, norms, 1.0)))


class _Optimiser:
    """The criterion and the constraints of one problem as functions of the free coefficients
    ``x`` (joint after joint, ``z_i = [q0_i, a_i2..a_iH, b_i2..b_iH]``) with exact gradients.

    The samples are linear in x (``q = P_q z``), so every gradient is a per-sample CasADi
    Jacobian (with respect to q, qd, qdd: small, mapped over the samples) chained with P."""

    def __init__(self, problem: _Problem, options: ExcitationOptions):
        self.problem, self.options = problem, options
        m = problem.model
        n, p = m.nq, len(m.param_names)
        self.n, self.p = n, p
        N = samples_per_period(options)
        times = np.arange(N) * options.period / N
        self.P = np.stack(_reduced_basis(options.period, options.harmonics, times))  # 3 N nz
        self.nz = self.P.shape[2]

        q, qd, qdd = (ca.SX.sym(name, n) for name in ("q", "qd", "qdd"))
        state = ca.vertcat(q, qd, qdd)
        Y = m.Y(q, qd, qd, qdd)
        fraction = options.limit_fraction
        vmax = np.array([j.velocity_limit for j in m.joints])
        emax = np.array([j.effort_limit for j in m.joints])
        span = problem.high - problem.low
        tau = Y @ ca.DM(m.p_nominal)
        # Each limit normalised by its size: a value in [0, 1] inside, negative outside.
        rows = ca.vertcat((ca.DM(problem.high) - q) / span, (q - ca.DM(problem.low)) / span,
                          (fraction * vmax - qd) / vmax, (fraction * vmax + qd) / vmax,
                          (fraction * emax - tau) / emax, (fraction * emax + tau) / emax,
                          problem.extra(q))
        self.rows = ca.Function("rows", [q, qd, qdd], [rows, ca.jacobian(rows, state)]).map(N)
        self.n_rows = rows.shape[0]
        # The regressor per sample, and the gradient of sum(W * Y) with respect to the state
        # for a weight W per sample (reverse mode: one sweep, whatever the parameters).
        W = ca.SX.sym("W", n, p)
        self.Y = ca.Function("Y", [q, qd, qdd], [Y]).map(N)
        self.dY = ca.Function("dY", [q, qd, qdd, W],
                              [ca.gradient(ca.sum1(ca.sum2(W * Y)), state)]).map(N)
        self.N = N
        self._cache: dict = {}

    def series(self, x: np.ndarray) -> FourierSeries:
        return _series_of(self.options.period, self.options.harmonics,
                          np.asarray(x, float).reshape(self.n, self.nz))

    def _states(self, x):
        Z = np.asarray(x, float).reshape(self.n, self.nz).T  # nz x n
        return [(P @ Z).T for P in self.P]  # q, qd, qdd: n x N each

    def _chain(self, dstate: np.ndarray) -> np.ndarray:
        """``d/dx`` from ``d/d(q, qd, qdd)`` per sample: ``dstate`` (rows, 3, n, N)."""
        return np.einsum("roik,okj->rij", dstate, self.P).reshape(dstate.shape[0], -1)

    def _evaluate(self, x: np.ndarray):
        key = np.asarray(x, float).tobytes()
        if key in self._cache:
            return self._cache[key]
        n, N = self.n, self.N
        states = self._states(x)
        Y = np.vstack(np.split(np.array(self.Y(*states)), N, axis=1))  # (N n) x p
        # The singular values from the small Gram matrix (a tall SVD or QR is slow under a
        # threaded BLAS); exact enough for the condition numbers that matter here (< 1e7).
        lam, V = np.linalg.eigh(Y.T @ Y)
        if not lam[0] > 0:
            value, grad = 1e3, np.zeros(len(x))
        else:
            value = 0.5 * float(np.log(lam[-1] / lam[0]))
            # d sigma = u' dY v with u = Y v / sigma: the weight of each entry of each sample's
            # Y in d log(sigma_max / sigma_min).
            v_max, v_min = V[:, -1], V[:, 0]
            W = np.outer(Y @ v_max, v_max) / lam[-1] - np.outer(Y @ v_min, v_min) / lam[0]
            W = np.hstack(np.split(W, N, axis=0))  # n x (p N): sample k's block side by side
            dstate = np.array(self.dY(*states, W)).reshape(3, n, N)
            grad = self._chain(dstate[None])[0]
        G, dG = (np.array(v) for v in self.rows(*states))  # rows x N; rows x (3 n N)
        dG = dG.reshape(self.n_rows, N, 3, n).transpose(0, 2, 3, 1)  # rows, 3, n, N
        low = G.min(axis=1, keepdims=True)
        e = np.exp(-AGGREGATION_SHARPNESS * (G - low))
        total = e.sum(axis=1, keepdims=True)
        g = (low - np.log(total) / AGGREGATION_SHARPNESS).ravel()
        dg = self._chain(dG * (e / total)[:, None, None, :])
        self._cache = {key: (value, grad, g, dg)}
        return self._cache[key]

    def criterion(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """log cond(Y) of the stacked base regressor and its gradient."""
        value, grad, _, _ = self._evaluate(x)
        return value, grad

    def violation(self, x: np.ndarray) -> float:
        return float(max(0.0, -np.min(self._evaluate(x)[2])))

    def start(self, rng: np.random.Generator) -> np.ndarray:
        """A random start: the working pose plus random harmonics, shrunk until feasible."""
        pr = self.problem
        Z = np.zeros((self.n, self.nz))
        Z[:, 0] = pr.centre
        H = self.options.harmonics
        w = 2 * math.pi / self.options.period
        k = np.arange(2, H + 1)
        # Harmonic k's position amplitude is |a_k| / (w k): draw it as a share of the band.
        Z[:, 1:H] = rng.uniform(-1, 1, (self.n, H - 1)) * pr.amplitude[:, None] * w * k / H
        Z[:, H:] = rng.uniform(-1, 1, (self.n, H - 1)) * pr.amplitude[:, None] * w * k / H
        for _ in range(30):
            if self.violation(Z.ravel()) == 0.0:
                break
            Z[:, 1:] *= 0.7
        return Z.ravel()

    def solve(self, x0: np.ndarray) -> tuple[np.ndarray, float, float]:
        result = minimize(
            lambda x: self._evaluate(x)[0], x0, jac=lambda x: self._evaluate(x)[1],
            method="SLSQP",
            constraints=[{"type": "ineq", "fun": lambda x: self._evaluate(x)[2],
                          "jac": lambda x: self._evaluate(x)[3]}],
            options={"maxiter": self.options.iterations, "ftol": 1e-7})
        x = self.pull_back(result.x)
        return x, self._evaluate(x)[0], self.violation(x)

    def pull_back(self, x: np.ndarray) -> np.ndarray:
        """``x`` shrunk towards the working pose (``s = 0``, inside every limit) by the
        largest factor ``s`` on a grid of 1/200 steps from 1 down with no aggregated
        constraint violated: SLSQP may stop just outside (its tolerance, its iteration limit).
        A scan, not a bisection: along the way a link may pass closer to the keep-out circle,
        so the feasible factors need not be one interval."""
        Z = np.asarray(x, float).reshape(self.n, self.nz)
        rest = np.zeros_like(Z)
        rest[:, 0] = self.problem.centre
        for factor in np.linspace(1.0, 0.0, 201):
            candidate = (rest + factor * (Z - rest)).ravel()
            if self.violation(candidate) == 0.0:
                return candidate
        return rest.ravel()


def check_options(options: ExcitationOptions) -> None:
    """Refuse options no excitation can have, before any model is built."""
    checks = [
        (math.isfinite(options.period) and 0.5 <= options.period <= 600.0,
         f"--period must be between 0.5 and 600 s, got {options.period}"),
        (2 <= options.harmonics <= 20,
         f"--harmonics must be between 2 and 20 (two at least: the series starts and ends at "
         f"rest), got {options.harmonics}"),
        (math.isfinite(options.amplitude_rad) and
         MIN_AMPLITUDE_RAD <= options.amplitude_rad <= math.pi,
         f"--amplitude-deg must be in [{math.degrees(MIN_AMPLITUDE_RAD):g}, 180] (a band of "
         f"a few encoder counts excites nothing), got {math.degrees(options.amplitude_rad):g}"),
        (math.isfinite(options.amplitude_m) and MIN_AMPLITUDE_M <= options.amplitude_m <= 1.0,
         f"--amplitude-mm must be in [{MIN_AMPLITUDE_M * 1000:g}, 1000] (a band of a few "
         f"encoder counts excites nothing), got {options.amplitude_m * 1000:g}"),
        (1 <= options.periods <= 1000,
         f"--periods must be between 1 and 1000, got {options.periods}"),
        (options.periods * options.period <= 3600.0,
         f"--periods x --period is {options.periods * options.period:g} s, more than the hour "
         "one as-fast run may hold: use fewer or shorter periods"),
        (0 <= options.seed < 2 ** 63, f"--seed must be a non-negative integer, got "
         f"{options.seed}"),
        (1 <= options.starts <= 100, f"--starts must be between 1 and 100, got "
         f"{options.starts}"),
        (1 <= options.iterations <= 10_000, f"--iterations must be between 1 and 10000, got "
         f"{options.iterations}"),
        (math.isfinite(options.limit_fraction) and 0 < options.limit_fraction < 1,
         f"--limit-fraction must be in (0, 1), got {options.limit_fraction}"),
        (math.isfinite(options.clearance) and 0 <= options.clearance <= 0.5,
         f"--clearance-mm must be in [0, 500], got {options.clearance * 1000:g}"),
    ]
    for ok, message in checks:
        if not ok:
            raise CochleaError(message)


def design(robot: str, arm: str | None = None,
           options: ExcitationOptions | None = None, description: str | Path | None = None,
           tracking: str | Path | None = None) -> Design:
    """The excitation of ``robot`` (for the serial system one ``arm``, default the first; the
    other holds still): see the module docstring. Raises :class:`CochleaError` for options no
    excitation can have, and when no start of the optimiser ends inside the limits."""
    options = options or ExcitationOptions()
    check_options(options)
    problem = _problem(robot, arm, options, description, tracking)
    opt = _Optimiser(problem, options)
    rng = np.random.default_rng(options.seed)
    best = None
    for _ in range(options.starts):
        x, value, violation = opt.solve(opt.start(rng))
        if violation == 0.0 and (best is None or value < best[1]):
            best = (x, value)
    if best is None:
        raise CochleaError(
            f"no excitation of {problem.unit} fits the limits from {options.starts} starts: "
            "lower --amplitude-deg / --amplitude-mm, lengthen --period, or use fewer "
            "--harmonics")
    series = opt.series(best[0])
    m = problem.model
    N = samples_per_period(options)
    times = np.arange(N) * options.period / N
    q, qd, qdd = series.evaluate(times)
    cond, scaled = conditions(m, q, qd, qdd)
    sine = hand_picked_sine(problem.centre, problem.amplitude, options.period)
    sine_cond, sine_scaled = conditions(m, *sine.evaluate(times))
    result = Design(robot, problem.unit, series, options, problem.centre, problem.amplitude,
                    cond, scaled, sine_cond, sine_scaled, held=problem.held,
                    description=description, study=problem.study,
                    study_label=problem.study_label)
    verify(problem, result)
    return result


def hand_picked_sine(centre: np.ndarray, amplitude: np.ndarray, period: float) -> FourierSeries:
    """One sine per joint at the fundamental, of the full amplitude: ``q_i = c_i + A_i sin(w
    t)`` (the comparison for the designed series; it does not start at rest)."""
    n = len(centre)
    w = 2 * math.pi / period
    a = np.zeros((n, 1))
    a[:, 0] = np.asarray(amplitude, float) * w
    return FourierSeries(period, np.asarray(centre, float).copy(), a, np.zeros((n, 1)))


def verify(problem: _Problem, result: Design) -> None:
    """Check the design at every control period of one period (1 kHz) against the limits
    themselves (the optimiser only saw its samples, with margins): positions inside the joint
    limits and the band, velocities and nominal torques inside their limits, and the robot's
    geometry (keep-out circle and the other arm; the mechanism's workspace). Fills the peaks
    of ``result``; raises :class:`CochleaError` naming the first violation."""
    m = problem.model
    options = result.options
    times = np.arange(int(round(options.period * CHECK_RATE_HZ)) + 1) / CHECK_RATE_HZ
    q, qd, qdd = result.series.evaluate(times)
    tau = (_stacked(m, q, qd, qdd) @ m.p_nominal).reshape(-1, m.nq).T
    vmax = np.array([j.velocity_limit for j in m.joints])
    emax = np.array([j.effort_limit for j in m.joints])
    tolerance = 1e-3 * problem.amplitude
    problems = []
    for i, j in enumerate(m.joints):
        lo, hi = j.position_limits
        if q[i].min() < max(lo, problem.low[i] - tolerance[i]) or \
                q[i].max() > min(hi, problem.high[i] + tolerance[i]):
            problems.append(f"joint {j.name} leaves its band or limits")
    result.peak_velocity = np.abs(qd).max(axis=1) / vmax
    result.peak_effort = np.abs(tau).max(axis=1) / emax
    for i, j in enumerate(m.joints):
        if result.peak_velocity[i] > 1.0:
            problems.append(f"joint {j.name} exceeds its velocity limit")
        if result.peak_effort[i] > 1.0:
            problems.append(f"joint {j.name} exceeds its effort limit")
    found, distances = problem.geometry.check_path(q, times)
    problems += found
    result.keep_out_distance = distances.get("keep_out_distance")
    result.clearance_distance = distances.get("clearance_distance")
    result.keep_out_volume_distance = distances.get("keep_out_volume_distance")
    if problems:
        raise CochleaError(f"the designed excitation of {problem.unit} fails the 1 kHz check "
                           f"({'; '.join(problems)}): use more --harmonics samples' margin by "
                           "lowering --limit-fraction or --amplitude-deg")


# --------------------------------------------------------------------------------------------
# The scenario
# --------------------------------------------------------------------------------------------


def _number_list(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def _robust_lines(robust) -> list[str]:
    """The study's robust-adaptation keys of ``[control]`` that it sets (none: no line)."""
    lines = []
    if robust.deadzone is not None:
        lines.append(f"adaptation_deadzone_SI = {_number_list(robust.deadzone)}")
    if robust.box_relative is not None:
        lines.append(f"estimate_box_relative = {float(robust.box_relative)!r}")
    if robust.sign != "free":
        lines.append(f'estimate_sign = "{robust.sign}"')
    if robust.static_ratio is not None:
        lines.append(f"static_friction_ratio = {_number_list(robust.static_ratio)}")
        lines.append(f"stribeck_velocity_SI = {_number_list(robust.stribeck_velocity)}")
    if robust.startup_ramp:
        lines.append(f"startup_ramp_s = {float(robust.startup_ramp)!r}")
    return lines


def scenario_text(result: Design, command: str, description_ref: str | None = None) -> str:
    """The joint-space scenario that tracks the design (``cochlea-run --scenario``): the
    control settings and gains of the robot's joint-space study for the realistic plant,
    every unit's own ``desired_joint`` (the excited one the series, the others holding
    their working pose), the initial state the path's start, at rest. ``description_ref``:
    the scenario's ``description`` key (a user's description; None: none, the shipped one)."""
    options = result.options
    study = result.study or load_scenario(TRACKING_SCENARIOS[result.robot])
    adapter = robot_adapter(result.robot)
    system = adapter.load(result.description)
    model = adapter.model(system, result.unit, parameterisation="base", actuators="all")
    kinds = ["rad" if j.type == "revolute" else "m" for j in model.joints]
    start = result.series.evaluate([0.0])[0][:, 0]
    paths = {}
    for unit in study.units:
        if unit.name == result.unit:
            paths[unit.name] = ([f"{result.series.formula(i)} {kind}"
                                 for i, kind in enumerate(kinds)], start)
        else:
            pose = result.held[unit.name]
            paths[unit.name] = ([f"{float(v)!r} {kind}" for v, kind in zip(pose, kinds)], pose)
    first = paths[study.units[0].name][0]
    leader = first[:len(adapter.layout(system, "joint").leader)]
    w = 2 * math.pi / options.period
    held = "; ".join(f"{name} holds still at its working pose" for name in result.held)
    study_name = result.study_label or study.path.name
    lines = [
        f"# Excitation for identification of the {result.robot} robot's {result.unit} (issue 14),",
        "# made by cochlea-excite (docs/excitation.md):",
        f"#   {comment(command)}",
        f"# seed {options.seed}, {options.starts} starts of SLSQP, {options.iterations} "
        "iterations each.",
        "#",
        f"# Per joint a finite Fourier series (Swevers): period {options.period:g} s (w_f = "
        f"{w:.6g} rad/s), {options.harmonics} harmonics, at rest (zero velocity and "
        "acceleration)",
        f"# at t = 0 and after each of the {options.periods} periods; within "
        f"{math.degrees(options.amplitude_rad):g} deg (revolute) / {options.amplitude_m * 1000:g}"
        " mm (prismatic) of the",
        f"# working pose; velocity and nominal torque within {options.limit_fraction:g} of "
        "their limits." + (f" {held}." if held else ""),
        "# Condition number of the stacked base regressor (actuators included) over one "
        "period:",
        f"#   designed {result.condition:.6g} (columns scaled to unit norm: "
        f"{result.scaled_condition:.6g})",
        f"#   hand-picked sine of the same amplitude {result.sine_condition:.6g} (scaled: "
        f"{result.sine_scaled_condition:.6g})",
        "# Peak |velocity| / limit per joint: "
        + ", ".join(f"{v:.2f}" for v in result.peak_velocity)
        + "; peak |nominal torque| / limit: " + ", ".join(f"{v:.2f}" for v in result.peak_effort),
    ]
    if result.keep_out_distance is not None and result.clearance_distance is not None:
        lines.append(f"# Closest approach of {result.unit}'s links: "
                     f"{result.keep_out_distance * 1000:.1f} mm to the cochlea centre, "
                     f"{result.clearance_distance * 1000:.1f} mm to the other arm.")
    else:
        lines += [f"# Closest approach of {result.unit}'s links: {v * 1000:.1f} mm to {what}."
                  for v, what in ((result.keep_out_distance, "the cochlea centre"),
                                  (result.clearance_distance, "the other arms"),
                                  (result.keep_out_volume_distance,
                                   "the description's keep-out volumes")) if v is not None]
    lines += [
        f"# Control: the settings and gains of {comment(study_name)} (controller "
        f"{study.controller}).",
        "# Every unit tracks its own desired_joint; the leader repeats the first unit's path.",
        "",
        'format = "cochlea-scenario/1"',
        f'robot = "{result.robot}"',
        *([f"description = {toml_string(description_ref)}"] if description_ref else []),
        'space = "joint"',
        f"duration_s = {options.periods * options.period!r}",
        "",
        "[control]",
        f"rate_Hz = {study.rate_hz!r}",
        f"plant_substeps = {study.plant_substeps}",
        f'variant = "{study.variant}"',
        f'parameterisation = "{study.parameterisation}"',
        f"adaptation_gain = {study.adaptation_gain!r}",
        f'adaptation = "{study.adaptation}"',
        f'initial_estimate = "{study.initial_estimate}"',
        f'actuators = "{study.controller_actuators}"',
        f"estimate_bound = {study.estimate_bound!r}",
        *_robust_lines(study.robust),
        "",
        "[desired]",
        "leader = [",
        *[f"  {toml_string(text)}," for text in leader],
        "]",
    ]
    for unit in study.units:
        texts, pose = paths[unit.name]
        lines += ["", "[[unit]]", f"name = {toml_string(unit.name)}",
                  "initial_joint = [" + ", ".join(f'"{float(v)!r} {kind}"'
                                                  for v, kind in zip(pose, kinds)) + "]",
                  "desired_joint = [", *[f"  {toml_string(text)}," for text in texts], "]",
                  "gains = { " + ", ".join(f"{k} = {_number_list(v)}"
                                           for k, v in unit.gains.items()) + " }"]
    joints = adapter.actuated_joints(system)
    no_gearbox = [j for j in joints if MODELS[j.motor.model].gearbox is None]
    if all(j.actuator.armature is not None for j in joints) and not no_gearbox:
        lines += ["", "[plant]", 'plant = "realistic"  # cochlea-run --plant ideal for the '
                  "rigid links; ignored on the motors", ""]
    elif all(j.actuator.armature is not None for j in joints):
        # The geared plant needs the motor model's gearbox data (backlash, stiffness,
        # Stribeck velocity), which only some models carry: the rigid links with their
        # drives' armature instead.
        lines += ["", "[plant]", 'plant = "ideal"  # the motor model '
                  f"{no_gearbox[0].motor.model} has no gearbox data for the realistic plant; "
                  "ignored on the motors", "armature = true", ""]
    else:  # the geared plant needs each joint's armature, which the description lacks
        lines += ["", "[plant]", 'plant = "ideal"  # the description gives no armature_kgm2 '
                  "for every joint, which the realistic plant needs; ignored on the motors", ""]
    return "\n".join(lines)
