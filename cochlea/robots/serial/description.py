"""The serial system's description: planar (or general) serial arms in one world frame.

Read from a TOML file with ``kind = "serial"`` (the shipped one: ``models/robots/
serial.toml``); see :mod:`cochlea.robots.description` for what every description shares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import DescriptionError, ModelError
from ..description import (
    MAX_ANGLE_DEG,
    MAX_INERTIA_KGM2,
    MAX_LENGTH_M,
    MAX_MASS_KG,
    MIN_INERTIA_KGM2,
    MIN_MASS_KG,
    Actuator,
    Motor,
    Table,
    Transmission,
    check_unique_motor_ids,
    open_description,
    read_actuator,
    read_limits,
    read_motor,
    read_transmission,
    resolve_path,
)

#: Most joints (links) of one arm. The symbolic model's cost grows about with the cube of the
#: joints (cochlea-model on a chain of n joints, this 2-core machine: 16 joints 1.3 s, 20 3.2 s,
#: 24 4.9 s, 30 11 s and 0.4 GB, 60 over 2 min and 3.3 GB), and the controllers and C kernels
#: cost more again; 16 keeps a model within seconds and is twice a 7-DoF arm's joints.
MAX_JOINTS = 16

# --------------------------------------------------------------------------------------------
# Dataclasses (SI units)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Joint:
    """The joint that moves a link relative to its parent.

    The joint frame sits at ``origin_xyz`` (m) in the parent link's frame, rotated by
    ``origin_rpy`` (rad, fixed-axis roll-pitch-yaw). The link frame is the joint frame rotated
    about ``axis`` by q (revolute, rad) or translated along it by q (prismatic, m).
    """

    type: str  # "revolute" | "prismatic"
    axis: np.ndarray  # unit vector in the joint frame
    origin_xyz: np.ndarray  # m, in the parent frame
    origin_rpy: np.ndarray  # rad
    position_limits: tuple[float, float]  # rad or m
    velocity_limit: float  # rad/s or m/s
    effort_limit: float  # N m or N
    #: What the joint's drive adds to the rigid link: armature and friction.
    actuator: Actuator = Actuator()
    #: The joint's own name (optional key ``name``, e.g. carried over from a URDF); None: the
    #: model names it after its link (``link2`` -> ``joint2``).
    name: str | None = None
    #: How the link's motor moves a prismatic joint (``[arm.link.joint.transmission]``,
    #: required there: a pinion, belt or lead screw); None for a revolute joint, which the
    #: motor's output shaft turns directly.
    transmission: Transmission | None = None


@dataclass(frozen=True)
class Link:
    """A rigid link with its inertial data expressed in the link frame (SI)."""

    name: str
    length: float  # m: the next joint (or the tool point) sits at [length, 0, 0]
    mass: float  # kg
    com: np.ndarray  # m, centre of mass in the link frame
    inertia_com: np.ndarray  # kg m^2, 3x3 about the centre of mass, link-frame axes
    joint: Joint
    motor: Motor


@dataclass(frozen=True)
class Arm:
    """A serial chain fixed at a base pose in the world (cochlea-centred) frame."""

    name: str
    base_xyz: np.ndarray  # m, base origin in the world frame
    base_yaw: float  # rad, rotation of the base frame about world z
    links: tuple[Link, ...]
    #: rad: the base frame's roll and pitch (``base_rpy_deg``; fixed-axis, R = Rz(yaw)
    #: Ry(pitch) Rx(roll)); zero for a base that only turns about the world z axis.
    base_roll: float = 0.0
    base_pitch: float = 0.0
    #: m: the tool point in the last link's frame (``tool_xyz_m``); None: ``[length_m, 0, 0]``.
    tool_xyz: np.ndarray | None = None
    #: rad: the tool frame's fixed-axis roll, pitch, yaw in the last link's frame
    #: (``tool_rpy_deg``); None: the last link's frame itself.
    tool_rpy: np.ndarray | None = None
    #: Optional keys for the tools (issue 25): the pose an excitation works around
    #: (``working_pose_deg``, rad here), ``cochlea-dxl calibrate``'s reference pose
    #: (``calibration_pose_deg``) and the joints' positive sense as the user sees it
    #: (``positive_direction``). None: the tools' defaults (docs/excitation.md, docs/hardware.md).
    working_pose: np.ndarray | None = None
    calibration_pose: np.ndarray | None = None
    positive_direction: str | None = None

    @property
    def base_rpy(self) -> np.ndarray:
        """rad: the base frame's fixed-axis roll, pitch and yaw in the world frame."""
        return np.array([self.base_roll, self.base_pitch, self.base_yaw])

    @property
    def base_is_level(self) -> bool:
        """True when the base frame only turns about the world z axis (no roll, no pitch)."""
        return self.base_roll == 0.0 and self.base_pitch == 0.0

    @property
    def base_rotation(self) -> np.ndarray:
        if not self.base_is_level:
            return rpy_matrix(self.base_rpy)
        c, s = math.cos(self.base_yaw), math.sin(self.base_yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class KeepOut:
    """A sphere no link may enter (world frame, SI): ``[[keep_out]]`` of a description."""

    name: str
    centre: np.ndarray  # m
    radius: float  # m


@dataclass(frozen=True)
class SerialSystem:
    """A system of serial arms sharing one world frame (the cochlea frame)."""

    name: str
    path: Path
    gravity: np.ndarray  # m/s^2, in the world frame
    arms: tuple[Arm, ...]
    #: m, R_m: the tools stay this far from the cochlea centre (the world origin) in task-space
    #: runs; None: ``keep_out_radius_m`` is absent, no keep-out circle (a user's arm).
    keep_out_radius: float | None = None
    #: Optional ``[[keep_out]]`` spheres (world frame) no link of an excitation may enter;
    #: None: the key is absent (the keep-out circle applies, docs/excitation.md).
    keep_out_volumes: tuple[KeepOut, ...] | None = None

    def described_pose(self, unit: str, which: str) -> np.ndarray | None:
        """The optional pose of arm ``unit`` its description gives: ``which`` "working"
        (``working_pose_deg``) or "calibration" (``calibration_pose_deg``); SI, or None."""
        arm = self.arm(unit)
        return arm.working_pose if which == "working" else arm.calibration_pose

    def described_positive(self, joint: str) -> str | None:
        """The ``positive_direction`` text of the arm of ``joint`` ("arm1.link2"), or None."""
        unit = joint.partition(".")[0]
        return next((a.positive_direction for a in self.arms if a.name == unit), None)

    def arm(self, name: str) -> Arm:
        for arm in self.arms:
            if arm.name == name:
                return arm
        raise ModelError(
            f"{self.path}: no arm named {name!r}; the arms are "
            + ", ".join(repr(a.name) for a in self.arms)
        )


# --------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------


def _within(bound: float):
    return lambda v: all(abs(x) <= bound for x in v)


def rpy_matrix(rpy: np.ndarray) -> np.ndarray:
    """Fixed-axis roll-pitch-yaw (rad) to a rotation matrix, R = Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), \
        math.sin(y)
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def inertia_matrix(six: np.ndarray) -> np.ndarray:
    """``[Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` to the symmetric 3x3 inertia matrix."""
    ixx, iyy, izz, ixy, ixz, iyz = six
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def _physical_inertia(six: list[float]) -> bool:
    """Positive definite with principal moments obeying the triangle inequality, every entry
    and moment within the description's bounds."""
    if not all(abs(x) <= MAX_INERTIA_KGM2 for x in six):
        return False
    moments = np.linalg.eigvalsh(inertia_matrix(np.array(six, dtype=float)))
    if moments[0] < MIN_INERTIA_KGM2:
        return False
    a, b, c = moments
    slack = 1e-12 * c
    return a + b >= c - slack


def _read_joint(t: Table, parent_length: float) -> Joint:
    name = t.name("name", required=False)
    jtype = t.string("type", ("revolute", "prismatic"))
    axis = t.vector("axis", 3, "the joint frame",
                    check=lambda v: all(abs(x) <= 1e3 for x in v) and np.linalg.norm(v) > 1e-9,
                    what="(a non-zero direction, each component within +-1000)")
    axis = axis / np.linalg.norm(axis)
    origin_xyz = t.vector("origin_xyz_m", 3, "m", check=_within(MAX_LENGTH_M),
                          what=f"(each within +-{MAX_LENGTH_M:g} m)", required=False)
    if origin_xyz is None:
        origin_xyz = np.array([parent_length, 0.0, 0.0])
    origin_rpy = t.vector("origin_rpy_deg", 3, "deg", check=_within(MAX_ANGLE_DEG),
                          what=f"(each within +-{MAX_ANGLE_DEG:g} deg)", required=False)
    origin_rpy = np.zeros(3) if origin_rpy is None else np.radians(origin_rpy)

    lo, hi, velocity, effort = read_limits(t, jtype)
    actuator = read_actuator(t, jtype)
    transmission = None
    if jtype == "prismatic":  # the motor's radians to the joint's metres: never guessed
        if "transmission" not in t.data:
            raise t.error("transmission", "a table (the key is missing): a prismatic joint's "
                          "motor moves it through a transmission, e.g. { kind = "
                          "\"lead_screw\", lead_m = 0.008 } or { kind = \"pinion\", radius_m "
                          "= 0.02 } (docs/extending.md)", show_got=False)
        transmission = read_transmission(t.table("transmission"))
    elif "transmission" in t.data:
        raise t.error("transmission", "no transmission on a revolute joint (its motor's output "
                      "shaft turns it directly; only a prismatic joint has one)",
                      show_got=False)
    t.done()
    return Joint(jtype, axis, origin_xyz, origin_rpy, (lo, hi), velocity, effort, actuator,
                 name, transmission)


def _read_link(t: Table, parent_length: float) -> Link:
    name = t.name("name")
    length = t.bounded("length_m", "a non-negative number (m)", lambda v: v >= 0, 0,
                       MAX_LENGTH_M, "m")
    mass = t.bounded("mass_kg", "a positive number (kg)", lambda v: v > 0, MIN_MASS_KG,
                     MAX_MASS_KG, "kg")
    com = t.vector("com_m", 3, "m", check=_within(MAX_LENGTH_M),
                   what=f"in the link frame, each within +-{MAX_LENGTH_M:g} m")
    inertia = t.vector(
        "inertia_com_kgm2", 6, "kg m^2",
        check=_physical_inertia,
        what="as [Ixx, Iyy, Izz, Ixy, Ixz, Iyz] about the centre of mass, forming a positive "
             "definite matrix whose principal moments obey the triangle inequality, each "
             f"moment in [{MIN_INERTIA_KGM2:g}, {MAX_INERTIA_KGM2:g}] kg m^2",
    )
    joint = _read_joint(t.table("joint"), parent_length)
    motor = read_motor(t.table("motor"))
    t.done()
    return Link(name, length, mass, com, inertia_matrix(inertia), joint, motor)


def _read_arm(t: Table) -> Arm:
    name = t.name("name")
    base_xyz = t.vector("base_xyz_m", 3, "m", check=_within(MAX_LENGTH_M),
                        what=f"in the world (cochlea) frame, each within +-{MAX_LENGTH_M:g} m")
    roll = pitch = 0.0
    if "base_rpy_deg" in t.data:  # the full base rotation; base_yaw_deg is its shorthand
        if "base_yaw_deg" in t.data:
            raise t.error("base_yaw_deg", "one of base_yaw_deg or base_rpy_deg (base_yaw_deg "
                          "is the shorthand of base_rpy_deg = [0, 0, yaw])", show_got=False)
        rpy = t.vector("base_rpy_deg", 3, "deg", check=_within(MAX_ANGLE_DEG),
                       what="(fixed-axis roll, pitch, yaw of the base frame in the world frame, "
                       f"each within +-{MAX_ANGLE_DEG:g} deg)")
        roll, pitch, base_yaw = (math.radians(float(v)) for v in rpy)
    else:
        base_yaw = math.radians(t.bounded("base_yaw_deg", "a number (deg)", lambda v: True,
                                          -MAX_ANGLE_DEG, MAX_ANGLE_DEG, "deg"))
    tool_xyz = t.vector("tool_xyz_m", 3, "m", check=_within(MAX_LENGTH_M), required=False,
                        what="(the tool point in the last link's frame; default [length_m of "
                        f"the last link, 0, 0]), each within +-{MAX_LENGTH_M:g} m")
    tool_rpy = t.vector("tool_rpy_deg", 3, "deg", check=_within(MAX_ANGLE_DEG), required=False,
                        what="(fixed-axis roll, pitch, yaw of the tool frame in the last link's "
                        f"frame), each within +-{MAX_ANGLE_DEG:g} deg")
    tool_rpy = None if tool_rpy is None else np.radians(tool_rpy)
    links = []
    parent_length = 0.0  # the first joint sits at the base origin unless told otherwise
    link_tables = t.tables("link", "the links from base to tip")
    if len(link_tables) > MAX_JOINTS:
        raise DescriptionError(t.path, t.key("link"), f"at most {MAX_JOINTS} [[arm.link]] tables "
                               " (a joint each: the model's cost grows with the cube of "
                               f"the joints), not {len(link_tables)}")
    for lt in link_tables:
        link = _read_link(lt, parent_length)
        links.append(link)
        parent_length = link.length
    poses = [_read_pose(t, key, links) for key in ("working_pose_deg", "calibration_pose_deg")]
    positive = t.get("positive_direction", "a short text (how the joints turn positive, as "
                     "the user sees them)", lambda v: isinstance(v, str) and 0 < len(v) <= 200,
                     required=False)
    t.done()
    names = [link.name for link in links]
    for i, n in enumerate(names):
        if n in names[:i]:
            raise DescriptionError(t.path, f"{t.where}.link[{i}].name",
                                   "a link name unique within the arm", n)
    # Joint names, given or the default (joint_name), name the model's joints and parameters
    # ("j1.Ia") and an exported URDF's joints: two alike would make both ambiguous.
    joints = [joint_name(link) for link in links]
    for i, n in enumerate(joints):
        if n in joints[:i]:
            given = links[i].joint.name is not None
            raise DescriptionError(
                t.path, f"{t.where}.link[{i}].joint.name" if given else f"{t.where}.link[{i}]",
                "a joint name unique within the arm (link "
                f"{joints.index(n)}'s joint is already called {n!r}"
                + ("" if given else f"; this link's joint is {n!r} by default: give it a "
                   "name") + ")", n)
    return Arm(name, base_xyz, base_yaw, tuple(links), roll, pitch, tool_xyz, tool_rpy,
               working_pose=poses[0], calibration_pose=poses[1], positive_direction=positive)


def joint_name(link: Link) -> str:
    """The name of ``link``'s joint: its ``name`` key, else ``jointK`` for a link ``linkK``
    (the shipped arms), else ``<link>_joint``."""
    if link.joint.name is not None:
        return link.joint.name
    if link.name.startswith("link"):
        return link.name.replace("link", "joint", 1)
    return f"{link.name}_joint"


def _read_pose(t: Table, key: str, links: list[Link]) -> np.ndarray | None:
    """An optional joint pose of the arm (deg for revolute joints, m for prismatic ones),
    inside every joint's position limits; SI."""
    if key not in t.data:
        t.used.add(key)
        return None
    raw = t.vector(key, len(links), "deg (m for a prismatic joint)",
                   check=lambda v: all(abs(x) <= MAX_ANGLE_DEG for x in v),
                   what=f"one value per link, each within +-{MAX_ANGLE_DEG:g}")
    pose = np.array([math.radians(v) if link.joint.type == "revolute" else v
                     for v, link in zip(raw, links)])
    for j, (v, link) in enumerate(zip(pose, links)):
        lo, hi = link.joint.position_limits
        if not lo <= v <= hi:
            raise DescriptionError(t.path, f"{t.key(key)}[{j}]", f"a position inside joint "
                                   f"{link.name}'s limits", float(raw[j]))
    return pose


def _read_keep_out(top: Table) -> tuple[KeepOut, ...] | None:
    if "keep_out" not in top.data:
        top.used.add("keep_out")
        return None
    volumes = []
    for i, t in enumerate(top.tables("keep_out", "spheres no link may enter")):
        name = t.name("name", required=False) or f"keep_out[{i}]"
        centre = t.vector("centre_m", 3, "m", check=_within(MAX_LENGTH_M),
                          what=f"in the world frame, each within +-{MAX_LENGTH_M:g} m")
        radius = t.bounded("radius_m", "a positive number (m)", lambda v: v > 0, 0,
                           MAX_LENGTH_M, "m")
        t.done()
        volumes.append(KeepOut(name, centre, radius))
    return tuple(volumes)


def load_serial(name_or_path: str | Path = "serial") -> SerialSystem:
    """Load and validate a description of serial arms (``kind = "serial"``)."""
    path = resolve_path(name_or_path)
    top, name, gravity, keep_out = open_description(
        path, "serial", 3, "in the world frame", "the cochlea centre that the tools",
        keep_out_required=False)
    arms = tuple(_read_arm(a) for a in top.tables("arm", "one per serial arm"))
    volumes = _read_keep_out(top)
    top.done()

    arm_names = [a.name for a in arms]
    for i, n in enumerate(arm_names):
        if n in arm_names[:i]:
            raise DescriptionError(path, f"arm[{i}].name", "an arm name unique in the file", n)
    check_unique_motor_ids(path, [(f"arm[{i}].link[{j}].motor.id", f"{arm.name}.{link.name}",
                                   link.motor)
                                  for i, arm in enumerate(arms)
                                  for j, link in enumerate(arm.links)])
    return SerialSystem(name, path, gravity, arms, keep_out, volumes)


def joint_rotation(joint: Joint) -> np.ndarray:
    """Rotation of the joint frame in the parent frame, from ``origin_rpy``."""
    return rpy_matrix(joint.origin_rpy)
