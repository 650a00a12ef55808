"""The simulated robot's period: the plant model integrated over one control period.

It lives with the robots because it is a property of a model alone: the simulation, the
code generator (its C kernel ``<unit>_plant_step``), the real-time sim backend and the
emulator all integrate the same Function.
"""

from __future__ import annotations

import casadi as ca

from .model import ACTUATOR_SUFFIX, RobotModel


def plant_step(plant: RobotModel, substeps: int, coulomb: bool = False) -> ca.Function:
    """One control period of a plant, torque held: RK4 with ``substeps`` equal steps.

    ``(x, tau, p, friction, h) -> x_next`` with ``x = [q, qd]``, ``p`` the plant's full
    inertial parameters and ``friction`` its viscous coefficients (N m s/rad or N s/m). Generic
    in the parameters, so the same Function is the simulation's plant and a C kernel.

    ``coulomb=True`` adds a last input, each joint's Coulomb friction level (N m or N), and
    names the Function ``<unit>_plant_step_coulomb``; a plant with its drives' armature is
    ``<unit>_armature_plant_step[_coulomb]``. Dry friction is decided once per RK4
    step, from the state at its start (an implicit, time-stepping treatment):

    * ``stop = M qd / dt + (tau - bias)`` is, per joint, the friction that would bring every
      joint to rest by the end of the step. A joint whose ``|stop|`` exceeds its level slides,
      against ``level * sign(stop)``; the others stick.
    * Sticking joints decelerate uniformly to rest within the step (``qdd = -qd / dt``); the
      torques that hold them are solved for together with the sliding joints' accelerations
      (one linear solve of the coupled system), clipped to their levels, and every friction
      torque is held over the step.
    * At the end of the step a sticking joint is at rest, where it decelerated to:
      ``q + qd dt / 2``. So a joint pushed below breakaway from rest stays exactly put, and
      one pushed past it moves with ``level`` against it.

    One pass, not an iteration over the stick/slip sets: a holding torque clipped at its level
    lets that joint slide from the next step on.
        """
    n = plant.nq
    x = ca.SX.sym("x", 2 * n)
    tau = ca.SX.sym("tau", n)
    p = ca.SX.sym("p", len(plant.param_names))
    friction = ca.SX.sym("friction", n)
    h = ca.SX.sym("h")
    inputs, names = [x, tau, p, friction, h], ["x", "tau", "p", "friction", "h"]
    level = ca.SX.sym("coulomb", n)
    if coulomb:
        inputs.append(level)
        names.append("coulomb")

    dt = h / substeps
    xk = x
    for _ in range(substeps):
        dry = ca.SX.zeros(n)
        if coulomb:
            q0, qd0 = xk[:n], xk[n:]
            M = plant.M_p(q0, p)
            rest = tau - friction * qd0 - plant.inverse_dynamics_p(q0, qd0, ca.SX.zeros(n), p)
            stop = M @ qd0 / dt + rest
            slides = ca.fabs(stop) > level
            sticks = (1 - slides) * (level > 0)
            sliding = -level * ca.sign(stop)
            # Unknowns: the sliding joints' accelerations and the sticking joints' torques.
            A = M @ ca.diag(slides) - ca.diag(1 - slides)
            z = ca.solve(A, rest + slides * sliding + M @ ((1 - slides) * qd0 / dt))
            dry = ca.fmin(ca.fmax(slides * sliding + (1 - slides) * z, -level), level)

        def f(state, dry=dry):
            q, qd = state[:n], state[n:]
            return ca.vertcat(qd, plant.forward_dynamics_p(q, qd, tau - friction * qd + dry, p))

        k1 = f(xk)
        k2 = f(xk + dt / 2 * k1)
        k3 = f(xk + dt / 2 * k2)
        k4 = f(xk + dt * k3)
        x_rk4 = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if coulomb:  # a sticking joint ends the step at rest, where it decelerated to
            x_rk4 = ca.vertcat(sticks * (q0 + qd0 * dt / 2) + (1 - sticks) * x_rk4[:n],
                               (1 - sticks) * x_rk4[n:])
        xk = x_rk4
    prefix = plant.name.replace("/", "_") + ACTUATOR_SUFFIX[plant.actuators]
    suffix = "_coulomb" if coulomb else ""
    return ca.Function(f"{prefix}_plant_step{suffix}", inputs, [xk], names, ["x_next"])
