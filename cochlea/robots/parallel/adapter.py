"""The parallel mechanism in scenarios: its one controlled unit, the leader (the left side) and
the right side by the mirror rule.

Joint space (controller f): the scenario gives the left side's ``th1, th2`` and the slider's
``d1``; the right pantograph's desired end point is the mirror image ``C' = (-C_u, C_v)`` of the
left's, turned into ``th1', th2'`` by closed-form IK on the branch of the initial
configuration. Task space (controller d): the scenario gives ``C_u, C_v, phi`` of the left end
effector; the right one follows the mirror rule ``C' = (-C_u, C_v)``, ``phi' = 180 deg - phi``,
which makes ``x_pd`` consistent (both sides imply the same slider height).
"""

from __future__ import annotations

import math
from pathlib import Path

import casadi as ca
import numpy as np

from ...errors import CochleaError, KinematicsError
from ...resources import ROBOTS_DIR, shipped_file
from ..adapter import (
    ActuatedJoint,
    ExcitationGeometry,
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
from . import excitation, figure, identified, summary
from .description import ParallelSystem, load_parallel
from .geometry import SCENARIO_START, ParallelGeometry
from .model import build_model

UNIT = "mechanism"
END_EFFECTORS = ("left.link5", "right.link5")  # the magnets; their frames sit at C and C'


def _sample_times(sc: ScenarioView, count: int = 501) -> np.ndarray:
    return np.linspace(0.0, sc.duration, count)


def _check_workspace(geometry, q_of_t: ca.Function, sc: ScenarioView) -> None:
    """Refuse a desired trajectory that leaves the workspace, before anything runs."""
    for t in _sample_times(sc):
        q = np.array(q_of_t(t)).ravel()
        problems = geometry.violations(q) if np.isfinite(q).all() else ["out of reach"]
        if problems:
            raise KinematicsError(f"scenario {sc.name}: the desired configuration leaves the "
                                  f"workspace at t = {t:.3f} s: {'; '.join(problems)}")


def _check_keep_out(lead: ca.SX, t: ca.SX, radius: float, sc: ScenarioView) -> None:
    """Refuse a task-space path that takes an end effector inside the keep-out circle around
    the slider point S = (0, d1), at any period of the run: the supervisor would stop it there.

    With the slider at ``d1 = C_v - C_u tan(phi)`` (the consistency rule), ``C - S =
    (C_u, C_u tan(phi))``, so ``|C - S| = |C_u| / |cos(phi)|``, in closed form and the same for
    the mirrored C'; checked period by period, not only at the workspace check's samples."""
    distance = ca.Function("distance", [t], [ca.fabs(lead[0]) / ca.fabs(ca.cos(lead[2]))])
    for times, (r,) in sampled(distance, sc.duration, sc.period):
        inside = first_inside(times, r, radius)
        if inside is not None:
            when, near = inside
            raise KinematicsError(
                f"scenario {getattr(sc, 'path', sc.name)}: the desired end-effector path passes "
                f"{near * 1000:.1f} mm from the slider point S at t = {when:.3f} s, "
                f"inside the keep-out radius {radius * 1000:.1f} mm: the supervisor would stop "
                "the run there; change the trajectory or shorten --duration")


def _check_joint_keep_out(fk_world: ca.Function, q_t: ca.SX, t: ca.SX, radius: float,
                          sc: ScenarioView) -> None:
    """Refuse a joint-space path that takes an end effector (C or C', the pose's (0, 1) and
    (3, 4)) inside the keep-out circle around the slider point S = (0, d1) of the same
    desired configuration, at any period of the run: the supervisor would stop it there, in
    joint space as in task space."""
    pose = fk_world(q_t)
    S = ca.vertcat(0, q_t[2])
    distance = ca.Function("distance", [t], [ca.fmin(ca.norm_2(pose[0:2] - S),
                                                      ca.norm_2(pose[3:5] - S))])
    for times, (r,) in sampled(distance, sc.duration, sc.period):
        inside = first_inside(times, r, radius)
        if inside is not None:
            when, near = inside
            raise KinematicsError(
                f"scenario {getattr(sc, 'path', sc.name)}: the desired joint path takes an end "
                f"effector {near * 1000:.1f} mm from the slider point S at t = "
                f"{when:.3f} s, inside the keep-out radius {radius * 1000:.1f} mm: the "
                "supervisor would stop the run there; change the trajectory or shorten "
                "--duration")


def _initial_joint(geometry, unit: UnitStart) -> np.ndarray:
    if unit.initial_joint is not None:
        q0 = unit.initial_joint
    else:
        # The thesis's printed x_p(0) is not consistent (its two sides imply slider heights
        # 7 mm apart): the slider height comes from the left side's (C, phi), each pantograph
        # from its own end point; phi' then follows from the mechanism.
        x = unit.initial_task
        d1 = geometry.slider_height(x[0:2], x[2])
        q0 = np.array([*geometry.side_ik("left", x[0:2]), d1, *geometry.side_ik("right", x[3:5])])
    problems = geometry.violations(q0)
    if problems:
        raise KinematicsError("the initial configuration is outside the workspace: "
                              + "; ".join(problems))
    return np.asarray(q0, float)


TASK_NAMES = ("C_u", "C_v", "phi", "C'_u", "C'_v", "phi'")
TASK_UNITS = ("m", "m", "rad") * 2
TASK_ANGLES = (2, 5)


class ParallelRobot(RobotAdapter):
    name = "parallel"
    method = "lagrange"
    excitation_study = "parallel_joint_realistic"
    calibration_reference = {
        "left.th1": (math.pi / 2, "link 1 pointing straight up (+v)"),
        "left.th2": (0.0, "link 4 horizontal, pointing away from the slider (+u)"),
        "right.th1": (math.pi / 2, "link 1' pointing straight up (+v)"),
        "right.th2": (math.pi, "link 4' horizontal, pointing away from the slider (-u)"),
        "slider.d1": (0.0, "the slider on its lower stop, d1 = 0 (its pivot at the bases' "
                      "height)"),
    }
    positive_direction = ("counter-clockwise seen with +u to your right and v up; the slider "
                          "up")

    def load(self, description: str | Path | None = None) -> ParallelSystem:
        return load_parallel(description if description is not None
                             else shipped_file(ROBOTS_DIR, self.name))

    def model(self, system: ParallelSystem, arm: str | None = None,
              parameterisation: str = "inertial", method: str | None = None,
              actuators: str = "none") -> RobotModel:
        # One unit: ``arm`` is accepted (and ignored) so every robot is called alike.
        return build_model(system, parameterisation, method or self.method, actuators)

    def layout(self, system: ParallelSystem, space: str) -> Layout:
        joint = ("angle", "angle", "length", "angle", "angle")
        task = ("length", "length", "angle") * 2
        n_bodies = 1 + sum(len(side.bodies) for side in system.sides)
        return Layout(leader=joint[:3] if space == "joint" else task[:3], joint=joint,
                      task=task, units=(UNIT,), n_joint=5, n_task=6, n_bodies=n_bodies)

    def unit_plans(self, system: ParallelSystem, sc: ScenarioView) -> list[UnitPlan]:
        ctrl_model = self.model(system, parameterisation=sc.parameterisation,
                                actuators=sc.controller_actuators)
        plant = self.model(system, parameterisation="inertial", actuators=sc.plant_actuators)
        geometry = ctrl_model.geometry
        (unit,) = sc.units
        q0 = _initial_joint(geometry, unit)
        qd0 = unit.initial_velocity if unit.initial_velocity is not None else np.zeros(5)

        t = ca.SX.sym("t")
        lead, _, _ = sc.desired_leader()(t)
        own = sc.unit_desired(UNIT, t)
        if own is not None:  # its own path for all five joints (joint space only)
            desired_expr = own
            _check_workspace(geometry, ca.Function("q_d", [t], [desired_expr]), sc)
        elif sc.space == "joint":
            th1, th2, d1 = lead[0], lead[1], lead[2]
            B = geometry.base(system.left)
            lp = geometry.lp
            C_u = B[0] + lp * (ca.cos(th1) + ca.cos(th2))
            C_v = B[1] + lp * (ca.sin(th1) + ca.sin(th2))
            mirrored = ca.vertcat(-C_u, C_v)
            branch = geometry.branches(q0)[1]
            right0 = np.array(geometry.side_ik_symbolic(
                "right", ca.evalf(ca.substitute(mirrored, t, 0.0)), branch)).ravel()
            offsets = 2 * np.pi * np.round((q0[3:5] - right0) / (2 * np.pi))
            right = geometry.side_ik_symbolic("right", mirrored, branch, offsets)
            desired_expr = ca.vertcat(th1, th2, d1, right)
            _check_workspace(geometry, ca.Function("q_d", [t], [desired_expr]), sc)
        else:
            phi = lead[2]
            desired_expr = ca.vertcat(lead[0], lead[1], phi, -lead[0], lead[1], math.pi - phi)
            x_of_t = ca.Function("x_d", [t], [desired_expr])
            for time in _sample_times(sc):  # consistent and inside the workspace at every sample
                geometry.ik(np.array(x_of_t(time)).ravel())
            _check_keep_out(lead, t, system.keep_out_radius, sc)
        if sc.space == "joint" and system.keep_out_radius:
            _check_joint_keep_out(ctrl_model.fk_world, desired_expr, t, system.keep_out_radius,
                                  sc)
        desired = desired_function(UNIT, desired_expr, t)
        x_start = np.array(desired(0.0)[0]).ravel()
        d1_0 = float(x_start[2]) if sc.space == "joint" else \
            float(geometry.slider_height(x_start[0:2], float(x_start[2])))
        return [UnitPlan(
            UNIT, ctrl_model, plant, desired, np.concatenate([q0, qd0]),
            {body: np.zeros(3) for body in END_EFFECTORS}, TASK_NAMES, TASK_UNITS, TASK_ANGLES,
            ctrl_model.fk_world, task=(ctrl_model.fk, ctrl_model.J),
            tool_points=(("C", (0, 1)), ("C'", (3, 4))), centre=(0.0, d1_0),
            moving_centre_joint=2)]

    def actuated_joints(self, system: ParallelSystem) -> list[ActuatedJoint]:
        return [ActuatedJoint(j.name, j.type, tuple(j.position_limits), j.effort_limit, j.motor,
                              j.transmission.ratio if j.transmission else 1.0, j.actuator)
                for j in system.joints]

    def link_frames(self, system: ParallelSystem, unit: str) -> LinkFrames:
        """Every body in the world frame (the mechanism's plane is its x-y plane: u -> x,
        v -> y): ``mechanism/slider`` at S = (0, d1), and per side ``mechanism/SIDE/linkN`` at
        the body frames of the model's energies (links 1 and 4 at B, 2 at A1, 3 at A4, 5 at C,
        7 at S; each turned about z by its angle)."""
        q = ca.SX.sym("q", 5)
        lp = system.link_length

        def planar(origin, angle):
            c, s = ca.cos(angle), ca.sin(angle)
            R = ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))
            return R, ca.vertcat(origin[0], origin[1], 0)

        S = ca.vertcat(0, q[2])
        names, poses = [f"{UNIT}/slider"], [planar(S, 0)]
        for side, (th1, th2) in zip(system.sides, ((q[0], q[1]), (q[3], q[4]))):
            e = lambda a: ca.vertcat(ca.cos(a), ca.sin(a))  # noqa: E731
            B = ca.DM([side.sign * system.base_offset, 0.0])
            A1, A4 = B + lp * e(th1), B + lp * e(th2)
            C = A1 + lp * e(th2)
            phi = ca.atan2(C[1] - S[1], C[0] - S[0])
            for body, origin, angle in (("link1", B, th1), ("link4", B, th2), ("link2", A1, th2),
                                        ("link3", A4, th1), ("link5", C, phi),
                                        ("link7", S, phi)):
                names.append(f"{UNIT}/{side.name}/{body}")
                poses.append(planar(origin, angle))
        return LinkFrames(tuple(names), ("world",) * len(names), frames_function(UNIT, q, poses))

    def unit(self, system: ParallelSystem, arm: str | None) -> str:
        if arm is not None:
            raise CochleaError("--arm is for the serial system; the parallel mechanism is one "
                               "robot")
        return UNIT

    def working_pose(self, system: ParallelSystem) -> np.ndarray:
        """The joint-space scenario's start (thesis 3.67, right side mirrored)."""
        return np.asarray(SCENARIO_START, float).copy()

    def excitation_geometry(self, system: ParallelSystem, unit: str, study_pose: np.ndarray,
                            held: dict[str, np.ndarray], clearance: float
                            ) -> ExcitationGeometry:
        # The mechanism works around SCENARIO_START, not the study's initial pose; nothing
        # else holds still beside it (one unit), so ``held`` and ``clearance`` do not apply.
        return excitation.excitation_geometry(ParallelGeometry(system))

    def identified_values(self, model: RobotModel, system: ParallelSystem, unit: str,
                          phi: np.ndarray) -> dict[tuple, str]:
        return identified.identified_values(model, system, phi)

    def fit_key(self, system: ParallelSystem, unit: str, joint: int, name: str) -> tuple:
        return identified.fit_key(name)

    def print_summary(self, system: ParallelSystem, args) -> None:
        summary.print_summary(self, system, args)

    def draw(self, system: ParallelSystem, q=None, path: str | Path | None = None,
             title: str | None = None):
        return figure.draw(system, q, path, title)


ROBOT = ParallelRobot()
