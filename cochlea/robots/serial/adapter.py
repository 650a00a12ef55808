"""The serial system in scenarios: serial arms, the first the leader, the others following it
by the dual-arm rule (point reflection through the cochlea centre, facing the leader).

The task coordinates are the scenario's ``[control] task`` (:mod:`.task`; default
``planar_yaw``). Planar 3R arms on a level base tracking ``planar_yaw`` (the shipped system,
the thesis's studies) use the closed-form inverse kinematics on an explicit elbow branch, and
joint-space followers track the mirrored pose through it; any other arm or task uses the
numeric solver (:func:`.ik.solve_ik`) for the initial state and to check the desired path,
and a joint-space follower of the leader needs the closed form."""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

from ...errors import CochleaError, KinematicsError, ModelError
from ...resources import ROBOTS_DIR, shipped_file
from ..adapter import (
    ActuatedJoint,
    ExcitationGeometry,
    FollowPlan,
    Layout,
    LinkFrames,
    RobotAdapter,
    ScenarioView,
    UnitPlan,
    UnitStart,
    desired_function,
    first_inside,
    frames_function,
    sampled,
)
from ..model import RobotModel
from . import excitation, identified, summary
from .chain import joint_transform, tool_offset
from .description import Arm, SerialSystem, load_serial, rpy_matrix
from .ik import (
    UnreachableTarget,
    check_sizes,
    elbow_cosine,
    follow_path,
    ik,
    ik_symbolic,
    planar_3r_lengths,
    solve_ik,
    world_to_base,
)
from .model import build_model
from .task import (
    DEFAULT_TASK,
    MAX_ORIENTATION_ERROR,
    TASKS,
    TaskSpace,
    mirrored,
    task_kinds,
    task_space,
    tool_world,
)
from .task import rpy_sx as _rpy_sx

TASK_NAMES = ("x", "y", "phi")
TASK_UNITS = ("m", "m", "rad")
TASK_ANGLES = (2,)


def _where(sc: ScenarioView) -> str:
    return str(getattr(sc, "path", sc.name))  # the file when the view has one


def _check_reachable(arm: Arm, pose_base_t: ca.SX, t: ca.SX, sc: ScenarioView,
                     limit: float = 1.0) -> None:
    """Refuse a follower trajectory that leaves the workspace, before anything runs;
    ``limit`` < 1 (``mirror = "measured"``: :data:`MIRROR_COS_LIMIT`) keeps the elbow that far
    from straight or folded."""
    c2 = ca.Function("c2", [t], [elbow_cosine(arm, pose_base_t)])
    for times, (values,) in sampled(c2, sc.duration, sc.period):
        values = values.ravel()
        bad = np.flatnonzero(~(np.abs(values) <= limit))
        if bad.size:
            k = bad[0]
            margin = "" if limit >= 1.0 else (
                f", beyond {limit:.4f}: mirror = \"measured\" stops a run whose follower's "
                f"elbow comes within {MIRROR_MIN_BEND_DEG:g} deg of straight or folded")
            raise UnreachableTarget(f"scenario {_where(sc)}: {arm.name}'s desired pose leaves the "
                                    f"workspace at t = {times[k]:.3f} s (cos th2 = "
                                    f"{values[k]:.4f}{margin})")


def _check_path(arm: Arm, q_t: ca.SX, tool_t: ca.SX, t: ca.SX, sc: ScenarioView,
                keep_out: float | None) -> None:
    """Refuse a desired path the supervisor would stop, before anything moves: a joint beyond
    its position limits, or (``keep_out``: the description's radius, None for none; joint and
    task space alike) the tool inside the keep-out circle around the cochlea centre, at any
    sampled time of the run."""
    lo = np.array([link.joint.position_limits[0] for link in arm.links])[:, None]
    hi = np.array([link.joint.position_limits[1] for link in arm.links])[:, None]
    path = ca.Function("path", [t], [q_t, ca.norm_2(tool_t[0:2])])
    for times, (q, r) in sampled(path, sc.duration, sc.period):
        outside = ~((lo <= q) & (q <= hi))
        if outside.any():
            j, k = np.argwhere(outside.T)[0][::-1]
            lo_j, hi_j = np.degrees(arm.links[j].joint.position_limits)
            raise UnreachableTarget(
                f"scenario {_where(sc)}: {arm.name}'s desired path takes joint "
                f"{arm.links[j].name} to {np.degrees(q[j, k]):.2f} deg at t = {times[k]:.3f} s, "
                f"outside its limits [{lo_j:g}, {hi_j:g}] deg: the supervisor would stop the "
                "run there; change the trajectory or shorten --duration")
        if keep_out is not None:
            inside = first_inside(times, r, keep_out)
            if inside is not None:
                when, near = inside
                raise UnreachableTarget(
                    f"scenario {_where(sc)}: {arm.name}'s desired tool path passes "
                    f"{near * 1000:.1f} mm from the cochlea centre at t = "
                    f"{when:.3f} s, inside the keep-out radius {keep_out * 1000:.1f} mm: the "
                    "supervisor would stop the run there; change the trajectory or shorten "
                    "--duration")


def _initial_joint(arm: Arm, unit: UnitStart) -> np.ndarray:
    """The initial joint position; the branch is explicit for a task-space initial pose."""
    if unit.initial_joint is not None:
        return unit.initial_joint
    reference = np.array([0.0, unit.elbow or 1, 0.0])
    q0, _, _ = ik(arm, unit.initial_task, reference)
    if unit.elbow is not None and np.sign(q0[1]) != unit.elbow:
        raise UnreachableTarget(f"{arm.name}: the initial pose has no solution on elbow branch "
                                f"{unit.elbow:+d}")
    return q0


def _closed_form(arm: Arm) -> bool:
    """Whether the arm is a planar 3R on a level base (the closed-form inverse kinematics)."""
    try:
        planar_3r_lengths(arm)
    except ModelError:
        return False
    return arm.base_is_level


def _numeric_initial(arm: Arm, space: TaskSpace, unit: UnitStart) -> np.ndarray:
    """The initial joint position of a task-space initial pose, by the numeric solver from
    the middle of the joint limits (``elbow``: on that sign of the second joint)."""
    return solve_ik(arm, space, unit.initial_task, elbow=unit.elbow)


def _check_task_path(arm: Arm, space: TaskSpace, pose_t: ca.SX, t: ca.SX, sc: ScenarioView,
                     q0: np.ndarray, keep_out: float | None) -> None:
    """Refuse, before anything moves, a task-space desired path that the supervisor would
    stop or the controller cannot track: its tool inside the keep-out circle (every period),
    or a pose out of reach within the joint limits or singular (inverse kinematics from the
    initial joint position along :data:`PATH_SAMPLES` evenly spaced times), or (``pose``) an
    initial orientation error beyond :data:`~.task.MAX_ORIENTATION_ERROR`."""
    radius = ca.Function("radius", [t], [ca.norm_2(pose_t[0:2])])
    for times, (r,) in sampled(radius, sc.duration, sc.period) if keep_out is not None else ():
        inside = np.flatnonzero(~(r.ravel() >= keep_out))
        if inside.size:
            k = inside[0]
            raise UnreachableTarget(
                f"scenario {_where(sc)}: {arm.name}'s desired tool path passes "
                f"{r.ravel()[k] * 1000:.1f} mm from the cochlea centre at t = {times[k]:.3f} s, "
                f"inside the keep-out radius {keep_out * 1000:.1f} mm: the supervisor would "
                "stop the run there; change the trajectory or shorten --duration")
    f = ca.Function("pose", [t], [pose_t])
    times = np.linspace(0.0, sc.duration, min(PATH_SAMPLES, int(sc.duration / sc.period) + 1))
    targets = np.array(f.map(len(times))(times.reshape(1, -1)), float)
    if space.task == "pose":
        _, R = tool_world(arm, ca.DM(q0))
        R_d = _rpy_sx(ca.DM(targets[3:6, 0]))
        cos = (float(ca.evalf(ca.trace(R_d.T @ ca.evalf(R)))) - 1.0) / 2.0
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        if angle > MAX_ORIENTATION_ERROR:
            raise UnreachableTarget(
                f"scenario {_where(sc)}: {arm.name}'s initial orientation is "
                f"{np.degrees(angle):.1f} deg from the desired one at t = 0, more than "
                f"{np.degrees(MAX_ORIENTATION_ERROR):.0f} deg (the orientation error's Jacobian "
                "is singular at 90 deg): start nearer the desired pose")
    try:
        q_start = solve_ik(arm, space, targets[:, 0], seeds=(q0,))
    except KinematicsError as exc:
        raise type(exc)(f"scenario {_where(sc)}: {arm.name}'s desired path at t = 0: {exc}"
                        ) from None
    try:
        follow_path(arm, space, targets, times, q_start)
    except KinematicsError as exc:
        raise type(exc)(f"scenario {_where(sc)}: {arm.name}'s desired path: {exc}") from None


#: Times at which a task-space path is solved by the numeric inverse kinematics (evenly
#: spaced over the run, at most one a period).
PATH_SAMPLES = 2001


#: ``mirror = "measured"``: the follower's elbow must stay this far (deg) from straight or
#: folded, the workspace's edge, where the inverse kinematics' derivatives grow without bound
#: (``dth2/dt = -d(cos th2)/dt / sin th2``: 5.8 times at 10 deg). The rule's pose beyond it is
#: the run's safe stop (rule ``mirror-reach``); the nominal path is checked against it before.
MIRROR_MIN_BEND_DEG = 10.0
MIRROR_COS_LIMIT = float(np.cos(np.radians(MIRROR_MIN_BEND_DEG)))


def _rule(pose):
    """The dual-arm rule on a ``planar_yaw`` pose (world frame): the point reflection through
    the cochlea centre, the tool turned by 180 deg to face the other's."""
    return ca.vertcat(-pose[0], -pose[1], pose[2] + np.pi)


def _follow_plan(lead: Arm, lead_model: RobotModel, lead_space: str, arm: Arm, space: str,
                 elbow: int, offsets, turns: float) -> FollowPlan:
    """``mirror = "measured"``: the rule applied to the leader's measured pose
    ``fk_world(q)``, its velocity to the measured tool velocity ``J_world(q) qd``, its
    acceleration to the leader's desired tool acceleration (nothing measures one); in joint
    space through the closed-form IK of ``arm``'s branch (``elbow``, ``offsets``: the nominal
    path's) and its first two derivatives. The margin is ``MIRROR_COS_LIMIT - |cos th2|`` of
    the rule's pose in ``arm``'s base (:func:`.ik.elbow_cosine`): negative out of reach (its
    elbow within :data:`MIRROR_MIN_BEND_DEG` of straight or folded). ``turns`` (rad, whole
    turns) takes the measured heading to the leader's desired one's turn (the joints' sum may
    be a turn away from the heading the scenario writes), once for the run."""
    n = len(lead.links)
    x_lead, a_lead = ca.SX.sym("x_lead", 2 * n), ca.SX.sym("a_lead", 3)
    q, qd = x_lead[:n], x_lead[n:]
    measured = lead_model.fk_world(q)
    pose = _rule(ca.vertcat(measured[0], measured[1], measured[2] + turns))
    flip = ca.DM(np.diag([-1.0, -1.0, 1.0]))
    velocity, acceleration = flip @ (lead_model.J_world(q) @ qd), flip @ a_lead
    margin = MIRROR_COS_LIMIT - ca.fabs(elbow_cosine(arm, world_to_base(arm, pose)))
    if space == "task":
        x, x_dot, x_ddot = pose, velocity, acceleration
    else:
        p, v, a = ca.SX.sym("p", 3), ca.SX.sym("v", 3), ca.SX.sym("a", 3)
        joints = ik_symbolic(arm, world_to_base(arm, p), elbow, offsets)
        dq_dp = ca.jacobian(joints, p)
        joints_dot = dq_dp @ v
        joints_ddot = dq_dp @ a + ca.jacobian(joints_dot, p) @ v
        x, x_dot, x_ddot = ca.Function("ik_path", [p, v, a], [joints, joints_dot, joints_ddot])(
            pose, velocity, acceleration)
    step = ca.Function(f"follow_{arm.name}", [x_lead, a_lead], [x, x_dot, x_ddot, margin],
                       ["x_lead", "a_lead"], ["x", "x_dot", "x_ddot", "margin"])
    xs, xs_dot, xs_ddot = (ca.SX.sym(k, n) for k in ("x", "x_dot", "x_ddot"))
    if lead_space == "task":
        tool_acc = xs_ddot
    else:  # d2/dt2 fk(q(t)) = J(q) qdd + (dJ/dt) qd
        tool_vel = lead_model.J_world(xs) @ xs_dot
        tool_acc = lead_model.J_world(xs) @ xs_ddot + ca.jacobian(tool_vel, xs) @ xs_dot
    lead_acceleration = ca.Function(f"lead_acceleration_{lead.name}", [xs, xs_dot, xs_ddot],
                                    [tool_acc], ["x", "x_dot", "x_ddot"], ["a_lead"])
    return FollowPlan(0, step, lead_acceleration,
                      f"out of its reach: its elbow would be within {MIRROR_MIN_BEND_DEG:g} deg "
                      "of straight or folded")


def _check_start_reachable(lead: Arm, lead_model: RobotModel, q0_lead, arm: Arm,
                           sc: ScenarioView) -> None:
    """``mirror = "measured"``: the rule's pose at t = 0, from the leader's initial position
    (what the first period measures), within ``arm``'s reach, refused before anything moves."""
    pose = np.array(ca.evalf(_rule(lead_model.fk_world(ca.DM(q0_lead))))).ravel()
    c2 = float(ca.evalf(elbow_cosine(arm, world_to_base(arm, pose))))
    if not abs(c2) <= MIRROR_COS_LIMIT:
        raise UnreachableTarget(
            f"scenario {_where(sc)}: mirror = \"measured\": {arm.name}'s desired pose at t = 0, "
            f"the mirror of {lead.name}'s initial pose (x = {pose[0]:.4f} m, y = "
            f"{pose[1]:.4f} m, phi = {np.degrees(pose[2]):.2f} deg), is out of "
            f"{arm.name}'s reach (cos th2 = {c2:.4f}, at most {MIRROR_COS_LIMIT:.4f} in "
            f"magnitude: the elbow {MIRROR_MIN_BEND_DEG:g} deg from straight or folded): start "
            f"{lead.name} elsewhere")


class SerialRobot(RobotAdapter):
    name = "serial"
    task_spaces = TASKS
    default_task = DEFAULT_TASK
    mirror_modes = ("desired", "measured")
    method = "newton-euler"
    units_are_arms = True
    excitation_study = "serial_joint_realistic"
    calibration_reference = {
        "*": (0.0, "links aligned: link 1 along its base's x axis (base_yaw_deg), every "
                   "other link in line with the one before it (the arm straight)")}
    positive_direction = "counter-clockwise seen from above"

    def load(self, description: str | Path | None = None) -> SerialSystem:
        return load_serial(description if description is not None
                           else shipped_file(ROBOTS_DIR, self.name))

    def model(self, system: SerialSystem, arm: str | Arm | None = None,
              parameterisation: str = "inertial", method: str | None = None,
              actuators: str = "none") -> RobotModel:
        return build_model(system, arm, parameterisation, method or self.method, actuators)

    def layout(self, system: SerialSystem, space: str, task: str | None = None) -> Layout:
        n = len(system.arms[0].links)
        kinds = tuple("length" if link.joint.type == "prismatic" else "angle"
                      for link in system.arms[0].links)
        task = task_kinds(task or DEFAULT_TASK)
        return Layout(leader=kinds if space == "joint" else task, joint=kinds, task=task,
                      units=tuple(a.name for a in system.arms), n_joint=n, n_task=len(task),
                      n_bodies=n)

    def unit_plans(self, system: SerialSystem, sc: ScenarioView) -> list[UnitPlan]:
        task = getattr(sc, "task", None) or DEFAULT_TASK
        if task == DEFAULT_TASK and all(_closed_form(a) for a in system.arms):
            return self._closed_form_plans(system, sc)
        if getattr(sc, "mirror", "desired") == "measured":
            raise KinematicsError(
                f"scenario {_where(sc)}: mirror = \"measured\" needs the closed-form inverse "
                f"kinematics (planar 3R arms on a level base, task {DEFAULT_TASK!r}; this is "
                f"task {task!r}): use mirror = \"desired\"")
        return self._numeric_plans(system, sc, task)

    def _numeric_plans(self, system: SerialSystem, sc: ScenarioView, task: str
                       ) -> list[UnitPlan]:
        """Any chain, any task space: numeric inverse kinematics for the initial state and the
        desired path's checks; a joint-space follower of the leader is refused (it needs the
        closed form)."""
        t = ca.SX.sym("t")
        x_lead, _, _ = sc.desired_leader()(t)
        models = {a.name: self.model(system, a, sc.parameterisation,
                                     actuators=sc.controller_actuators) for a in system.arms}
        spaces = {a.name: task_space(a, task, models[a.name]) for a in system.arms}
        leader_arm = system.arms[0]
        lead_pose = x_lead if sc.space == "task" else spaces[leader_arm.name].fk(x_lead)
        plans = []
        for arm, unit in zip(system.arms, sc.units, strict=True):
            m, space = models[arm.name], spaces[arm.name]
            if sc.space == "task":
                check_sizes(arm, space, square=True)
            q0 = (unit.initial_joint if unit.initial_joint is not None
                  else _numeric_initial(arm, space, unit))
            qd0 = (unit.initial_velocity if unit.initial_velocity is not None
                   else np.zeros(len(q0)))
            own = sc.unit_desired(arm.name, t)
            if own is not None:
                desired_expr = own
            elif arm is leader_arm:
                desired_expr = x_lead
            elif sc.space == "task":
                desired_expr = mirrored(task, lead_pose)
            else:
                raise KinematicsError(
                    f"scenario {_where(sc)}: {arm.name} would follow the leader in joint space "
                    "through inverse kinematics along the whole path, which cochlea has in "
                    f"closed form only for a planar 3R arm on a level base with task "
                    f"{DEFAULT_TASK!r} (this is task {task!r}, {len(arm.links)} joints): give "
                    "the unit its own desired_joint, or run in task space")
            if sc.space == "task":
                _check_task_path(arm, space, desired_expr, t, sc, q0, system.keep_out_radius)
            else:
                _check_path(arm, desired_expr, m.fk_world(desired_expr), t, sc,
                            system.keep_out_radius)
            tool = arm.links[-1]
            pose_task = None if space.model_pose else (
                (space.fk, space.J) if space.error is None else (space.fk, space.J, space.error))
            plans.append(UnitPlan(
                arm.name, m, self.model(system, arm, "inertial", actuators=sc.plant_actuators),
                desired_function(arm.name, desired_expr, t), np.concatenate([q0, qd0]),
                {tool.name: tool_offset(arm)},
                space.names, space.units, space.angles, space.fk, task=pose_task))
        return plans

    def _closed_form_plans(self, system: SerialSystem, sc: ScenarioView) -> list[UnitPlan]:
        """Planar 3R arms on a level base, task ``planar_yaw``: the thesis's system."""
        t = ca.SX.sym("t")
        x_lead, _, _ = sc.desired_leader()(t)
        models = {a.name: self.model(system, a, sc.parameterisation,
                                     actuators=sc.controller_actuators) for a in system.arms}
        leader_arm = system.arms[0]
        # The leader's tool pose in the cochlea frame, as a function of t.
        lead_pose = x_lead if sc.space == "task" else models[leader_arm.name].fk_world(x_lead)
        measured = getattr(sc, "mirror", "desired") == "measured"
        plans = []
        for arm, unit in zip(system.arms, sc.units, strict=True):
            m = models[arm.name]
            q0 = _initial_joint(arm, unit)
            qd0 = (unit.initial_velocity if unit.initial_velocity is not None
                   else np.zeros(len(q0)))
            own = sc.unit_desired(arm.name, t)
            follows = False
            if own is not None:  # its own joint path (joint space only): no rule applies
                desired_expr = own
            elif arm is leader_arm:
                desired_expr = x_lead
            else:  # dual-arm rule: point reflection through the cochlea centre
                follows = True
                pose = _rule(lead_pose)
                if measured:  # the run stops nearer than the edge: the nominal path must not
                    _check_reachable(arm, world_to_base(arm, pose), t, sc, MIRROR_COS_LIMIT)
                if sc.space == "task":
                    desired_expr = pose
                else:
                    pose_base = world_to_base(arm, pose)
                    _check_reachable(arm, pose_base, t, sc)
                    pose0 = np.array(ca.evalf(ca.substitute(pose, t, 0.0))).ravel()
                    _, elbow, offsets = ik(arm, pose0, q0)
                    if unit.elbow is not None:
                        elbow = unit.elbow
                        q_branch = np.array(ik_symbolic(arm, ca.DM(world_to_base(arm, pose0)),
                                                        elbow)).ravel()
                        offsets = 2 * np.pi * np.round((q0 - q_branch) / (2 * np.pi))
                    desired_expr = ik_symbolic(arm, pose_base, elbow, offsets)
            if sc.space == "task":
                pose_base = world_to_base(arm, desired_expr)
                _check_reachable(arm, pose_base, t, sc)
                # The joints follow the branch and turns of the initial configuration.
                elbow = unit.elbow or (1 if q0[1] >= 0 else -1)
                pose0 = np.array(ca.evalf(ca.substitute(desired_expr, t, 0.0))).ravel()
                q_branch = np.array(ik_symbolic(arm, ca.DM(world_to_base(arm, pose0)),
                                                elbow)).ravel()
                offsets = 2 * np.pi * np.round((q0 - q_branch) / (2 * np.pi))
                _check_path(arm, ik_symbolic(arm, pose_base, elbow, offsets), desired_expr, t,
                            sc, system.keep_out_radius)
            else:
                _check_path(arm, desired_expr, m.fk_world(desired_expr), t, sc,
                            system.keep_out_radius)
            follow = None
            if follows and measured:  # the nominal path above is checked as before
                lead_model, q0_lead = models[leader_arm.name], plans[0].x0[:len(q0)]
                _check_start_reachable(leader_arm, lead_model, q0_lead, arm, sc)
                heading = float(ca.evalf(ca.substitute(lead_pose[2], t, 0.0)))
                start = float(lead_model.fk_world(q0_lead)[2])
                turns = 2 * np.pi * np.round((heading - start) / (2 * np.pi))
                follow = _follow_plan(leader_arm, lead_model, sc.space, arm, sc.space, elbow,
                                      offsets, turns)
            tool = arm.links[-1]
            plans.append(UnitPlan(
                arm.name, m, self.model(system, arm, "inertial", actuators=sc.plant_actuators),
                desired_function(arm.name, desired_expr, t), np.concatenate([q0, qd0]),
                {tool.name: np.array([tool.length, 0.0, 0.0])},
                TASK_NAMES, TASK_UNITS, TASK_ANGLES, m.fk_world, follow=follow))
        return plans

    def actuated_joints(self, system: SerialSystem) -> list[ActuatedJoint]:
        joints = []
        for arm in system.arms:
            for link in arm.links:
                j = link.joint
                # m/rad through the transmission (the loader requires one on a prismatic
                # joint); a revolute joint is the motor's output shaft.
                ratio = j.transmission.ratio if j.transmission is not None else 1.0
                joints.append(ActuatedJoint(f"{arm.name}.{link.name}", j.type,
                                            tuple(j.position_limits), j.effort_limit,
                                            link.motor, ratio, j.actuator))
        return joints

    def link_frames(self, system: SerialSystem, unit: str) -> LinkFrames:
        """``UNIT/base`` in the world (the arm's base pose), each link ``UNIT/LINK`` in the one
        before it (its joint's transform), and ``UNIT/tool`` in the last link (the tool point
        and ``tool_rpy_deg``)."""
        arm = system.arm(unit)
        q = ca.SX.sym("q", len(arm.links))
        names, parents = [f"{unit}/base"], ["world"]
        poses = [(ca.SX(ca.DM(arm.base_rotation)), ca.SX(ca.DM(arm.base_xyz)))]
        for i, link in enumerate(arm.links):
            poses.append(joint_transform(link.joint, q[i]))
            names.append(f"{unit}/{link.name}")
            parents.append(names[-2])
        tool_R = np.eye(3) if arm.tool_rpy is None else rpy_matrix(arm.tool_rpy)
        poses.append((ca.SX(ca.DM(tool_R)), ca.SX(ca.DM(tool_offset(arm)))))
        names.append(f"{unit}/tool")
        parents.append(names[-2])
        return LinkFrames(tuple(names), tuple(parents), frames_function(unit, q, poses))

    def unit(self, system: SerialSystem, arm: str | None) -> str:
        units = [a.name for a in system.arms]
        arm = arm or units[0]
        if arm not in units:
            raise CochleaError(f"--arm {arm!r}: no such arm; the arms are {', '.join(units)}")
        return arm

    def excitation_geometry(self, system: SerialSystem, unit: str, study_pose: np.ndarray,
                            held: dict[str, np.ndarray], clearance: float
                            ) -> ExcitationGeometry:
        return excitation.excitation_geometry(system, unit, study_pose, held, clearance)

    def identified_values(self, model: RobotModel, system: SerialSystem, unit: str,
                          phi: np.ndarray) -> dict[tuple, str]:
        return identified.identified_values(model, system, unit, phi)

    def fit_key(self, system: SerialSystem, unit: str, joint: int, name: str) -> tuple:
        return identified.fit_key(system, unit, joint)

    def print_summary(self, system: SerialSystem, args) -> None:
        summary.print_summary(self, system, args)


ROBOT = SerialRobot()
