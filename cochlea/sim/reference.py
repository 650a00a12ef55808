"""The reference closed loop in CasADi: controller sampled and held at the control rate, plant
integrated with RK4 sub-steps, estimates integrated once per period.

The plant is the same symbolic model with its own parameters (the scenario may scale masses, add
a tip payload and viscous friction); measurements may carry Gaussian noise and a delay of whole
periods. Everything that can be is fused into one CasADi Function per unit and period; the
Python loop only adds noise, delays measurements and stores the log. The generated C kernels
(:mod:`cochlea.sim.compiled`) are checked against this loop.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..robots.plant import plant_step
from .result import SimulationResult, UnitLog
from .scenario import Scenario
from .setup import UnitSetup, quantise


def period_function(u: UnitSetup, h: float, substeps: int) -> ca.Function:
    """``(t, x_true, x_measured, p_hat) -> (x_true_next, p_hat_next, tau, errors, xd, xd_dot)``;
    ``tau`` is the command as applied: clipped to the joints' effort limits."""
    n = u.controller_model.nq
    t = ca.SX.sym("t")
    x_true = ca.SX.sym("x_true", 2 * n)
    x_meas = ca.SX.sym("x_meas", 2 * n)
    p_hat = ca.SX.sym("p_hat", u.controller.n_params)
    xd, xd_dot, xd_ddot = u.desired(t)
    tau, p_next, errors = u.controller.step(
        x_meas[:n], x_meas[n:], xd, xd_dot, xd_ddot, p_hat, ca.DM(u.gains), ca.DM(u.gamma),
        u.bound, h)
    limit = ca.DM(u.effort_limit)
    tau = ca.fmin(ca.fmax(tau, -limit), limit)  # as the supervisor clips every command
    step = plant_step(u.plant_model, substeps, coulomb=u.coulomb is not None)
    extra = [] if u.coulomb is None else [ca.DM(u.coulomb)]
    x_next = step(x_true, tau, ca.DM(u.plant_params), ca.DM(u.friction), h, *extra)
    return ca.Function(f"period_{u.name}", [t, x_true, x_meas, p_hat],
                       [x_next, p_next, tau, errors, xd, xd_dot],
                       ["t", "x_true", "x_meas", "p_hat"],
                       ["x_true_next", "p_hat_next", "tau", "errors", "xd", "xd_dot"])


def simulate_reference(sc: Scenario, duration: float,
                       setups: list[UnitSetup]) -> SimulationResult:
    """Run the scenario on the CasADi Functions and return the log of every period (see
    :func:`cochlea.sim.simulate`)."""
    h = sc.period
    steps = int(round(duration / h))
    time = np.arange(steps) * h
    rng = np.random.default_rng(sc.plant.seed)
    logs = []
    diverged: dict[str, float] = {}
    for u in setups:
        n, n_p = u.controller_model.nq, u.controller.n_params
        nd, ne = u.controller.n_desired, u.controller.n_desired + n
        period = period_function(u, h, sc.plant_substeps)
        X = np.empty((steps, 2 * n))
        log = {k: np.empty((steps, s)) for k, s in
               [("tau", n), ("errors", ne), ("xd", nd), ("xd_dot", nd), ("p_hat", n_p)]}
        x = u.x0.astype(float).copy()
        p_hat = u.p_hat0.astype(float).copy()
        noise = np.concatenate([np.full(n, sc.plant.noise_q_std),
                                np.full(n, sc.plant.noise_qd_std)])
        delay = sc.plant.delay_periods
        rows = steps
        for k in range(steps):
            X[k] = x
            measured = X[max(k - delay, 0)]
            if noise.any():
                measured = measured + noise * rng.standard_normal(2 * n)
            if u.quantum is not None:  # as the motors report it: encoder and velocity counts
                measured = quantise(measured, u.quantum, u.grid_offset)
            log["p_hat"][k] = p_hat
            out = period(time[k], x, measured, p_hat)
            x = np.array(out[0]).ravel()
            p_hat = np.array(out[1]).ravel()
            log["tau"][k] = np.array(out[2]).ravel()
            log["errors"][k] = np.array(out[3]).ravel()
            log["xd"][k] = np.array(out[4]).ravel()
            log["xd_dot"][k] = np.array(out[5]).ravel()
            if not (np.isfinite(x).all() and np.isfinite(p_hat).all()):
                diverged[u.name] = float(time[k])  # keep the log up to and including row k
                rows = k + 1
                break
        X = X[:rows]
        log = {key: value[:rows] for key, value in log.items()}
        pose = np.array(u.fk_world.map(rows)(X[:, :n].T)).T
        logs.append(UnitLog(u.name, sc.space, X[:, :n], X[:, n:], log["xd"], log["xd_dot"],
                            log["errors"], log["tau"], log["p_hat"], pose, u))
    rows = min(len(u.q) for u in logs)
    if rows < steps:  # every unit's log ends where the first one diverged
        for u in logs:
            for key in ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x"):
                setattr(u, key, getattr(u, key)[:rows])
    return SimulationResult(sc, time[:rows], logs, diverged)
