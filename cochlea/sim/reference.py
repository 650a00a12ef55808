"""The reference closed loop in CasADi: controller sampled and held at the control rate, plant
integrated with RK4 sub-steps (or, with the gearbox, the geared plant's linearly implicit
steps: :func:`cochlea.robots.plant.gear_plant_step`; its state is the plant's own, the log and
the measurement its ``[q, qd]``), estimates integrated once per period.

The plant is the same symbolic model with its own parameters (the scenario may scale masses, add
a tip payload and viscous friction); measurements may carry Gaussian noise, whole encoder counts
of noise and a delay of whole periods, fixed or jittering; measurements and applied efforts may
sit on the motors' grids, and the motors may give another torque than their fit assumes (the
plant gets ``UnitSetup.torque_scale`` times the applied effort, the log the applied effort).
Everything that can be is fused into one CasADi Function per unit and period; the Python loop
only adds noise, delays measurements, rounds what CasADi cannot round exactly (measurements,
and with current quantisation the commands, between the controller's Function and the
plant's), scales the applied efforts by the torque-constant error and stores the log. The
generated C kernels (:mod:`cochlea.sim.compiled`) are checked against this loop.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from .result import SimulationResult, simulated_log, truncate
from .scenario import Scenario
from .setup import (
    MirrorFailure,
    UnitSetup,
    delay_ages,
    encoder_noise,
    mirror_stop,
    quantise,
)

#: The names of a follower's desired inputs (the outputs' ``xd``, ``xd_dot`` are taken).
_GIVEN_NAMES = ["xd_in", "xd_dot_in", "xd_ddot_in"]


def _given(u: UnitSetup) -> list:
    """The desired samples as inputs of a follower's period Functions (``mirror =
    "measured"``: computed from its leader's measured state, :meth:`Follow.samples`); none for
    a unit whose ``desired`` is a function of t."""
    if u.follow is None:
        return []
    nd = u.controller.n_desired
    return [ca.SX.sym(k, nd) for k in ("xd", "xd_dot", "xd_ddot")]


def _command(u: UnitSetup, h: float, t, x_meas, p_hat, given=()):
    """The controller's period on symbols: ``(tau, p_hat_next, errors, xd, xd_dot)``, ``tau``
    clipped to the joints' effort limits as the supervisor clips every command. ``given``:
    the desired samples as symbols (a follower's, :func:`_given`), else ``u.desired(t)``."""
    n = u.controller_model.nq
    xd, xd_dot, xd_ddot = given if len(given) else u.desired(t)
    tau, p_next, errors = u.controller.step(
        x_meas[:n], x_meas[n:], xd, xd_dot, xd_ddot, p_hat, ca.DM(u.gains), ca.DM(u.gamma),
        u.bound, h, *[ca.DM(v) for v in u.robust_inputs])
    limit = ca.DM(u.effort_limit)
    return ca.fmin(ca.fmax(tau, -limit), limit), p_next, errors, xd, xd_dot


def _plant(u: UnitSetup, h: float, substeps: int, x_true, tau):
    step = u.plant_function(substeps)
    extra = [] if u.drive is None else [ca.DM(u.drive)]
    return step(x_true, tau, ca.DM(u.plant_params), ca.DM(u.friction), h, *extra)


def _nx(u: UnitSetup) -> int:
    """The plant's state size: ``[q, qd]``, or with the gearbox ``[q, qd, theta, theta_dot]``."""
    return len(u.plant_x0)


def period_function(u: UnitSetup, h: float, substeps: int) -> ca.Function:
    """``(t, x_true, x_meas, p_hat) -> (x_true_next, p_hat_next, tau, errors, xd, xd_dot)``;
    ``tau`` is the command as applied: clipped to the joints' effort limits.

    With the drives' effort grid (``u.effort_grid``) the command is rounded between the
    controller and the plant, which CasADi cannot do exactly (it has no round half to even):
    use :func:`command_function` and :func:`plant_function` then, the rounding in numpy."""
    n = u.controller_model.nq
    t = ca.SX.sym("t")
    x_true = ca.SX.sym("x_true", _nx(u))
    x_meas = ca.SX.sym("x_meas", 2 * n)
    p_hat = ca.SX.sym("p_hat", u.controller.n_params)
    given = _given(u)
    tau, p_next, errors, xd, xd_dot = _command(u, h, t, x_meas, p_hat, given)
    x_next = _plant(u, h, substeps, x_true, tau)
    return ca.Function(f"period_{u.name}", [t, x_true, x_meas, p_hat, *given],
                       [x_next, p_next, tau, errors, xd, xd_dot],
                       ["t", "x_true", "x_meas", "p_hat"] + _GIVEN_NAMES[:len(given)],
                       ["x_true_next", "p_hat_next", "tau", "errors", "xd", "xd_dot"])


def command_function(u: UnitSetup, h: float) -> ca.Function:
    """``(t, x_meas, p_hat) -> (tau, p_hat_next, errors, xd, xd_dot)``: the controller's half
    of :func:`period_function`, ``tau`` clipped to the effort limits (not yet on the grid)."""
    n = u.controller_model.nq
    t = ca.SX.sym("t")
    x_meas = ca.SX.sym("x_meas", 2 * n)
    p_hat = ca.SX.sym("p_hat", u.controller.n_params)
    given = _given(u)
    return ca.Function(f"command_{u.name}", [t, x_meas, p_hat, *given],
                       list(_command(u, h, t, x_meas, p_hat, given)),
                       ["t", "x_meas", "p_hat"] + _GIVEN_NAMES[:len(given)],
                       ["tau", "p_hat_next", "errors", "xd", "xd_dot"])


def plant_function(u: UnitSetup, h: float, substeps: int) -> ca.Function:
    """``(x_true, tau) -> x_true_next``: the plant's half of :func:`period_function`."""
    n = u.controller_model.nq
    x_true = ca.SX.sym("x_true", _nx(u))
    tau = ca.SX.sym("tau", n)
    return ca.Function(f"plant_{u.name}", [x_true, tau], [_plant(u, h, substeps, x_true, tau)],
                       ["x_true", "tau"], ["x_true_next"])


def _period(u: UnitSetup, h: float, substeps: int):
    """One period as a callable ``(t, x_true, x_meas, p_hat) -> (x_true_next, p_hat_next, tau,
    errors, xd, xd_dot)`` (numpy arrays): the fused Function, or, with the drives' effort grid
    or the gearbox, the controller, the rounding in numpy and the plant's own Function called
    with the setup's numbers. The geared plant's stiff gear turns the last bit of a constant
    folded into the fused graph into a different stick/slip or rounding decision within a few
    hundred periods, so it runs the very Function the C kernel is generated from."""
    if u.effort_grid is None and not u.gearbox and u.torque_scale is None:
        fused = period_function(u, h, substeps)
        return lambda *args: [np.array(v).ravel() for v in fused(*args)]
    command, grid, scale = command_function(u, h), u.effort_grid, u.torque_scale
    step = u.plant_function(substeps)
    numbers = [u.plant_params, u.friction, h] + ([] if u.drive is None else [u.drive])
    if u.gearbox:  # the controller's own Function too, called with the setup's numbers
        command = _numeric_command(u, h)

    def period(t, x_true, x_meas, p_hat, *given):
        tau, p_next, errors, xd, xd_dot = (np.array(v).ravel() for v in command(t, x_meas,
                                                                                 p_hat, *given))
        if grid is not None:
            grid.apply(tau)
        # The motor's torque: the applied effort times its torque-constant error (logged: tau).
        applied = tau if scale is None else np.multiply(tau, scale)
        return [np.array(step(x_true, applied, *numbers)).ravel(), p_next, tau, errors, xd,
                xd_dot]

    return period


def _numeric_command(u: UnitSetup, h: float):
    """:func:`command_function`'s values from the desired Function and the controller's step
    called with numbers (what the C loop runs, bit for bit), the command clipped in numpy."""
    n = u.controller_model.nq
    limit = u.effort_limit
    gains, gamma, bound = ca.DM(u.gains), ca.DM(u.gamma), u.bound
    robust = [ca.DM(v) for v in u.robust_inputs]

    def command(t, x_meas, p_hat, *given):
        xd, xd_dot, xd_ddot = given if given else (ca.densify(v) for v in u.desired(t))
        tau, p_next, errors = u.controller.step(x_meas[:n], x_meas[n:], xd, xd_dot, xd_ddot,
                                                p_hat, gains, gamma, bound, h, *robust)
        tau = np.clip(np.array(tau).ravel(), -limit, limit)
        return tau, p_next, errors, xd, xd_dot

    return command


def simulate_reference(sc: Scenario, duration: float,
                       setups: list[UnitSetup]) -> SimulationResult:
    """Run the scenario on the CasADi Functions and return the log of every period (see
    :func:`cochlea.sim.simulate`)."""
    h = sc.period
    steps = int(round(duration / h))
    time = np.arange(steps) * h
    rng = np.random.default_rng(sc.plant.seed)
    ages = delay_ages(sc.plant, steps)  # None: every period delay_periods old
    counts = encoder_noise(sc.plant, steps, setups)
    logs = []
    diverged: dict[str, float] = {}
    stopped: MirrorFailure | None = None
    seen_by: list[np.ndarray] = []  # per unit, what its controller saw in each period
    for u, encoder in zip(setups, counts):
        n, n_p = u.controller_model.nq, u.controller.n_params
        given, rows = None, steps
        if u.follow is not None:  # its desired from the leader's measured states (run first)
            given, failure = u.follow.samples(seen_by[u.follow.leader], time)
            rows = len(given[0])
            if failure is not None and (stopped is None or failure.row < stopped.row):
                stopped = failure
        nd, ne = u.controller.n_desired, u.controller.n_desired + n
        period = _period(u, h, sc.plant_substeps)
        noise = np.concatenate([np.full(n, sc.plant.noise_q_std),
                                np.full(n, sc.plant.noise_qd_std)])
        X = np.empty((steps, 2 * n))
        # What the controller saw in each period (the true state when it measures exactly).
        exact = not (sc.plant.delay_periods or ages is not None or noise.any()
                     or u.quantum is not None)
        seen = X if exact else np.empty((steps, 2 * n))
        log = {k: np.empty((steps, s)) for k, s in
               [("tau", n), ("errors", ne), ("xd", nd), ("xd_dot", nd), ("p_hat", n_p)]}
        x = u.plant_x0.astype(float)  # the plant's state; the log and measurement: [q, qd]
        p_hat = u.p_hat0.astype(float).copy()
        delay = sc.plant.delay_periods
        follower_rows, rows = rows, steps
        for k in range(follower_rows):
            X[k] = x[:2 * n]
            measured = X[max(k - (delay if ages is None else ages[k]), 0)]
            if noise.any() or encoder is not None:
                # As the C loop's noise array: the Gaussian draw, then whole encoder counts.
                drawn = noise * rng.standard_normal(2 * n) if noise.any() else np.zeros(2 * n)
                if encoder is not None:
                    drawn[:n] += encoder[k]
                measured = measured + drawn
            if u.quantum is not None:  # as the motors report it: encoder and velocity counts
                measured = quantise(measured, u.quantum, u.grid_offset)
            if not exact:
                seen[k] = measured
            log["p_hat"][k] = p_hat
            extra = () if given is None else (given[0][k], given[1][k], given[2][k])
            x, p_hat, log["tau"][k], log["errors"][k], log["xd"][k], log["xd_dot"][k] = \
                period(time[k], x, measured, p_hat, *extra)
            if not (np.isfinite(x).all() and np.isfinite(p_hat).all()):
                diverged[u.name] = float(time[k])  # keep the log up to and including row k
                rows = k + 1
                break
        rows = min(rows, follower_rows)
        X = X[:rows]
        seen = X if exact else seen[:rows]
        seen_by.append(seen)
        log = {key: value[:rows] for key, value in log.items()}
        pose = np.array(u.fk_world.map(rows)(X[:, :n].T)).T
        logs.append(simulated_log(u, sc.space, X, seen, pose, log["xd"], log["xd_dot"],
                                  log["errors"], log["tau"], log["p_hat"]))
    rows = min(len(u.q) for u in logs)
    if rows < steps:  # every unit's log ends where the first one diverged (or stopped)
        truncate(logs, rows)
    return SimulationResult(sc, time[:rows], logs, diverged,
                            mirror_stop=mirror_stop(stopped, rows))
