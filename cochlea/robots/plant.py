"""The simulated robot's period: the plant model integrated over one control period.

It lives with the robots because it is a property of a model alone: the simulation, the
code generator (its C kernel ``<unit>_plant_step``), the real-time sim backend and the
emulator all integrate the same Function.
"""

from __future__ import annotations

import casadi as ca

from .model import RobotModel


def plant_step(plant: RobotModel, substeps: int) -> ca.Function:
    """One control period of a plant, torque held: RK4 with ``substeps`` equal steps.

    ``(x, tau, p, friction, h) -> x_next`` with ``x = [q, qd]``, ``p`` the plant's full
    inertial parameters and ``friction`` its viscous coefficients (N m s/rad or N s/m). Generic
    in the parameters, so the same Function is the simulation's plant and a C kernel.
    """
    n = plant.nq
    x = ca.SX.sym("x", 2 * n)
    tau = ca.SX.sym("tau", n)
    p = ca.SX.sym("p", len(plant.param_names))
    friction = ca.SX.sym("friction", n)
    h = ca.SX.sym("h")

    def f(state):
        q, qd = state[:n], state[n:]
        return ca.vertcat(qd, plant.forward_dynamics_p(q, qd, tau - friction * qd, p))

    dt = h / substeps
    xk = x
    for _ in range(substeps):
        k1 = f(xk)
        k2 = f(xk + dt / 2 * k1)
        k3 = f(xk + dt / 2 * k2)
        k4 = f(xk + dt * k3)
        xk = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    prefix = plant.name.replace("/", "_")
    return ca.Function(f"{prefix}_plant_step", [x, tau, p, friction, h], [xk],
                       ["x", "tau", "p", "friction", "h"], ["x_next"])
