"""What each controlled unit of a scenario needs to run: the robot's plan (models, initial state,
desired trajectory) plus the controller, its gains and the simulated plant's parameters.

The same setups drive the as-fast simulation (CasADi or C kernels), the real-time loop and the
emulator, so every one of them runs exactly the same controller on exactly the same plant.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from ..control import Controller, build
from ..dynamixel.control_table import MODELS
from ..errors import CochleaError
from ..kernels.bind import BufferedFunction
from ..robots import robot
from ..robots.adapter import keep_out_centre, sampled
from ..robots.model import INERTIAL_NAMES, RobotModel
from ..robots.motor_fit import bridge_compensates_friction, drive_terms, effort_grid
from ..robots.plant import gear_plant_step, plant_step
from . import scenario as scenario_mod


@dataclass
class EffortGrid:
    """What each joint's drive applies (scenario keys ``current_quantisation``,
    ``bridge_offset``), per joint, in N m (revolute) or N (prismatic). The bridge turns each
    command, already clipped to the effort limit ``limit`` by the supervisor, into a current:
    with the bridge's offset ``tau / a + I0 clip(tau / ramp, -1, 1)``, so the motor torque is
    ``tau + offset * clip(tau / ramp, -1, 1)``; then a whole number of Goal Current LSBs, and
    the motor saturates at its Current Limit; the applied effort is ::

        u = tau + offset * clip(tau / ramp, -1, 1)                  (offset: zero without it)
        clip(quantum * round(u / quantum), -bound, bound)       (a zero quantum: no rounding)

    rounded half to even (C's ``nearbyint``). ``quantum`` is one LSB through the fit's slope
    and the joint's ratio, ``saturation`` the effort at the Current Limit
    (:func:`cochlea.robots.motor_fit.effort_grid`: net of the fit's offset; the motor's torque
    ``a I_lim`` where the plant carries the gearbox's friction itself,
    :func:`cochlea.robots.motor_fit.drive_terms`). ``bound = min(saturation, limit)`` without
    the offset: bounding by ``limit`` too keeps the supervisor's promise where rounding would
    add up to half a quantum; with it ``bound = saturation``: the motor torque, friction
    compensation included, may exceed the command's limit."""

    quantum: np.ndarray
    saturation: np.ndarray
    limit: np.ndarray
    #: The bridge's friction compensation at the joint (N m or N) and its ramp, or None.
    offset: np.ndarray | None = None
    ramp: np.ndarray | None = None

    def __post_init__(self):
        if self.offset is None:
            self.bound = np.minimum(self.saturation, self.limit)
        else:
            self.bound = np.asarray(self.saturation, float).copy()
            self._scratch = np.empty_like(self.bound)
        self._lower = -self.bound
        self._rounds = bool((np.asarray(self.quantum) > 0).all())
        self._divisor = np.where(np.asarray(self.quantum) > 0, self.quantum, 1.0)

    @property
    def top(self) -> np.ndarray:
        """The effort a saturated command gets (per joint): a command clipped to ``limit``,
        rounded and bounded; no applied effort is larger."""
        return np.minimum(self.quantum * np.rint(self.limit / self.quantum), self.bound)

    def apply(self, tau: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """The applied efforts of the commands ``tau`` (clipped to ``limit``) into ``out``
        (default: in place); no allocation, the C driver's floating-point operations."""
        out = tau if out is None else out
        if self.offset is not None:  # the bridge's offset current, as the C driver adds it
            s = self._scratch
            np.divide(tau, self.ramp, out=s)
            np.clip(s, -1.0, 1.0, out=s)
            np.multiply(self.offset, s, out=s)
            np.add(tau, s, out=out)
            tau = out
        if self._rounds:
            np.divide(tau, self.quantum, out=out)
            np.rint(out, out=out)
            np.multiply(out, self.quantum, out=out)
        else:
            on_grid = self.quantum * np.rint(tau / self._divisor)
            np.copyto(out, np.where(self.quantum > 0, on_grid, tau))
        np.clip(out, self._lower, self.bound, out=out)
        return out


#: The rule of a following unit failed (``mirror = "measured"``): the stop rule's name.
MIRROR_RULE = "mirror-reach"


@dataclass(frozen=True)
class MirrorFailure:
    """The first period whose rule's pose is out of the follower's reach or not finite: the
    run's safe stop (:data:`MIRROR_RULE`), at ``row``'s time ``time`` (s)."""

    row: int
    time: float
    detail: str


@dataclass(frozen=True)
class Follow:
    """``mirror = "measured"``: a unit whose desired trajectory is the dual-arm rule applied,
    each period, to unit ``leader``'s measured state (:class:`cochlea.robots.adapter.
    FollowPlan`, with the scenario's startup ramp). What depends on time only is evaluated
    ahead, in chunks: ``timed(t) -> w = [a_lead (3), s, s_dot, s_ddot]``, the leader's desired
    tool acceleration and the ramp's blend (1, 0, 0 without a ramp); in the period,
    ``step(x_lead, w) -> (x, x_dot, x_ddot, margin)`` (dense outputs) from the leader's
    measured ``[q, qd]``; a NaN or a negative margin is out of reach (:meth:`failure`)."""

    leader: int
    leader_name: str
    name: str
    timed: ca.Function = field(repr=False)
    step: ca.Function = field(repr=False)
    reach: str = "out of its reach"  # what a negative margin means (FollowPlan.reach)

    def ok(self, outputs) -> bool:
        """Whether one period's ``step`` outputs (numpy arrays) may be tracked: all finite,
        the margin not negative. Allocates nothing."""
        for v in outputs[:3]:
            if not math.isfinite(float(v @ v)):
                return False
        return float(outputs[3][0]) >= 0.0

    def failure(self, row: int, time: float, x_lead: np.ndarray, outputs) -> MirrorFailure:
        """The safe stop's line for period ``row``, whose ``step`` outputs were not
        :meth:`ok`: the arm, the pose it was to take, and why."""
        n = len(x_lead) // 2
        margin = float(np.asarray(outputs[3]).ravel()[0])
        why = f"{self.reach} (margin {margin:.4g})" if margin < 0 else "not finite"
        return MirrorFailure(row, time, (
            f"{self.name}'s desired pose, the dual-arm rule on {self.leader_name}'s measured "
            f"pose (q = [{', '.join(f'{np.degrees(v):.2f}' for v in x_lead[:n])}] deg), is "
            f"{why}: {self.name} cannot follow it"))

    def evaluate(self, seen: np.ndarray, time: np.ndarray) -> tuple[list[np.ndarray],
                                                                     np.ndarray]:
        """``step``'s four outputs at every row of ``seen`` and ``time`` (each ``(N, size)``)
        and, per row, whether it fails (not :meth:`ok`)."""
        rows = min(len(seen), len(time))
        if rows == 0:
            sizes = [self.step.size1_out(i) for i in range(4)]
            return [np.zeros((0, k)) for k in sizes], np.zeros(0, bool)
        w = self.timed.map(rows)(np.asarray(time[:rows], float).reshape(1, -1))
        out = [np.array(v, float).T for v in self.step.map(rows)(seen[:rows].T, w)]
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(out[0]).all(axis=1) | ~np.isfinite(out[1]).all(axis=1) | \
                ~np.isfinite(out[2]).all(axis=1) | ~(out[3][:, 0] >= 0.0)
        return out, bad

    def samples(self, seen: np.ndarray, time: np.ndarray
                ) -> tuple[tuple[np.ndarray, np.ndarray, np.ndarray], MirrorFailure | None]:
        """The follower's ``(x, x_dot, x_ddot)`` (each ``(N, nd)``) at the rows of the
        leader's measured states ``seen`` (``(N, 2 n)``, what its controller saw) and times
        ``time``, up to the first period that fails, and that failure (None: none)."""
        out, bad = self.evaluate(seen, time)
        rows = len(bad)
        first = int(np.argmax(bad)) if bad.any() else rows
        failure = None
        if first < rows:
            failure = self.failure(first, float(time[first]), seen[first],
                                   [o[first] for o in out])
        return tuple(o[:first] for o in out[:3]), failure


def mirror_stop(failure: MirrorFailure | None, rows: int) -> dict | None:
    """An as-fast run's ``mirror_stop`` (:class:`~cochlea.sim.result.SimulationResult`): the
    safe stop a follower's failed rule makes at row ``rows`` (its logs end just before it),
    or None."""
    if failure is None or failure.row > rows:
        return None
    return {"rule": MIRROR_RULE, "time_s": failure.time, "detail": failure.detail}


def follow_setup(plan, leader_plan, space: str, ramp: float, start: np.ndarray | None
                 ) -> Follow:
    """The :class:`Follow` of ``plan`` (its ``follow``) after its leader's plan
    ``leader_plan`` (its ``desired`` with the scenario's startup ramp, if any); ``ramp``:
    ``startup_ramp_s`` (0: none), ``start``: the follower's pose the ramp starts from
    (:func:`ramp_start`)."""
    f = plan.follow
    t = ca.SX.sym("t")
    a_lead = f.lead_acceleration(*leader_plan.desired(t))
    if ramp > 0:
        s = quintic_blend(t / ramp)
        s_dot = ca.jacobian(s, t)
        blend = [s, s_dot, ca.jacobian(s_dot, t)]
    else:
        blend = [ca.SX(1.0), ca.SX(0.0), ca.SX(0.0)]
    timed = ca.Function(f"timed_{plan.name}", [t], [ca.densify(ca.vertcat(a_lead, *blend))],
                        ["t"], ["w"])
    x_lead = ca.SX.sym("x_lead", f.step.size1_in(0))
    w = ca.SX.sym("w", 6)
    x, x_dot, x_ddot, margin = f.step(x_lead, w[0:3])
    if ramp > 0:  # as startup_ramp blends the nominal path: x_r = s x + (1 - s) x_0
        s, s_dot, s_ddot = w[3], w[4], w[5]
        away = x - ca.DM(start)
        x, x_dot, x_ddot = (x - (1 - s) * away, s * x_dot + s_dot * away,
                            s * x_ddot + 2 * s_dot * x_dot + s_ddot * away)
    step = ca.Function(f"follow_{plan.name}", [x_lead, w],
                       [ca.densify(v) for v in (x, x_dot, x_ddot, margin)],
                       ["x_lead", "w"], ["x", "x_dot", "x_ddot", "margin"])
    return Follow(f.leader, leader_plan.name, plan.name, timed, step, f.reach)


@dataclass
class UnitSetup:
    """Everything one controlled unit needs, in SI."""

    name: str
    controller_model: RobotModel
    plant_model: RobotModel  # full inertial parameterisation
    plant_params: np.ndarray
    controller: Controller
    desired: ca.Function  # t -> (xd, xd_dot, xd_ddot) in the controller's space
    x0: np.ndarray  # [q0, qd0]
    gains: np.ndarray
    gamma: np.ndarray
    bound: float
    p_hat0: np.ndarray
    friction: np.ndarray
    joint_units: tuple[str, ...]  # "rad" | "m" per joint
    task_names: tuple[str, ...]
    task_units: tuple[str, ...]
    task_angles: tuple[int, ...]
    fk_world: ca.Function = field(repr=False)
    #: Tool points drawn in the path figure: label -> indices of (u, v) in the task pose.
    tool_points: tuple[tuple[str, tuple[int, int]], ...] = (("tool", (0, 1)),)
    #: Centre of the cochlea-centred circle in the path figure (m, world frame).
    centre: tuple[float, float] = (0.0, 0.0)
    #: Index of the joint whose value moves the keep-out centre along v (the parallel
    #: mechanism's slider: S = (0, d1)), or None for a fixed centre at ``centre``.
    moving_centre_joint: int | None = None
    #: The measurement grid per coordinate of ``[q, qd]``: measured values are
    #: ``offset + quantum * round((value - offset) / quantum)``; a zero quantum leaves the
    #: coordinate continuous. SI (rad, m, rad/s, m/s).
    quantum: np.ndarray | None = None
    grid_offset: np.ndarray | None = None
    #: Coulomb friction per joint (N m or N; the plant sticks and slips, see
    #: :func:`cochlea.robots.plant.plant_step`), or None: none.
    coulomb: np.ndarray | None = None
    #: The plant step's last input, or None (the rigid plant without dry friction): the rigid
    #: plant's ``dry`` = ``[Fc, Fs, vs]`` (3 n), the gear plant's ``drive`` (7 n, the rows of
    #: :data:`cochlea.robots.plant.GEAR_DRIVE`).
    drive: np.ndarray | None = None
    #: The geared plant with backlash (:func:`cochlea.robots.plant.gear_plant_step`): its
    #: state is ``[q, qd, theta, theta_dot]``; the measurement and the log are ``[q, qd]``.
    gearbox: bool = False
    #: The drives' effort resolution and saturation (:class:`EffortGrid`), or None: every
    #: command clipped to the effort limit is applied as it is.
    effort_grid: EffortGrid | None = None
    #: The controller's robust options, its Functions' trailing inputs in the order of
    #: :data:`cochlea.control.controllers.ROBUST_INPUTS` (dead zone, box, static friction), or
    #: None: the neutral ones (:meth:`robust_inputs`).
    robust: tuple[np.ndarray, ...] | None = None
    #: Per joint, the motor's torque over what the bridge's fit assumes (``1 +
    #: torque_constant_error``), or None: exactly the fit's. The plant gets the applied effort
    #: (after the drive's rounding and saturation) times it; the log keeps the applied effort.
    torque_scale: np.ndarray | None = None
    #: ``mirror = "measured"``: the unit's desired trajectory comes from its leader's measured
    #: state, period by period (:class:`Follow`); ``desired`` is then the nominal path (the
    #: rule on the leader's desired), which the checks before a run sample. None: ``desired``.
    follow: Follow | None = None

    @property
    def robust_inputs(self) -> tuple[np.ndarray, ...]:
        """The robust options every caller of the controller's step passes (SI)."""
        return self.robust if self.robust is not None else self.controller.neutral()

    @property
    def plant_x0(self) -> np.ndarray:
        """The plant's initial state: ``x0``, and with the gearbox each rotor where its link
        is (the teeth centred in the backlash), at its speed."""
        if not self.gearbox:
            return self.x0.copy()
        n = len(self.x0) // 2
        return np.concatenate([self.x0, self.x0[:n], self.x0[n:]])

    def plant_function(self, substeps: int) -> ca.Function:
        """The plant's step Function (inputs ``x, tau, p, friction, h`` and, with
        :attr:`drive`, that last)."""
        if self.gearbox:
            return gear_plant_step(self.plant_model, substeps)
        return plant_step(self.plant_model, substeps, coulomb=self.drive is not None)

    @property
    def effort_limit(self) -> np.ndarray:
        """Per joint, the largest effort a command may ask (N m or N): the supervisor clips
        every command to it, in the real-time loop and the as-fast simulation alike."""
        return np.array([j.effort_limit for j in self.controller_model.joints])

    def keep_out_centre(self, q) -> tuple:
        """Centre ``(u, v)`` of the safety keep-out circle (m, world frame) at joint position
        ``q``, or at each row of ``q``: the robot adapter's rule
        (:func:`cochlea.robots.adapter.keep_out_centre`) on this unit's plan. The supervisor's
        checks and the C drivers' keep-out points (:meth:`keep_out_reference`) take it from
        here."""
        return keep_out_centre(self.centre, self.moving_centre_joint, q)

    def keep_out_reference(self) -> tuple[float, float, int | None]:
        """The centre as a closed-loop driver takes it: ``(u, v, joint)``, the fixed centre
        and no joint, or the moving centre's joint with its u (and ``v`` 0: the joint's
        position is added) -- :meth:`keep_out_centre` at ``q = 0``."""
        u, v = self.keep_out_centre(np.zeros(self.controller_model.nq))
        return float(u), float(v), self.moving_centre_joint


def perturbed_parameters(full, plant: scenario_mod.Plant,
                         payload_points: dict[str, np.ndarray]) -> np.ndarray:
    """Full inertial parameters of the simulated robot: bodies scaled, payloads added.

    Works from the parameter names ``<body>.<m|mx|my|mz|Ixx|...>`` of any model: each body's
    parameters scale with ``plant.mass_scale`` (same shape, denser), and a point mass
    ``plant.payload_kg`` is added at ``payload_points[body]`` (m, body frame).
    """
    p = np.asarray(full.nominal, float).copy()
    bodies, owned = _parameter_owners(tuple(full.names))
    if plant.mass_scale is not None:
        for body, scale in zip(bodies, plant.mass_scale, strict=True):
            for i, _ in owned.get(body, ()):
                p[i] *= scale
    m = plant.payload_kg
    for body, point in payload_points.items():
        x, y, z = (list(point) + [0.0, 0.0])[:3]
        added = {"m": m, "mx": m * x, "my": m * y, "mz": m * z,
                 "Ixx": m * (y * y + z * z), "Iyy": m * (x * x + z * z),
                 "Izz": m * (x * x + y * y), "Ixy": -m * x * y, "Ixz": -m * x * z,
                 "Iyz": -m * y * z}
        for i, kind in owned.get(body, ()):
            if kind in added:
                p[i] += added[kind]
    return p


@functools.lru_cache(maxsize=64)
def _parameter_owners(names: tuple[str, ...]) -> tuple[tuple[str, ...], dict]:
    """The rigid bodies of a parameter list in order (an actuator's parameters, armature,
    neither scale nor carry payloads), and per owner of a parameter its ``(index, kind)``s in
    order: read once per list (a sweep's samples share it), not once a sample."""
    bodies = tuple(dict.fromkeys(name.rsplit(".", 1)[0] for name in names
                                 if name.rsplit(".", 1)[1] in INERTIAL_NAMES))
    owned: dict[str, list[tuple[int, str]]] = {}
    for i, name in enumerate(names):
        owner, kind = name.rsplit(".", 1)
        owned.setdefault(owner, []).append((i, kind))
    return bodies, {k: tuple(v) for k, v in owned.items()}


def measurement_grids(adapter, system, plant: scenario_mod.Plant
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """For every joint of the whole system in the loop's order, the measurement grid as the
    motor reports it: ``(quantum, offset)``, each ``(n_joints, 2)`` for (position, velocity).
    Positions in encoder counts (the motor model's, e.g. ``2 pi / 4096`` rad on the X series,
    through the joint's ratio and zero offset), velocities in Present Velocity LSBs (0.229 rpm
    on the X series). A zero quantum where the scenario's plant keeps the measurement
    continuous; None: neither. A model whose units are unsourced is refused (CochleaError)."""
    if not (plant.position_encoder or plant.velocity_register):
        return None
    joints = adapter.actuated_joints(system)
    scale = np.array([abs(j.ratio) for j in joints])  # joint travel per motor radian
    # Each motor model's own units (X series: 4096 counts, 0.229 rpm; control_table.MODELS).
    # A unit no source gave is refused, as the bridge refuses it (drives.joint_drives): the X
    # series' 4096 counts would quantise a P motor's position 250 times too coarsely.
    units = [MODELS[j.motor.model] for j in joints]
    for j, m in zip(joints, units):
        problem = m.units_problem()
        if problem:
            raise CochleaError(f"joint {j.name}: the scenario's plant reports what the motor "
                               f"measures, but {problem}")
    per_count = np.array([m.rad_per_count for m in units])
    per_lsb = np.array([m.rad_s_per_velocity_lsb for m in units])
    quantum = np.column_stack([scale * per_count * plant.position_encoder,
                               scale * per_lsb * plant.velocity_register])
    # q = direction * ratio * (theta - zero_offset): the position grid is shifted.
    offset = np.column_stack([[-j.motor.direction * j.ratio * j.motor.zero_offset
                               for j in joints], np.zeros(len(joints))])
    return quantum, offset


def plant_friction(adapter, system, plant: scenario_mod.Plant
                   ) -> tuple[np.ndarray, np.ndarray | None]:
    """For every joint of the whole system in the loop's order, the plant's viscous friction
    (N m s/rad or N s/m) and Coulomb friction (N m or N; None: the plant has none, so its step
    needs no stick-slip). The scenario's values (one per joint of a unit, the same for every
    unit) come first; then, with ``friction_from_description``, the description's actuators
    (zero where a joint declares none)."""
    joints = adapter.actuated_joints(system)

    def per_joint(given, field):
        if given is not None:
            return np.tile(np.asarray(given, float), len(joints) // len(given))
        if plant.friction_from_description:
            return np.array([getattr(j.actuator, field) or 0.0 for j in joints])
        return None

    viscous = per_joint(plant.viscous_friction, "viscous")
    coulomb = per_joint(plant.coulomb_friction, "coulomb")
    return (np.zeros(len(joints)) if viscous is None else viscous), coulomb


def _gearbox(j, what: str):
    """The motor model's gearbox of joint ``j`` (``what`` names the value wanted)."""
    gear = MODELS[j.motor.model].gearbox
    if gear is None:
        raise CochleaError(f"joint {j.name}: its motor model {j.motor.model} has no gearbox "
                           f"data for the plant's {what}: give it in [plant]")
    return gear


def plant_drive(adapter, system, plant: scenario_mod.Plant, coulomb: np.ndarray | None
                ) -> np.ndarray | None:
    """For every joint of the whole system in the loop's order, the plant step's last input as
    rows (``(rows, n_joints)``; None: the rigid plant without dry friction):

    * the rigid plant with dry friction: ``[Fc, Fs, vs]``: the Coulomb levels, the static ones
      (``static_friction_ratio`` times), the Stribeck velocities;
    * the gear plant (``gearbox``): :data:`cochlea.robots.plant.GEAR_DRIVE`: the rotor's
      inertia (the description's armature, required), the gear's backlash, stiffness and
      damping (the scenario's, or the motor model's :class:`~cochlea.dynamixel.control_table.
      Gearbox` through the joint's ratio: backlash times ``|ratio|``, stiffness and damping
      over ``ratio^2``), then the dry friction's three rows (zero levels without friction).

    Per-joint scenario values are one per joint of a unit, the same for every unit."""
    joints = adapter.actuated_joints(system)
    n = len(joints)

    def tiled(given):
        return np.tile(np.asarray(given, float), n // len(given))

    if plant.stribeck_velocity is not None:
        vs = tiled(plant.stribeck_velocity)
    elif coulomb is not None or plant.gearbox:
        vs = np.array([_gearbox(j, "Stribeck velocity").stribeck_velocity_rad_s * abs(j.ratio)
                       for j in joints])
    levels = np.zeros(n) if coulomb is None else coulomb
    dry = [] if coulomb is None and not plant.gearbox else \
        [levels, plant.static_friction_ratio * levels, vs]
    if not plant.gearbox:
        return None if coulomb is None else np.array(dry)
    armature = np.array([j.actuator.armature or 0.0 for j in joints])
    if not (armature > 0).all():
        bad = joints[int(np.argmin(armature > 0))].name
        raise CochleaError(f"joint {bad}: the gearbox plant needs the rotor's inertia: give the "
                           "joint's armature in the description")

    def gear(given, field, scale):
        if given is not None:
            return tiled(given)
        return np.array([getattr(_gearbox(j, field), field) * scale(abs(j.ratio))
                         for j in joints])

    backlash = (tiled(plant.backlash) if plant.backlash is not None else
                np.array([_gearbox(j, "backlash").backlash_rad * abs(j.ratio) for j in joints]))
    stiffness = gear(plant.gear_stiffness, "stiffness_Nm_rad", lambda r: 1.0 / r ** 2)
    damping = gear(plant.gear_damping, "damping_Nms_rad", lambda r: 1.0 / r ** 2)
    return np.array([armature, backlash, stiffness, damping, *dry])


def bridge_offset_applied(sc: scenario_mod.Scenario) -> bool:
    """Whether the scenario's plant gets the bridge's offset current: its ``bridge_offset``,
    "auto" resolved by :func:`cochlea.robots.motor_fit.bridge_compensates_friction` for the
    scenario's controller."""
    if sc.plant.bridge_offset == "auto":
        return bridge_compensates_friction(sc.controller_actuators)
    return bool(sc.plant.bridge_offset)


def adaptation_gains(sc: scenario_mod.Scenario, p_nominal: np.ndarray) -> np.ndarray:
    """The diagonal of Gamma. "relative": ``adaptation_gain * max(|p_i|, 1e-3 max|p|)^2``, so
    an armature of 3e-3 kg m^2 and a slider's 18 kg both move by the same fraction of themselves
    (with one gain for all, the small ones swing past their size and the loop goes unstable on
    the realistic plant); the floor keeps a zero nominal adaptable."""
    if sc.adaptation == "uniform":
        return sc.adaptation_gain * np.ones(len(p_nominal))
    size = np.abs(np.asarray(p_nominal, float))
    return sc.adaptation_gain * np.maximum(size, 1e-3 * max(size.max(), 1e-300)) ** 2


def drive_grids(adapter, system, plant: scenario_mod.Plant, offset: bool = False
                ) -> tuple[np.ndarray, ...] | None:
    """For every joint of the whole system in the loop's order, ``(quantum, saturation)`` of
    its drive's effort (N m or N, :func:`cochlea.robots.motor_fit.effort_grid`), and with the
    bridge's ``offset`` its offset and ramp too (:func:`cochlea.robots.motor_fit.drive_terms`),
    or None when the scenario's plant applies efforts as commanded.

    Without ``current_quantisation`` the quantum is zero and the saturation infinite. The
    saturation is the fit's effort at the Current Limit net of its offset (the motor's torque
    less the friction the offset stands for), or, where the plant carries the gearbox's
    friction itself (``friction_from_description``), the motor's torque ``a I_lim``."""
    if not (plant.current_quantisation or offset):
        return None
    joints = adapter.actuated_joints(system)
    terms = np.array([drive_terms(j.motor, j.ratio, j.effort_limit) for j in joints]).T
    quantum, motor_saturation, off, ramp = terms
    if plant.current_quantisation:
        saturation = (motor_saturation if plant.friction_from_description else
                      np.array([effort_grid(j.motor, j.ratio, j.effort_limit)[1]
                                for j in joints]))
    else:
        quantum, saturation = np.zeros(len(joints)), np.full(len(joints), np.inf)
    if not offset:
        return quantum, saturation
    return quantum, saturation, off, ramp


#: Periods of one as-fast simulation, which keeps every period in memory (about 1.2 kB each
#: for the serial system: 4.5 GB for an hour at 1 kHz). The real-time loop's own bound is
#: :data:`cochlea.sim.scenario.MAX_PERIODS`.
MAX_FAST_PERIODS = 3_600_000


def check_run_length(duration: float, rate_hz: float, what: str = "the duration",
                     max_periods: int = scenario_mod.MAX_PERIODS) -> int:
    """The number of periods of a run of ``duration`` s at ``rate_hz``, refused unless finite,
    at least one period and at most ``max_periods``; ``what`` names the option or key."""
    if not (isinstance(duration, (int, float)) and math.isfinite(duration) and duration > 0):
        raise CochleaError(f"{what} must be positive and finite (seconds), got "
                           f"{duration}")
    periods = int(round(duration * rate_hz))
    if periods < 1:
        raise CochleaError(f"{what} {duration:g} s is shorter than one control period "
                           f"({1.0 / rate_hz:g} s at {rate_hz:g} Hz): give at least "
                           f"{1.0 / rate_hz:g} s")
    if periods > max_periods:
        raise CochleaError(f"{what} {duration:g} s at {rate_hz:g} Hz is {periods:,} periods, "
                           f"more than the {max_periods:,} one run may hold: split the session "
                           f"into runs of at most {max_periods / rate_hz:g} s")
    return periods


def check_start(sc: scenario_mod.Scenario, plan) -> None:
    """A unit's initial state finite and inside its joints' position and velocity limits, and
    its desired trajectory finite over the run: what the supervisor would otherwise stop at
    the first period, or later, after the robot moved."""
    m = plan.controller_model
    q0, qd0 = plan.x0[:m.nq], plan.x0[m.nq:]
    where = f"scenario {sc.path}: unit {plan.name}"
    if not np.isfinite(plan.x0).all():
        raise CochleaError(f"{where}: the initial state {plan.x0.tolist()} is not finite: "
                           "check initial_joint / initial_task / initial_velocity")
    for j, q, qd in zip(m.joints, q0, qd0):
        lo, hi = j.position_limits
        unit, scale = ("deg", 180.0 / math.pi) if j.type == "revolute" else ("m", 1.0)
        if not lo - 1e-9 <= q <= hi + 1e-9:
            raise CochleaError(f"{where}: the initial position of joint {j.name}, "
                               f"{q * scale:.4g} {unit}, is outside its limits "
                               f"[{lo * scale:g}, {hi * scale:g}] {unit}")
        if not abs(qd) <= j.velocity_limit:
            raise CochleaError(f"{where}: the initial velocity of joint {j.name}, {qd:.4g} "
                               f"{'rad/s' if j.type == 'revolute' else 'm/s'}, exceeds its "
                               f"limit {j.velocity_limit:g}")
    names = ("position", "velocity", "acceleration")
    for times, outputs in sampled(plan.desired, sc.duration, sc.period):
        for order, values in enumerate(outputs):
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                i, k = bad[0]
                raise CochleaError(f"{where}: the desired {names[order]} of coordinate {i} is "
                                   f"{values[i, k]} at t = {times[k]:.6g} s (derived from "
                                   "[desired] leader): change the trajectory or shorten "
                                   "--duration")


#: Functions of one dense column out of dense columns in, bound to buffers once per process
#: (:func:`evaluate_column`), each kept alive with its buffers (so its id stays its own).
BUFFERED_CACHE_SIZE = 64
_BUFFERED: OrderedDict[int, tuple[ca.Function, BufferedFunction | None]] = OrderedDict()
_BUFFERED_LOCK = threading.Lock()


def _column_function(f: ca.Function) -> BufferedFunction | None:
    """``f`` bound to buffers, or None where its call converts more than dense columns."""
    if f.n_out() < 1 or not f.sparsity_out(0).is_dense() or f.size2_out(0) != 1:
        return None
    if not all(f.sparsity_in(i).is_dense() and f.size2_in(i) == 1 for i in range(f.n_in())):
        return None
    try:
        return BufferedFunction(f)
    except RuntimeError:  # a Function CasADi cannot buffer: called as before
        return None


def evaluate_column(f: ca.Function, *args: np.ndarray) -> np.ndarray:
    """``np.array(f(*args), float).ravel()`` of ``f``'s first output, bit for bit (the same
    Function evaluated on the same doubles), through buffers bound once per Function object
    instead of CasADi's conversions of every argument and result (0.12 ms a call against a
    few microseconds: every unit of every sweep sample is checked against gravity). Anything
    but dense columns of the right sizes goes through the call as before."""
    with _BUFFERED_LOCK:
        hit = _BUFFERED.get(id(f))
        if hit is None or hit[0] is not f:
            hit = _BUFFERED[id(f)] = (f, _column_function(f))
            while len(_BUFFERED) > BUFFERED_CACHE_SIZE:
                _BUFFERED.popitem(last=False)
        else:
            _BUFFERED.move_to_end(id(f))
        bound = hit[1]
        if bound is not None and len(args) == len(bound.inputs):
            values = [np.asarray(a, float) for a in args]
            if all(v.shape == b.shape for v, b in zip(values, bound.inputs)):
                for v, b in zip(values, bound.inputs):
                    b[:] = v
                bound()
                return bound.outputs[0].copy()
    return np.array(f(*args), float).ravel()


class GravityRefused(CochleaError):
    """Gravity at a unit's initial pose needs more effort than a joint's drive can give: the
    motor cannot hold the robot there (it would sag the moment torque is enabled). A sweep or a
    tuning search counts such a sample as refused (:data:`GRAVITY_RULE`), not as an error."""


#: The name a sweep's row gives a sample refused by :class:`GravityRefused` (its stop rule).
GRAVITY_RULE = "gravity-refused"


def check_gravity(sc: scenario_mod.Scenario, setups: list[UnitSetup],
                  saturation: np.ndarray | None = None, actuated: list | None = None) -> None:
    """Refuse (:class:`GravityRefused`) a run whose plant needs, against gravity at a unit's
    initial joint position, more effort on a joint than its drive can give: the joint's
    effort limit (the supervisor clips every command there) and, where the plant or the
    drives saturate at their Current Limit, that saturation through the fit (the unit's
    ``effort_grid``, or ``saturation``: per joint of the system in the loop's order, the real
    drives' of a hardware run). ``G`` is the plant's (masses scaled, payload added), so the
    scenario's ``mass_scale`` and ``payload_kg`` count, and so does its
    ``torque_constant_error`` (the simulated motors give ``1 + e`` times the applied effort;
    not with ``saturation``, real drives). ``actuated``: the system's actuated joints (the
    adapter's), whose motors the message names."""
    first = 0
    for u in setups:
        m = u.controller_model
        q0 = u.x0[:m.nq]
        gravity = np.abs(evaluate_column(u.plant_model.G_p, q0, u.plant_params))
        limit = u.effort_limit
        drive = None
        if u.effort_grid is not None:
            drive = u.effort_grid.saturation
        if saturation is not None:
            mine = np.asarray(saturation, float)[first:first + m.nq]
            drive = mine if drive is None else np.minimum(drive, mine)
        first += m.nq
        can = limit if drive is None else np.minimum(limit, drive)
        weaker = saturation is None and u.torque_scale is not None
        if weaker:  # the simulated motors give 1 + e times the applied effort
            can = can * u.torque_scale
        for j, joint in enumerate(m.joints):
            if gravity[j] <= can[j] * (1 + 1e-9):
                continue
            unit = "N m" if joint.type == "revolute" else "N"
            if drive is not None and drive[j] < limit[j]:
                motor = actuated[first - m.nq + j].motor if actuated is not None else None
                current = motor.current_limit_mA if motor is not None else None
                source = ("its drive's Current Limit" + (f" ({current:g} mA)" if current
                                                          else "") + " through the motor's fit, "
                          f"below the effort limit {limit[j]:.4g} {unit}")
                remedy = "raise the joint's Current Limit (current_limit_mA)"
            else:
                source = "its effort limit"
                remedy = ("raise the joint's " + ("torque_limit_Nm" if joint.type == "revolute"
                                                  else "force_limit_N") + " if the motor can")
            position = (f"{math.degrees(q0[j]):.4g} deg" if joint.type == "revolute"
                        else f"{q0[j]:.4g} m")
            if weaker:
                source += (f", times the plant's 1 + torque_constant_error = "
                           f"{u.torque_scale[j]:g}")
                remedy += ", or raise [plant] torque_constant_error"
            raise GravityRefused(
                f"scenario {sc.path}: unit {u.name}: gravity needs {gravity[j]:.4g} {unit} on "
                f"joint {joint.name} at its initial position ({position}), more than the "
                f"{can[j]:.4g} {unit} its drive can give ({source}): the motor cannot hold the "
                "robot there and it would sag the moment torque is enabled; lower [plant] "
                f"payload_kg or mass_scale, start from another pose, or {remedy}")


#: Distinct symbolic structures a process keeps (:func:`unit_setups`): each holds a few MB of
#: CasADi graphs; a sweep's worker meets one, or one per structural key it sweeps.
STRUCTURE_CACHE_SIZE = 8


@dataclass(frozen=True)
class _Structure:
    """What :func:`unit_setups` builds and checks once per symbolic structure: the units' plans
    (models, desired paths, initial states, already checked over the run) and controllers.
    Everything in it is immutable (CasADi Functions) or never written (the plans' arrays)."""

    system: Any  # kept alive: its id is part of the key
    plans: tuple
    controllers: tuple
    follows: tuple  # per unit, its Follow (mirror = "measured") or None


_STRUCTURES: OrderedDict[tuple, _Structure] = OrderedDict()


def _array_key(a) -> tuple | None:
    if a is None:
        return None
    a = np.asarray(a)
    return (a.dtype.str, a.shape, a.tobytes())


def structure_key(sc: scenario_mod.Scenario, system) -> tuple:
    """Everything of a scenario that the units' plans, controllers and up-front path checks
    depend on: robot and description (the loaded object: :func:`cochlea.sim.scenario.
    load_system` gives one per file content), space, run length and rate, parameterisation,
    the controller's and the plant's actuators, variant, the desired trajectory and each unit's
    initial state. Not in it: what only enters as numbers (masses, payload, friction, gains,
    Gamma, the estimate bound and start, delay, noise, seeds, the measurement and drive grids,
    the plant's RK4 sub-steps), which :func:`unit_setups` recomputes for every call."""
    units = tuple((u.name, _array_key(u.initial_joint), _array_key(u.initial_task),
                   _array_key(u.initial_velocity), u.elbow, u.desired_joint) for u in sc.units)
    return (sc.robot, id(system), sc.space, float(sc.duration), float(sc.rate_hz),
            sc.parameterisation, sc.controller_actuators, sc.plant_actuators, sc.variant,
            sc.controller, sc.mirror, tuple(sc.definitions.items()), sc.leader, units,
            float(sc.robust.startup_ramp), sc.task)


def clear_cache() -> None:
    """Forget every cached structure (:func:`unit_setups`)."""
    _STRUCTURES.clear()


def _structure(sc: scenario_mod.Scenario, adapter, system) -> _Structure:
    """Plans and controllers, every check of the desired path and initial state passed; the
    checks run in the order they always did, so a bad scenario gets the same error."""
    scenario_mod.check_desired(sc)
    plans, controllers, follows = [], [], []
    ramp = sc.robust.startup_ramp
    for plan in adapter.unit_plans(system, sc):
        start = ramp_start(plan, sc.space) if ramp > 0 else None
        if ramp > 0:
            plan = dataclasses.replace(plan, desired=startup_ramp(plan, sc.space, ramp))
        check_start(sc, plan)
        controllers.append(build(plan.controller_model, sc.controller, variant=sc.variant,
                                 task_angles=plan.task_angles, task=plan.task))
        follows.append(None if plan.follow is None else follow_setup(
            plan, plans[plan.follow.leader], sc.space, ramp, start))
        plans.append(plan)
    return _Structure(system, tuple(plans), tuple(controllers), tuple(follows))


def unit_setups(sc: scenario_mod.Scenario, cache: bool = True, *, gravity: bool = True,
                on_motors: bool = False) -> list[UnitSetup]:
    """Every controlled unit of the scenario, ready to run (the description read once, with
    the scenario). Everything the run's duration (``sc.duration``) lets us check before
    anything moves is checked here: the leader's formulas finite, each unit's initial state
    and desired path inside the workspace and the limits (the adapters' checks), and, unless
    ``gravity`` is False, that every joint's drive can hold the plant against gravity at the
    initial pose (:func:`check_gravity`; ``on_motors``: the efforts go through real drives, a
    hardware run, which saturate at their Current Limit whatever the scenario's plant says).

    ``cache``: reuse the models, controllers and checked paths of an earlier call with the
    same :func:`structure_key` in this process (the last :data:`STRUCTURE_CACHE_SIZE`), so a
    perturbed sample of a sweep costs only its numbers; the setups are the same, bit for bit,
    as with ``cache=False`` (which builds and checks everything again)."""
    adapter = robot(sc.robot)
    system = sc.system if sc.system is not None else scenario_mod.load_system(sc.robot,
                                                                              sc.description)
    check_run_length(sc.duration, sc.rate_hz, "duration_s")
    if not cache:
        structure = _structure(sc, adapter, system)
    else:
        key = structure_key(sc, system)
        structure = _STRUCTURES.get(key)
        # A dask worker runs samples on several threads: another may evict or add an entry
        # between these lines, which must not fail this sample.
        if structure is None:
            structure = _STRUCTURES[key] = _structure(sc, adapter, system)
            while len(_STRUCTURES) > STRUCTURE_CACHE_SIZE:
                with contextlib.suppress(KeyError):
                    _STRUCTURES.popitem(last=False)
        else:
            with contextlib.suppress(KeyError):
                _STRUCTURES.move_to_end(key)
    grids = measurement_grids(adapter, system, sc.plant)
    viscous, coulomb = plant_friction(adapter, system, sc.plant)
    drive_rows = plant_drive(adapter, system, sc.plant, coulomb)
    drives = drive_grids(adapter, system, sc.plant, bridge_offset_applied(sc))
    first_joint = 0  # the unit's first joint in the system
    setups = []
    for plan, controller, unit, follow in zip(structure.plans, structure.controllers, sc.units,
                                              structure.follows, strict=True):
        m = plan.controller_model
        gains = np.concatenate([unit.gains[k] for k in controller.gain_names])
        n_p = len(m.param_names)
        bound = sc.estimate_bound * max(euclidean_norm(m.p_nominal), 1e-12)
        p_hat0 = np.zeros(n_p) if sc.initial_estimate == "zero" else m.p_nominal.copy()
        robust = robust_inputs(sc, m, controller, bound)
        if robust is not None:  # the estimate starts in its box
            p_hat0 = np.minimum(np.maximum(p_hat0, robust[1]), robust[2])
        plant_params = perturbed_parameters(plan.plant_model.parameters, sc.plant,
                                            plan.payload_points)
        quantum = offset = drive = None
        mine = slice(first_joint, first_joint + m.nq)
        if grids is not None:  # this unit's joints, as [q..., qd...]
            quantum, offset = (grid[mine].T.ravel() for grid in grids)
        if drives is not None:
            limit = np.array([j.effort_limit for j in m.joints])
            drive = EffortGrid(*(d[mine] for d in drives[:2]), limit,
                               *(d[mine] for d in drives[2:]))
        first_joint += m.nq
        # The plan's initial state is shared by every set-up of its structure: a copy each.
        setups.append(UnitSetup(
            plan.name, m, plan.plant_model, plant_params, controller, plan.desired,
            plan.x0.copy(), gains, adaptation_gains(sc, m.p_nominal), bound, p_hat0,
            viscous[mine], plan.joint_units, plan.task_names, plan.task_units, plan.task_angles,
            plan.fk_world, tool_points=plan.tool_points, centre=plan.centre,
            moving_centre_joint=plan.moving_centre_joint,
            coulomb=None if coulomb is None else coulomb[mine],
            drive=None if drive_rows is None else drive_rows[:, mine].ravel(),
            gearbox=sc.plant.gearbox,
            quantum=quantum, grid_offset=offset, effort_grid=drive, robust=robust,
            torque_scale=torque_scale(sc.plant, m.nq), follow=follow))
    if gravity:
        real = None
        if on_motors:  # the motors' own Current Limits, whatever the simulated plant applies
            real = drive_grids(adapter, system, dataclasses.replace(
                sc.plant, current_quantisation=True))[1]
        check_gravity(sc, setups, real, adapter.actuated_joints(system))
    return setups


#: Parameter kinds (the name's last part) physics keeps non-negative: masses, the inertias
#: about the link frame's axes, armatures, viscous and Coulomb friction.
NON_NEGATIVE = ("m", "Ixx", "Iyy", "Izz", "Ia", "Fv", "Fc")


def estimate_box(sc: scenario_mod.Scenario, m: RobotModel) -> tuple[np.ndarray, np.ndarray]:
    """``(p_min, p_max)`` of ``[control] estimate_box_relative`` and ``estimate_sign``: each
    estimate within ``p_i +- k max(|p_i|, 1e-3 max|p|)`` of its nominal value ``p_i``, and
    with ``"physical"`` never below zero where the parameter is a mass, an inertia, an
    armature or a friction (:data:`NON_NEGATIVE`); +-inf where neither applies."""
    nominal = np.asarray(m.p_nominal, float)
    n_p = len(nominal)
    lower, upper = np.full(n_p, -np.inf), np.full(n_p, np.inf)
    k = sc.robust.box_relative
    if k is not None:
        size = np.maximum(np.abs(nominal), 1e-3 * max(np.abs(nominal).max(), 1e-300))
        lower, upper = nominal - k * size, nominal + k * size
    if sc.robust.sign == "physical":
        physical = np.array([name.rsplit(".", 1)[-1] in NON_NEGATIVE for name in m.param_names])
        lower = np.where(physical, np.maximum(lower, 0.0), lower)
    return lower, upper


def euclidean_norm(values) -> float:
    """``|values|``, the squares summed left to right: the same last bit on every machine.
    ``numpy.linalg.norm`` sums through the BLAS kernel the CPU selects, whose order differs
    between CPUs (on the realistic serial studies' 12 parameters an AMD EPYC and the machine
    that wrote generated_c/ differed in the last bit), and the estimate bound is written into
    the generated embedded C, which ``cochlea-codegen --check`` compares byte for byte."""
    total = 0.0
    for v in np.asarray(values, float).ravel():
        total += float(v) * float(v)
    return math.sqrt(total)


def robust_inputs(sc: scenario_mod.Scenario, m: RobotModel, controller: Controller,
                  bound: float) -> tuple[np.ndarray, ...] | None:
    """The controller's robust inputs (:data:`cochlea.control.controllers.ROBUST_INPUTS`) for
    one unit of the scenario, or None when every option is off (the neutral inputs). A box
    reaching outside the ball ``|p_hat| <= bound`` is refused: the step clips to the box last,
    so such a box could carry the estimate past the bound the supervisor stops on."""
    o = sc.robust
    if (o.deadzone is None and o.box_relative is None and o.sign == "free"
            and (o.static_ratio is None or not np.any(o.static_ratio > 1))):
        return None
    deadzone, _, _, excess, stribeck = controller.neutral()
    if o.deadzone is not None:
        deadzone = np.asarray(o.deadzone, float).copy()
    lower, upper = estimate_box(sc, m)
    far = np.maximum(np.abs(lower), np.abs(upper))
    if o.box_relative is not None and np.linalg.norm(far) > bound * (1 + 1e-12):
        raise CochleaError(
            f"scenario {sc.path}: [control] estimate_box_relative = {o.box_relative:g} puts "
            f"the box's far corner at |p| = {np.linalg.norm(far):.4g}, outside the projection "
            f"ball |p_hat| <= {bound:.4g} (estimate_bound = {sc.estimate_bound:g} times "
            "|p_nominal|): lower the box or raise estimate_bound")
    if o.static_ratio is not None:
        excess = np.asarray(o.static_ratio, float) - 1.0
        stribeck = np.asarray(o.stribeck_velocity, float).copy()
    return deadzone, lower, upper, excess, stribeck


def quintic_blend(tau):
    """``10 tau^3 - 15 tau^4 + 6 tau^5``: 0 to 1 over ``tau`` in [0, 1] with zero first and
    second derivatives at both ends (C2), held at 1 after."""
    tau = ca.fmin(ca.fmax(tau, 0), 1)
    return tau ** 3 * (10 - 15 * tau + 6 * tau ** 2)


def ramp_start(plan, space: str) -> np.ndarray:
    """Where :func:`startup_ramp` starts a unit's path: its initial joint position, or in task
    space its initial task pose (each angle within half a turn of the planned one at t = 0)."""
    m = plan.controller_model
    q0 = np.asarray(plan.x0[:m.nq], float)
    if space == "joint":
        return q0
    fk = plan.task[0] if plan.task is not None else plan.fk_world
    start = np.array(fk(q0), float).ravel()
    planned = np.array(plan.desired(0.0)[0], float).ravel()
    for i in plan.task_angles:
        start[i] += 2 * np.pi * np.round((planned[i] - start[i]) / (2 * np.pi))
    return start


def startup_ramp(plan, space: str, duration: float) -> ca.Function:
    """``plan.desired`` blended from the unit's initial pose onto the planned path over
    ``duration`` s (``[control] startup_ramp_s``): ``x_r = x_d + (1 - s(t / T)) (x_0 - x_d)``
    with the quintic ``s`` (:func:`quintic_blend`), so ``x_r(0) = x_0`` with zero velocity and
    acceleration, ``x_r = x_d`` exactly from ``T`` on, and velocity and acceleration
    continuous and finite throughout (exact derivatives, symbolic). ``x_0`` is the initial
    joint position, or in task space the initial task pose (each angle taken within half a
    turn of the planned one at t = 0)."""
    start = ramp_start(plan, space)
    t = ca.SX.sym("t")
    xd, xd_dot, xd_ddot = plan.desired(t)
    s = quintic_blend(t / duration)
    s_dot = ca.jacobian(s, t)
    s_ddot = ca.jacobian(s_dot, t)
    away = xd - ca.DM(start)
    # x_r = s x_d + (1 - s) x_0, differentiated with the planned path's own derivatives.
    x = xd - (1 - s) * away
    x_dot = s * xd_dot + s_dot * away
    x_ddot = s * xd_ddot + 2 * s_dot * xd_dot + s_ddot * away
    f = plan.desired
    return ca.Function(f"{f.name()}_ramped", [t], [x, x_dot, x_ddot], f.name_in(),
                       f.name_out())


def torque_scale(plant: scenario_mod.Plant, n: int) -> np.ndarray | None:
    """Per joint of a unit, ``1 + torque_constant_error`` (every unit alike), or None where the
    scenario gives no error (or only zeros: the plant gets the applied effort as it is)."""
    e = plant.torque_constant_error
    if e is None or not np.any(e):
        return None
    return 1.0 + np.broadcast_to(np.asarray(e, float), (n,))


#: Streams of the scenario's ``seed`` beside the Gaussian noise's (``default_rng(seed)``):
#: each disturbance draws from its own, so adding one leaves every other's numbers as they were.
JITTER_STREAM, ENCODER_STREAM = 1, 2


def disturbance_rng(plant: scenario_mod.Plant, stream: int) -> np.random.Generator:
    """The generator of one disturbance's stream (:data:`JITTER_STREAM`,
    :data:`ENCODER_STREAM`) of the scenario's seed."""
    return np.random.default_rng([plant.seed, stream])


def uniform_integers(u: np.ndarray, low: int, high: int) -> np.ndarray:
    """Uniform doubles in [0, 1) turned, in place, into integers ``low..high`` (as floats):
    ``low + min(floor(u (high - low + 1)), high - low)``. Drawn as doubles (one 64-bit output
    each), so a run drawn up front and the sim backend drawing period by period get the same
    numbers."""
    count = high - low + 1
    np.multiply(u, count, out=u)
    np.floor(u, out=u)
    np.minimum(u, count - 1, out=u)
    np.add(u, low, out=u)
    return u


def delay_ages(plant: scenario_mod.Plant, steps: int) -> np.ndarray | None:
    """Per period of a run, how many periods old the measurement is: ``delay_periods + j_k``
    with ``j_k`` uniform in ``0..delay_jitter_periods`` (one draw per period for the whole
    system, which is read at once), from the seed's :data:`JITTER_STREAM`; None without
    jitter (every period ``delay_periods`` old). Period k measures the state of period
    ``max(k - age_k, 0)``: never older than the log."""
    jitter = plant.delay_jitter_periods
    if not jitter:
        return None
    j = uniform_integers(disturbance_rng(plant, JITTER_STREAM).random(steps), 0, jitter)
    return plant.delay_periods + j.astype(np.int64)


def encoder_noise(plant: scenario_mod.Plant, steps: int, setups: list[UnitSetup]
                  ) -> list[np.ndarray | None]:
    """Per unit, ``(steps, n)``: each joint's position noise in whole encoder counts (uniform
    in ``-encoder_noise_counts..encoder_noise_counts``, per joint of the whole system and
    period, row by row, from the seed's :data:`ENCODER_STREAM`) times its encoder's quantum
    (``UnitSetup.quantum``); Nones without it. Added to the measured positions before the
    encoder grid: a whole number of quanta, so the measurement stays on the grid."""
    counts = plant.encoder_noise_counts
    if not counts:
        return [None] * len(setups)
    total = sum(u.controller_model.nq for u in setups)
    draws = uniform_integers(disturbance_rng(plant, ENCODER_STREAM).random((steps, total)),
                             -counts, counts)
    noise, first = [], 0
    for u in setups:
        n = u.controller_model.nq
        noise.append(draws[:, first:first + n] * u.quantum[:n])
        first += n
    return noise


def quantise(values: np.ndarray, quantum: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """``values`` (one state, or rows of states) on their measurement grid where the quantum is
    positive (round half to even, as C's ``nearbyint``), unchanged elsewhere."""
    on_grid = offset + quantum * np.rint((values - offset) / np.where(quantum > 0, quantum, 1.0))
    return np.where(quantum > 0, on_grid, values)


def measurements(states: np.ndarray, delay, noise: np.ndarray | None = None,
                 quantum: np.ndarray | None = None, offset: np.ndarray | None = None,
                 shifted: np.ndarray | None = None) -> np.ndarray:
    """What the controller saw in every period of a run, from the true states ``[q, qd]`` it
    logged: row k is ``states[max(k - delay, 0)] + noise[k]``, on the measurement grid where
    there is one; the same floating-point operations as the C driver (and
    :class:`MeasurementGrid`). ``delay``: whole periods, or per period (:func:`delay_ages`).
    ``states`` itself when the plant measures exactly. ``shifted``: those delayed rows
    ``states[max(k - delay, 0)]`` (one delay), when the caller has them without a copy (a
    view of the C driver's log: :meth:`cochlea.kernels.library.ClosedLoopLog.delayed`);
    never written."""
    jitter = np.ndim(delay) > 0
    if not jitter and not delay and noise is None and quantum is None:
        return states
    if jitter:
        delay = np.asarray(delay)[:len(states)]
        seen = states[np.maximum(np.arange(len(states)) - delay, 0)]
    elif shifted is not None:
        if shifted.shape != states.shape:
            raise ValueError(f"measurements: the shifted states are {shifted.shape}, the "
                             f"states {states.shape}")
        # The noise added into a new array: the same sums the copy and its += give.
        seen = shifted if noise is None else np.add(shifted, noise[:len(states)])
        return seen if quantum is None else quantise(seen, quantum, offset)
    else:  # one delay: the rows shifted by slices (a fancy index costs several times more)
        seen = np.empty_like(states)
        d = min(int(delay), len(states))
        seen[d:] = states[:len(states) - d]
        seen[:d] = states[:1]
    if noise is not None:
        seen += noise[:len(states)]
    if quantum is not None:
        seen = quantise(seen, quantum, offset)
    return seen


class MeasurementGrid:
    """:func:`quantise` for one state vector at a time, in place and without allocating: what
    the per-period loops (the Python loop over the C kernels, the sim backend) run each period.
    The same floating-point operations, so the same values."""

    def __init__(self, quantum: np.ndarray, offset: np.ndarray):
        self.quantum = np.asarray(quantum, float)
        self.offset = np.asarray(offset, float)
        self.on_grid = self.quantum > 0
        self.everywhere = bool(self.on_grid.all())
        self._divisor = np.where(self.on_grid, self.quantum, 1.0)
        self._scratch = np.empty_like(self.quantum)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """``x`` on the grid, in place; returned."""
        s = x if self.everywhere else self._scratch
        np.subtract(x, self.offset, out=s)
        np.divide(s, self._divisor, out=s)
        np.rint(s, out=s)
        np.multiply(self.quantum, s, out=s)
        np.add(self.offset, s, out=s)
        if not self.everywhere:
            np.copyto(x, s, where=self.on_grid)
        return x


def run_inputs(sc: scenario_mod.Scenario, duration: float | None,
               setups: list[UnitSetup] | None) -> tuple[float, list[UnitSetup]]:
    """A run's duration (default: the scenario's; s, positive) and its setups (default: made
    from the scenario): what every simulation entry point starts from."""
    duration = sc.duration if duration is None else duration
    check_run_length(duration, sc.rate_hz, max_periods=MAX_FAST_PERIODS)
    if setups is None:  # checked over this run's duration, not the scenario's
        setups = unit_setups(dataclasses.replace(sc, duration=duration))
    return duration, setups
