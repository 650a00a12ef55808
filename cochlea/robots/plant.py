"""The simulated robot's period: the plant model integrated over one control period.

It lives with the robots because it is a property of a model alone: the simulation, the
code generator (its C kernel ``<unit>_plant_step``), the real-time sim backend and the
emulator all integrate the same Function.

Two plants:

* :func:`plant_step`, the rigid links (optionally with the drives' armature in the mass
  matrix), RK4, optional dry friction with sticking at the joint;
* :func:`gear_plant_step`, the geared drive with backlash (the dead-zone model): per joint a
  rotor and the link, coupled by the gear only while its teeth touch, the encoder on the link
  (output) side; a linearly implicit Euler step, since the engaged gear is stiff.
"""

from __future__ import annotations

import casadi as ca

from . import stage_trig as stage_trig_mod
from .model import ACTUATOR_SUFFIX, RobotModel
from .parallel.description import ParallelSystem
from .parallel.forward import forward_dynamics

#: Per joint, the rows of the gear plant's ``drive`` input (each ``n`` long, in this order).
GEAR_DRIVE = ("armature", "backlash", "stiffness", "damping", "coulomb", "static",
              "stribeck_velocity")
#: Rows of the rigid plant's dry-friction input ``dry``.
DRY = ("coulomb", "static", "stribeck_velocity")
#: Linearly implicit Euler steps of the gear plant per RK4 sub-step of the scenario
#: (``plant_substeps``): 20 at 1 kHz is 50 us, measured against 10x as many in
#: docs/models.md ("The geared plant").
GEAR_SUBSTEPS = 20
#: Added to the Stribeck velocity's square: a zero velocity (a driver's NULL input reads as
#: zeros) gives the Coulomb level instead of a 0/0.
_TINY = 1e-300


def stribeck_level(v, coulomb, static, vs):
    """The dry-friction level at velocity ``v``: ``Fc + (Fs - Fc) exp(-(v / vs)^2)``, ``Fs``
    at rest (breakaway), ``Fc`` sliding fast. With ``Fs == Fc`` exactly ``Fc``."""
    return coulomb + (static - coulomb) * ca.exp(-(v * v) / (vs * vs + _TINY))


def cheapest_forward_dynamics(plant: RobotModel):
    """The plant's forward dynamics ``(q, qd, tau, p) -> qdd`` in its cheapest exact form: a
    parallel mechanism's closed chain solved by blocks
    (:func:`cochlea.robots.parallel.forward.forward_dynamics`: 2389 operations a period of the
    shipped mechanism's general plant step instead of 9955 with the Lagrange model's QR
    solve, equal to rounding), any other model's ``forward_dynamics_p``."""
    if isinstance(getattr(plant.geometry, "system", None), ParallelSystem):
        return forward_dynamics(plant)
    return plant.forward_dynamics_p


def plant_step(plant: RobotModel, substeps: int, coulomb: bool = False,
               forward=None, stage_trig: bool = False) -> ca.Function:
    """One control period of a plant, torque held: RK4 with ``substeps`` equal steps.

    ``(x, tau, p, friction, h) -> x_next`` with ``x = [q, qd]``, ``p`` the plant's full
    inertial parameters and ``friction`` its viscous coefficients (N m s/rad or N s/m). Generic
    in the parameters, so the same Function is the simulation's plant and a C kernel.

    ``coulomb=True`` adds a last input ``dry`` = ``[Fc, Fs, vs]`` (``3 n``: per joint the
    Coulomb level and the static level, N m or N, and the Stribeck velocity, rad/s or m/s) and
    names the Function ``<unit>_plant_step_coulomb``; a plant with its drives' armature is
    ``<unit>_armature_plant_step[_coulomb]``. The level at velocity ``v`` is
    :func:`stribeck_level`: ``Fs`` at rest, tending to ``Fc`` sliding (``Fs = Fc``: plain
    Coulomb friction). Dry friction is decided once per RK4 step, from the state at its start
    (an implicit, time-stepping treatment), with the level at the joint's velocity there:

    * ``stop = M qd / dt + (tau - bias)`` is, per joint, the friction that would bring every
      joint to rest by the end of the step. A joint whose ``|stop|`` exceeds its level slides,
      against ``level * sign(stop)``; the others stick.
    * Sticking joints decelerate uniformly to rest within the step (``qdd = -qd / dt``); the
      torques that hold them are solved for together with the sliding joints' accelerations
      (one linear solve of the coupled system), clipped to their levels, and every friction
      torque is held over the step.
    * At the end of the step a sticking joint is at rest, where it decelerated to:
      ``q + qd dt / 2``. So a joint pushed below breakaway from rest (``Fs``) stays exactly
      put, and one pushed past it moves with the level against it.

    One pass, not an iteration over the stick/slip sets: a holding torque clipped at its level
    lets that joint slide from the next step on.

    ``forward``: a callable ``(q, qd, tau, p) -> qdd``, the forward dynamics to integrate;
    None: :func:`cheapest_forward_dynamics` (a parallel mechanism's block form, the model's
    ``forward_dynamics_p`` otherwise), so the simulation, the C kernels and the emulator
    integrate the same expression.

    ``stage_trig=True``: each RK4 step's later stages take the joints' sines and cosines from
    its first stage's by the angle sums (:mod:`cochlea.robots.stage_trig`), and the Function
    has a second output ``far``, the number of stage offsets past
    :data:`~cochlea.robots.stage_trig.REACH`: where it is not 0 the result is not to be used
    (take the plain period's). Equal to the plain period to rounding where ``far`` is 0.
    """
    forward_dynamics = cheapest_forward_dynamics(plant) if forward is None else forward
    lift = (stage_trig_mod.lifted(forward_dynamics, plant.nq, len(plant.param_names))
            if stage_trig else None)
    lifted_forward, angles = lift if lift is not None else (None, ())
    far = ca.SX(0)
    n = plant.nq
    x = ca.SX.sym("x", 2 * n)
    tau = ca.SX.sym("tau", n)
    p = ca.SX.sym("p", len(plant.param_names))
    friction = ca.SX.sym("friction", n)
    h = ca.SX.sym("h")
    inputs, names = [x, tau, p, friction, h], ["x", "tau", "p", "friction", "h"]
    dry_in = ca.SX.sym("dry", 3 * n)
    if coulomb:
        inputs.append(dry_in)
        names.append("dry")
    fc, fs, vs = dry_in[:n], dry_in[n:2 * n], dry_in[2 * n:]

    dt = h / substeps
    xk = x
    for _ in range(substeps):
        dry = ca.SX.zeros(n)
        if coulomb:
            q0, qd0 = xk[:n], xk[n:]
            level = stribeck_level(qd0, fc, fs, vs)
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

        if lift is None:
            def f(state, dry=dry):
                q, qd = state[:n], state[n:]
                return ca.vertcat(qd, forward_dynamics(q, qd, tau - friction * qd + dry, p))

            k1 = f(xk)
            k2 = f(xk + dt / 2 * k1)
            k3 = f(xk + dt / 2 * k2)
            k4 = f(xk + dt * k3)
        else:
            def f(state, trig, dry=dry):
                q, qd = state[:n], state[n:]
                return ca.vertcat(qd, lifted_forward(q, *trig, qd, tau - friction * qd + dry,
                                                     p))

            first = (ca.SX.zeros(n), ca.SX.zeros(n))
            for i in angles:
                first[0][i], first[1][i] = ca.sin(xk[i]), ca.cos(xk[i])
            k1 = f(xk, first)
            offset = dt / 2 * k1
            k2 = f(xk + offset, _shifted_trig(first, offset, angles))
            far = far + _past_reach(offset, angles)
            offset = dt / 2 * k2
            k3 = f(xk + offset, _shifted_trig(first, offset, angles))
            far = far + _past_reach(offset, angles)
            offset = dt * k3
            k4 = f(xk + offset, _shifted_trig(first, offset, angles))
            far = far + _past_reach(offset, angles)
        x_rk4 = xk + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        if coulomb:  # a sticking joint ends the step at rest, where it decelerated to
            x_rk4 = ca.vertcat(sticks * (q0 + qd0 * dt / 2) + (1 - sticks) * x_rk4[:n],
                               (1 - sticks) * x_rk4[n:])
        xk = x_rk4
    prefix = plant.name.replace("/", "_") + ACTUATOR_SUFFIX[plant.actuators]
    suffix = "_coulomb" if coulomb else ""
    if lift is not None:
        return ca.Function(f"{prefix}_plant_step{suffix}_stages", inputs, [xk, far], names,
                           ["x_next", "far"])
    return ca.Function(f"{prefix}_plant_step{suffix}", inputs, [xk], names, ["x_next"])


def _shifted_trig(first, offset, angles):
    """The sines and cosines of an RK4 stage at ``offset`` from the first stage, whose own are
    ``first`` (:func:`cochlea.robots.stage_trig.shifted`, for the joints ``angles``)."""
    s, c = ca.SX(first[0]), ca.SX(first[1])
    for i in angles:
        s[i], c[i] = stage_trig_mod.shifted(first[0][i], first[1][i], offset[i])
    return s, c


def _past_reach(offset, angles):
    """How many of the joints ``angles``' stage offsets are past the series' reach."""
    return sum((ca.fabs(offset[i]) > stage_trig_mod.REACH for i in angles), ca.SX(0))


def dead_zone(d, half):
    """``d - half`` above ``half``, ``d + half`` below ``-half``, zero in between."""
    return ca.if_else(d > half, d - half, ca.if_else(d < -half, d + half, 0))


def gear_plant_step(plant: RobotModel, substeps: int) -> ca.Function:
    """One control period of the geared plant with backlash (the dead-zone model of Nordin and
    Gutman 2002), torque held: ``(x, tau, p, friction, h, drive) -> x_next``.

    ``plant`` is the rigid-link model (no armature: the rotor is its own coordinate).
    ``x = [q, qd, theta, theta_dot]`` (``4 n``): the link (what the output-side encoder
    measures) and the rotor reflected to the joint. ``tau`` is the motor torque at the joint,
    ``friction`` the gearbox's viscous coefficients (on the rotor), ``drive`` the rows of
    :data:`GEAR_DRIVE` (``7 n``): the rotor's inertia (the description's armature, kg m^2 or
    kg; positive), the backlash (full width ``beta``, rad or m), the gear's stiffness ``k``
    (N m/rad or N/m) and damping ``c`` (N m s/rad or N s/m), the gearbox's Coulomb and static
    friction levels and Stribeck velocity (:func:`stribeck_level`). ::

        Ia theta_dd = tau - fv theta_d - F_dry - tau_g
        M(q) qdd + C(q, qd) qd + G(q) = tau_g
        tau_g = k dz(theta - q, beta / 2) + c (theta_d - qd)   while |theta - q| > beta / 2,
                0 otherwise (the teeth apart: the link moves free of its rotor).

    Integration: ``substeps * GEAR_SUBSTEPS`` linearly implicit steps of ``dt``. At the start
    of each step the engaged set and the rotor's stick/slip are decided; the gear torque is
    taken as its mean over the step by the trapezoidal rule, linearised in the new velocities,
    ``k dz0 + K (u0 + u1)`` with ``u = theta_d - qd`` and ``K = k dt / 4 + c / 2``, and the
    rotor's viscous friction likewise, so the new velocities come from one linear solve (the
    rotor is diagonal per joint: ``w1`` is eliminated, an ``n x n`` system for ``v1`` with
    ``M / dt`` plus a positive diagonal); the positions then move with the mean of the old and
    new velocities. Coriolis and gravity are taken at the start. For the engaged gear this is
    the trapezoidal rule: A-stable in the stiff gear (link 3 of a serial arm has 1/570 of its
    rotor's inertia) and without numerical damping, so the gear rings as lightly as its own
    damping lets it (implicit Euler would add damping ``omega^2 dt / 2`` to each mode: at
    920 rad/s and 50 us four times the MX-64 mesh's own).

    The rotor sticks when the friction that would stop it within the step (its end speed zero,
    the link's taken at the start) is within its level at its current speed (``Fs`` at rest):
    it then ends the step at rest, where it decelerated to (``theta + w dt / 2``: a rotor at
    rest stays exactly put), and the link sees it as fixed. Otherwise it slides against the
    level.
    """
    n = plant.nq
    x = ca.SX.sym("x", 4 * n)
    tau = ca.SX.sym("tau", n)
    p = ca.SX.sym("p", len(plant.param_names))
    friction = ca.SX.sym("friction", n)
    h = ca.SX.sym("h")
    drive = ca.SX.sym("drive", len(GEAR_DRIVE) * n)
    ia, beta, k, c, fc, fs, vs = (drive[i * n:(i + 1) * n] for i in range(len(GEAR_DRIVE)))
    dt = h / (substeps * GEAR_SUBSTEPS)
    q, v, th, w = x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:]
    for _ in range(substeps * GEAR_SUBSTEPS):
        d = th - q
        # Engaged at the step's start or by its end at the current speeds: a gear that meets
        # within the step works on it over the whole step, so the spring's energy at the end is
        # the work done (deciding at the start alone skips that work and pumps energy in).
        engaged = ca.fmax(ca.fabs(d), ca.fabs(d + dt * (w - v))) >= beta / 2
        K = engaged * (k * dt / 4 + c / 2)
        g0 = k * dead_zone(d, beta / 2) + K * (w - v)  # the step's mean gear torque: g0 + K u1
        level = stribeck_level(w, fc, fs, vs)
        push = ia * w / dt - friction * w / 2 + tau - g0  # on the rotor, but its own end speed
        stop = push + K * v
        sticks = (ca.fabs(stop) <= level) * (level > 0)
        slides = 1 - sticks
        r = push - slides * level * ca.sign(stop)
        D = ia / dt + friction / 2 + K
        M = plant.M_p(q, p)
        bias = plant.inverse_dynamics_p(q, v, ca.SX.zeros(n), p)
        A = M / dt + ca.diag(K - slides * K * K / D)
        v1 = ca.solve(A, M @ v / dt + g0 - bias + slides * K * r / D)
        w1 = slides * (r + K * v1) / D
        q = q + dt / 2 * (v + v1)
        th = th + dt / 2 * (w + w1)
        v, w = v1, w1
    prefix = plant.name.replace("/", "_") + ACTUATOR_SUFFIX[plant.actuators]
    return ca.Function(f"{prefix}_gear_plant_step", [x, tau, p, friction, h, drive],
                       [ca.vertcat(q, v, th, w)], ["x", "tau", "p", "friction", "h", "drive"],
                       ["x_next"])
