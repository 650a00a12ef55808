"""What every robot offers the layers above it: the interface of a robot adapter.

A robot (``serial``, ``parallel``) is one :class:`RobotAdapter` in :mod:`cochlea.robots`'s
registry. Everything above the robots layer -- scenarios, simulation, the real-time loop, the
Dynamixel bridge, the command-line tools -- asks the adapter instead of branching on the
robot's name:

* ``load(description)``: the description (a shipped name or a TOML path), read once;
* ``model(system, ...)``: the symbolic :class:`~cochlea.robots.model.RobotModel` of one unit;
* ``layout(system, space)``: what a scenario of this robot is made of (:class:`Layout`);
* ``unit_plans(system, scenario)``: each controlled unit's models, initial state and desired
  trajectory for a scenario (:class:`UnitPlan`); the simulation adds controller and gains;
  ``mirror_modes``: what a scenario's ``[control] mirror`` may be, and with ``"measured"`` a
  follower's plan says how it follows its leader's measured state (:class:`FollowPlan`);
* ``actuated_joints(system)``: every joint with its motor, in the loop's order;
* ``system.keep_out_radius``: the supervisor's keep-out circle (m);
* ``unit(system, arm)``: the unit a command's ``--arm`` names (``units_are_arms``: whether
  a robot's units are chosen that way at all);
* ``working_pose(system)``: a documented pose inside the workspace (``cochlea-model``'s
  default, the figures');
* ``excitation_study`` and ``excitation_geometry(...)``: what ``cochlea-excite`` needs of the
  robot beyond its model and limits (:class:`ExcitationGeometry`);
* ``identified_values(...)`` and ``fit_key(...)``: where identified values go in the
  robot's description (``cochlea-identify --update-description``);
* ``calibration_reference``, ``positive_direction``: ``cochlea-dxl calibrate``'s prompts;
* ``print_summary(system, args)`` and ``draw(system, q, path, title)``: ``cochlea-model``'s
  text and the robot's figure.
* ``link_frames(system, unit)``: every body frame of a unit as a function of its joints
  (:class:`LinkFrames`; ``cochlea-mcap``'s ``/tf``).

Code outside :mod:`cochlea.robots` asks these instead of comparing a robot's name or importing
:mod:`cochlea.robots.serial` or :mod:`cochlea.robots.parallel` (``tests/test_architecture.py``
refuses both; docs/extending.md).

A *unit* is one controlled robot unit: an arm of the serial system, or the whole parallel
mechanism. (Physical units are called SI units everywhere.)
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import casadi as ca
import numpy as np

from .description import Actuator, Motor
from .model import RobotModel


class UnitStart(Protocol):
    """What an adapter reads of one unit of a scenario (SI): its initial state."""

    name: str
    initial_joint: np.ndarray | None
    initial_task: np.ndarray | None
    initial_velocity: np.ndarray | None
    elbow: int | None  # inverse-kinematics branch where the robot has one


class ScenarioView(Protocol):
    """What an adapter reads of a scenario. Scenarios are read by the simulation layer above
    (:class:`cochlea.sim.scenario.Scenario`), so the robots see them through this view."""

    name: str
    space: str  # "joint" | "task"
    duration: float  # s
    parameterisation: str
    units: Sequence[UnitStart]
    #: What the controller's model and the simulated plant carry of the drives
    #: (:data:`~cochlea.robots.model.ACTUATORS`; the plant: "none" or "armature").
    controller_actuators: str
    plant_actuators: str

    @property
    def period(self) -> float: ...  # s

    def desired_leader(self) -> ca.Function: ...  # t -> (x, x_dot, x_ddot) of the leader

    #: The task coordinates (``[control] task``) where the robot offers a choice
    #: (:attr:`RobotAdapter.task_spaces`); read with ``getattr(sc, "task", None)``, None: the
    #: robot's default.
    task: str | None

    #: A unit's own joint path in t (SI), tracked instead of the leader's rule; None: the rule.
    def unit_desired(self, name: str, t: ca.SX) -> ca.SX | None: ...

    #: What a following unit's rule is applied to (:attr:`RobotAdapter.mirror_modes`):
    #: "desired" (the leader's desired pose) or "measured" (its measured pose, each period).
    mirror: str


@dataclass(frozen=True)
class Layout:
    """The coordinates of a robot's scenarios: kinds (``"angle"`` | ``"length"``) of the
    leader's desired trajectory and of one unit's joint and task coordinates, the units' names,
    and the sizes the scenario's gains and plant options must have."""

    leader: tuple[str, ...]
    joint: tuple[str, ...]
    task: tuple[str, ...]
    units: tuple[str, ...]
    n_joint: int
    n_task: int
    n_bodies: int  # per unit: one mass-scale factor each


@dataclass(frozen=True)
class FollowPlan:
    """A unit whose desired trajectory is a rule applied, each period, to another unit's
    *measured* state (``mirror = "measured"``), SI.

    ``step(x_lead, a_lead) -> (x, x_dot, x_ddot, margin)``: ``x_lead`` the leader's measured
    ``[q, qd]`` (what its controller sees in the same period), ``a_lead`` the leader's desired
    tool acceleration (world frame; no acceleration is measured); the outputs are the
    follower's desired position, velocity and acceleration in its controller's space, and
    ``margin``, >= 0 where the rule's pose is within the follower's reach (a NaN or a negative
    margin: out of reach, the run's safe stop). ``lead_acceleration(x, x_dot, x_ddot) ->
    a_lead``: that acceleration from the leader's desired trajectory in its controller's
    space."""

    leader: int  # the leader's index among the plans (an earlier unit)
    step: ca.Function = field(repr=False)
    lead_acceleration: ca.Function = field(repr=False)
    #: What a negative margin means, for the stop's line ("its elbow within 10 deg of ...").
    reach: str = "out of its reach"


@dataclass
class UnitPlan:
    """One controlled unit of a scenario, as the robot sees it (SI)."""

    name: str
    controller_model: RobotModel
    plant_model: RobotModel  # full inertial parameterisation
    desired: ca.Function  # t -> (xd, xd_dot, xd_ddot) in the controller's space
    x0: np.ndarray  # [q0, qd0]
    #: Where the scenario's payload sits: body name -> point (m, body frame).
    payload_points: dict[str, np.ndarray]
    task_names: tuple[str, ...]
    task_units: tuple[str, ...]
    task_angles: tuple[int, ...]  # task coordinates whose error wraps to (-pi, pi]
    fk_world: ca.Function = field(repr=False)
    #: ``(fk, J)`` of the task-space controllers; None: the model's ``fk_world``, ``J_world``.
    #: A third Function, ``(q, x_d) -> e``, replaces the error ``fk(q) - x_d`` of controller g
    #: (a serial arm's full pose: :mod:`cochlea.robots.serial.task`).
    task: tuple[ca.Function, ...] | None = field(default=None, repr=False)
    #: Tool points drawn in the path figure: label -> indices of (u, v) in the task pose.
    tool_points: tuple[tuple[str, tuple[int, int]], ...] = (("tool", (0, 1)),)
    #: Centre of the cochlea-centred circle in the path figure (m, world frame).
    centre: tuple[float, float] = (0.0, 0.0)
    #: Index of the joint whose value moves the keep-out centre along v (the parallel
    #: mechanism's slider: S = (0, d1)), or None for a fixed centre at ``centre``.
    moving_centre_joint: int | None = None
    #: ``mirror = "measured"``: how the unit follows its leader's measured state; ``desired``
    #: is then the nominal path (the rule on the leader's desired), checked before a run.
    follow: FollowPlan | None = None

    def keep_out_centre(self, q) -> tuple:
        """The keep-out circle's centre at ``q`` (see :func:`keep_out_centre`)."""
        return keep_out_centre(self.centre, self.moving_centre_joint, q)

    @property
    def joint_units(self) -> tuple[str, ...]:
        return tuple("rad" if j.type == "revolute" else "m"
                     for j in self.controller_model.joints)


@dataclass(frozen=True)
class ActuatedJoint:
    """A joint of the whole system with the motor that drives it (SI)."""

    name: str  # unique in the system: "arm1.link2", "th1", "d1", ...
    type: str  # "revolute" | "prismatic"
    position_limits: tuple[float, float]  # rad or m
    effort_limit: float  # N m or N
    motor: Motor
    ratio: float  # motor torque (N m) per unit of joint effort (1 for a direct drive)
    actuator: Actuator = Actuator()  # the drive's armature and friction at the joint


@dataclass(frozen=True)
class LinkFrames:
    """Every body frame of one unit, as a function of its joint position (SI): frame ``i`` is
    named ``names[i]`` and posed in frame ``parents[i]`` (``"world"``: the cochlea-centred
    frame, or an earlier frame of the list). ``function(q)`` gives a ``12 x len(names)``
    matrix, one column per frame: its rotation matrix (9 entries, column-major) then its
    translation (m). What ``cochlea-mcap`` publishes on ``/tf`` (docs/logs.md)."""

    names: tuple[str, ...]
    parents: tuple[str, ...]
    function: ca.Function = field(repr=False)


def frames_function(name: str, q: ca.SX, poses: list[tuple[ca.SX, ca.SX]]) -> ca.Function:
    """The ``q -> 12 x k`` Function of :class:`LinkFrames` from ``(R, p)`` expressions."""
    columns = [ca.vertcat(ca.reshape(R, 9, 1), p) for R, p in poses]
    return ca.Function(f"frames_{name}", [q], [ca.horzcat(*columns)])


#: The up-front checks of a desired path sample it at every control period up to this many
#: samples; a longer run is sampled at this many evenly spaced times (the supervisor still
#: watches every period). About 10 us a sample: at most ~2 s before a run starts.
MAX_CHECK_SAMPLES = 200_000
#: Samples evaluated at once: bounds the check's memory whatever the run's length.
CHECK_CHUNK = 20_000


def sample_times(duration: float, period: float):
    """The times (s) at which a run's desired path is checked, in chunks (numpy arrays): every
    period from 0 to ``duration`` inclusive, or :data:`MAX_CHECK_SAMPLES` evenly spaced times
    when that is fewer."""
    count = int(math.floor(duration / period + 1e-9)) + 1
    step = period
    if count > MAX_CHECK_SAMPLES:
        count, step = MAX_CHECK_SAMPLES, duration / (MAX_CHECK_SAMPLES - 1)
    for start in range(0, count, CHECK_CHUNK):
        yield np.minimum(np.arange(start, min(start + CHECK_CHUNK, count)) * step, duration)


def keep_out_centre(centre: tuple[float, float], moving_centre_joint: int | None, q) -> tuple:
    """Centre ``(u, v)`` of the safety keep-out circle (m, world frame) at joint position ``q``,
    or at each row of ``q`` (then ``v`` is a column where the centre moves): the fixed
    ``centre``, or ``(0, q[moving_centre_joint])`` where the centre rides on a joint (the
    parallel robot's slider: S = (0, d1)). The one statement of that rule: the supervisor's
    checks and the C drivers' keep-out points (:meth:`cochlea.sim.setup.UnitSetup.
    keep_out_centre`) and the replay's circle (:mod:`cochlea.view.replay`) take it from here."""
    if moving_centre_joint is None:
        return centre
    v = np.asarray(q)[..., moving_centre_joint]
    return (0.0, float(v) if v.ndim == 0 else v)


def sampled(f: ca.Function, duration: float, period: float):
    """``(times, outputs)`` chunk by chunk of a function of t over a run: each output a
    ``(size, n_times)`` array."""
    for times in sample_times(duration, period):
        values = f.map(len(times))(times.reshape(1, -1))
        values = values if isinstance(values, (list, tuple)) else [values]
        yield times, [np.array(v) for v in values]


def first_inside(times: np.ndarray, distances: np.ndarray, radius: float
                 ) -> tuple[float, float] | None:
    """The first ``(time, distance)`` (s, m) of sampled distances from a keep-out centre (one
    chunk of :func:`sampled`) that lies inside the circle of ``radius`` (m): nearer than it,
    or not a number; None when none does."""
    r = np.ravel(distances)
    inside = np.flatnonzero(~(r >= radius))
    if not inside.size:
        return None
    k = inside[0]
    return float(times[k]), float(r[k])


def desired_function(name: str, expr_t: ca.SX, t: ca.SX) -> ca.Function:
    """``t -> (x, x_dot, x_ddot)`` of a trajectory expression in ``t``, derivatives exact."""
    x_dot = ca.jacobian(expr_t, t)
    return ca.Function(f"desired_{name}", [t], [expr_t, x_dot, ca.jacobian(x_dot, t)],
                       ["t"], ["x", "x_dot", "x_ddot"])


@dataclass
class ExcitationGeometry:
    """What an excitation of one unit must respect of the robot's own geometry, beyond its
    joint, velocity and effort limits (``cochlea-excite``, :mod:`cochlea.ident.excite`), SI."""

    #: The band's centre: the pose the excited unit works around.
    working_pose: np.ndarray
    #: How messages name the unit ("arm1", "the mechanism").
    label: str
    #: ``q -> values``, each >= 0 where the pose is allowed (normalised to about 1).
    constraints: ca.Function = field(repr=False)
    #: Raises :class:`~cochlea.errors.CochleaError` when the working pose itself is not
    #: allowed (the design's margins included).
    check_start: Callable[[], None] = field(repr=False)
    #: ``(q (n, N), times (N,)) -> (problems, distances)`` over the 1 kHz check: the problems
    #: found (empty: none) and the closest approaches the robot reports (name -> m; the serial
    #: arms: ``keep_out_distance``, ``clearance_distance``).
    check_path: Callable[[np.ndarray, np.ndarray], tuple[list[str], dict[str, float]]] = \
        field(repr=False)


class RobotAdapter:
    """The interface; :mod:`cochlea.robots.serial` and :mod:`cochlea.robots.parallel`
    implement it."""

    name: str
    #: The default ``method`` of :meth:`model`.
    method: str = "newton-euler"
    #: Whether the system's units are arms chosen by name (``model(system, arm)``, the
    #: commands' ``--arm``); False: one unit, and ``arm`` is ignored.
    units_are_arms: bool = False
    #: The joint-space scenario whose control settings and gains track an excitation (and
    #: whose initial joint positions are the units' working poses, where :meth:`working_pose`
    #: does not say otherwise).
    excitation_study: str = ""
    #: ``cochlea-dxl calibrate``'s reference pose: joint name (or ``"*"``: every other joint)
    #: -> (joint coordinate, SI; how to set it by hand).
    calibration_reference: dict[str, tuple[float, str]] = {}
    #: The positive sense of the robot's joints, as the user sees them.
    positive_direction: str = ""
    #: The task spaces a scenario may choose (``[control] task``); empty: the robot has one,
    #: and the key is refused.
    task_spaces: tuple[str, ...] = ()
    #: The task space of a scenario that does not choose one (when :attr:`task_spaces`).
    default_task: str | None = None
    #: The values of a scenario's ``[control] mirror`` (the first the default): what a
    #: following unit's rule is applied to, its leader's "desired" or "measured" pose.
    mirror_modes: tuple[str, ...] = ("desired",)

    def load(self, description: str | Path | None = None) -> Any:
        raise NotImplementedError

    def model(self, system: Any, arm: str | None = None, parameterisation: str = "inertial",
              method: str | None = None, actuators: str = "none") -> RobotModel:
        raise NotImplementedError

    def layout(self, system: Any, space: str, task: str | None = None) -> Layout:
        """``task``: one of :attr:`task_spaces` (None: the default); only robots that offer a
        choice take it."""
        raise NotImplementedError

    def unit_plans(self, system: Any, scenario: ScenarioView) -> list[UnitPlan]:
        raise NotImplementedError

    def actuated_joints(self, system: Any) -> list[ActuatedJoint]:
        raise NotImplementedError

    def link_frames(self, system: Any, unit: str) -> LinkFrames:
        """Every body frame of ``unit`` (its links, and its tool where it has one) as a
        function of the unit's joint position: :class:`LinkFrames`."""
        raise NotImplementedError(f"no link frames of the {self.name} robot")

    def unit(self, system: Any, arm: str | None) -> str:
        """The unit a command's ``--arm`` names (None: the first); a
        :class:`~cochlea.errors.CochleaError` for an arm the robot does not have."""
        raise NotImplementedError

    def working_pose(self, system: Any) -> np.ndarray | None:
        """A documented joint position inside the workspace (SI), or None: all zero."""
        return None

    def is_shipped(self, system: Any) -> bool:
        """Whether ``system`` is the robot's shipped description or an edited copy of it (the
        same ``[system] name``, e.g. one ``cochlea-dxl calibrate`` or ``cochlea-identify``
        wrote): the robot's documented poses (:attr:`excitation_study`,
        :attr:`calibration_reference`) are for it, a user's robot gets the defaults."""
        return system.name == self.load(None).name

    def calibration_references(self, system: Any, shipped: bool = True
                               ) -> dict[str, tuple[float, str]]:
        """``cochlea-dxl calibrate``'s reference pose of every actuated joint: joint name ->
        (joint coordinate, SI; how to set it by hand). A unit whose description gives
        ``calibration_pose_deg`` takes it; otherwise :attr:`calibration_reference` for the
        description the robot ships (``shipped``), and for a user's description each joint's
        zero as the description defines it (the middle of its limits where zero is outside
        them)."""
        joints = self.actuated_joints(system)
        table = self.calibration_reference
        refs: dict[str, tuple[float, str]] = {}
        for j in joints:
            lo, hi = j.position_limits
            if shipped and (j.name in table or "*" in table):
                refs[j.name] = table.get(j.name, table.get("*"))
            elif lo <= 0.0 <= hi:
                refs[j.name] = (0.0, "its zero as the description defines it (the joint's "
                                     "frame at q = 0, from origin_xyz_m / origin_rpy_deg)")
            else:
                refs[j.name] = (0.5 * (lo + hi), "the middle of its limits (zero is outside "
                                                 "them)")
        described = getattr(system, "described_pose", None)
        for unit in (self.layout(system, "joint").units if described is not None else ()):
            pose = described(unit, "calibration")
            if pose is None:
                continue
            names = [j.name for j in joints if j.name.startswith(f"{unit}.")]
            for name, q in zip(names, pose, strict=True):
                refs[name] = (float(q), "the description's calibration_pose_deg")
        return refs

    def calibration_positive(self, system: Any, joint: str, shipped: bool = True) -> str:
        """The positive sense of ``joint`` (an actuated joint's name) as the user sees it: the
        description's ``positive_direction`` of its unit where given, else
        :attr:`positive_direction` for the shipped description, else the right-hand rule
        about the joint's axis."""
        described = getattr(system, "described_positive", None)
        text = described(joint) if described is not None else None
        if text:
            return text
        if shipped and self.positive_direction:
            return self.positive_direction
        return ("by the right-hand rule about the joint's axis in the description: thumb "
                "along the axis, the fingers curl positive")

    def excitation_pose(self, system: Any, unit: str) -> np.ndarray:
        """The joint pose an excitation of ``unit`` works around when the description is not
        the one :attr:`excitation_study` was made for (a user's robot): the description's own
        where it gives one, else the middle of each joint's position limits (SI)."""
        described = getattr(system, "described_pose", None)  # a description's optional key
        pose = described(unit, "working") if described is not None else None
        if pose is not None:
            return np.array(pose, float)
        model = self.model(system, unit)
        return np.array([0.5 * (j.position_limits[0] + j.position_limits[1])
                         for j in model.joints])

    def excitation_geometry(self, system: Any, unit: str, study_pose: np.ndarray,
                            held: dict[str, np.ndarray], clearance: float
                            ) -> ExcitationGeometry:
        """The geometry an excitation of ``unit`` must respect; ``study_pose``: its initial
        joint position in :attr:`excitation_study`, ``held``: the other units and the pose
        each holds, ``clearance``: the distance (m) to keep from them."""
        raise NotImplementedError

    def identified_values(self, model: RobotModel, system: Any, unit: str,
                          phi: np.ndarray) -> dict[tuple, str]:
        """``{key path in the description's TOML: value text}`` for the full parameters
        ``phi`` of ``unit``'s ``model`` (``cochlea.ident.writeback.key_lines``' paths)."""
        raise NotImplementedError

    def fit_key(self, system: Any, unit: str, joint: int, name: str) -> tuple:
        """The key path of the current-to-torque ``fit`` of ``unit``'s joint ``joint`` (its
        index in the model; ``name``: its name in the system, ``"arm1.link2"``,
        ``"left.th1"``)."""
        raise NotImplementedError

    def print_summary(self, system: Any, args: Any) -> None:
        """``cochlea-model``'s text for the robot (``args``: its parsed options)."""
        raise NotImplementedError

    def draw(self, system: Any, q: np.ndarray | None = None, path: str | Path | None = None,
             title: str | None = None):
        """A matplotlib Figure of the robot at ``q`` (default :meth:`working_pose`)."""
        raise NotImplementedError(f"no figure of the {self.name} robot")
