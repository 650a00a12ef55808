"""Robot descriptions: load a TOML file from ``models/``, validate it, return frozen dataclasses.

Every dimensional key carries its unit as a suffix (``_m``, ``_kg``, ``_kgm2``, ``_deg``,
``_rad_s``, ``_Nm``, ``_m_s2``, ...). Degrees exist only in the file: the dataclasses hold SI
values (metres, kilograms, radians). Any mistake -- a missing key, an unknown key, a wrong type,
a non-physical value -- raises one :class:`~cochlea.errors.DescriptionError` naming the file,
the key and what was expected.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from .dynamixel.control_table import MODELS as MOTOR_SPECS
from .errors import DescriptionError

#: Folder of the descriptions shipped with the project.
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"

#: Value of the top-level ``format`` key this loader reads.
FORMAT = "cochlea-robot/1"

#: Dynamixel models the bridge knows, with their model numbers (control table address 0).
MOTOR_MODELS = {"MX-64": 311, "XM540-W270": 1120}

#: Quantities a motor's linear fit ``y = a x + b`` may relate (name_unit).
FIT_INPUTS = ("current_A", "current_mA")
FIT_OUTPUTS = ("torque_Ncm", "torque_Nm")

#: Largest Dynamixel ID usable by a motor (253..255 are reserved by Protocol 2.0).
MAX_MOTOR_ID = 252


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


@dataclass(frozen=True)
class MotorFit:
    """Linear calibration of a motor, ``y = a x + b`` (thesis Table C.1).

    ``x`` and ``y`` name the quantity and unit, e.g. ``x = "current_A"``,
    ``y = "torque_Ncm"``.
    """

    a: float
    b: float
    x: str
    y: str


@dataclass(frozen=True)
class Motor:
    """The Dynamixel driving a joint and how the bridge maps it (``cochlea.dynamixel.units``).

    ``zero_offset`` is the motor's angle (rad, Present Position x 2 pi / 4096) at which the
    joint coordinate is zero and ``direction`` (+1 or -1) whether joint and motor turn the same
    way. ``current_limit_mA`` is the Current Limit the bridge writes; ``None`` derives it from
    the joint's torque (force) limit through the fit.
    """

    model: str
    id: int
    fit: MotorFit
    direction: int = 1
    zero_offset: float = 0.0  # rad, motor angle at joint zero
    current_limit_mA: float | None = None


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

    @property
    def base_rotation(self) -> np.ndarray:
        c, s = math.cos(self.base_yaw), math.sin(self.base_yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SerialSystem:
    """A system of serial arms sharing one world frame (the cochlea frame)."""

    name: str
    path: Path
    gravity: np.ndarray  # m/s^2, in the world frame
    arms: tuple[Arm, ...]
    keep_out_radius: float = 0.0  # m, R_m: the tools stay this far from the cochlea centre

    def arm(self, name: str) -> Arm:
        for arm in self.arms:
            if arm.name == name:
                return arm
        from .errors import ModelError

        raise ModelError(
            f"{self.path}: no arm named {name!r}; the arms are "
            + ", ".join(repr(a.name) for a in self.arms)
        )


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class _Table:
    """Reads the keys of one TOML table, each once, and reports the keys nobody asked for."""

    def __init__(self, path: Path, data: Any, where: str):
        self.path = path
        self.where = where
        if not isinstance(data, dict):
            raise DescriptionError(path, where or "(top level)", "a table", data)
        self.data = data
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def error(self, name: str, expected: str, got: Any = None, *, show_got: bool = True):
        if show_got:
            return DescriptionError(self.path, self.key(name), expected, got)
        return DescriptionError(self.path, self.key(name), expected)

    def get(self, name: str, expected: str, check: Callable[[Any], bool], default: Any = None,
            required: bool = True) -> Any:
        self.used.add(name)
        if name not in self.data:
            if required:
                raise self.error(name, f"{expected} (the key is missing)", show_got=False)
            return default
        value = self.data[name]
        if not check(value):
            raise self.error(name, expected, value)
        return value

    def number(self, name: str, expected: str = "a number", check=lambda v: True, **kw) -> float:
        value = self.get(name, expected, lambda v: _is_number(v) and check(v), **kw)
        return None if value is None else float(value)

    def string(self, name: str, choices: tuple[str, ...] | None = None, **kw) -> str:
        if choices:
            expected = "one of " + ", ".join(repr(c) for c in choices)
            return self.get(name, expected, lambda v: isinstance(v, str) and v in choices, **kw)
        return self.get(name, "a non-empty string", lambda v: isinstance(v, str) and v != "", **kw)

    def vector(self, name: str, size: int, unit: str, check=lambda v: True, what: str = "",
               **kw) -> np.ndarray | None:
        expected = f"a list of {size} numbers in {unit}" + (f" {what}" if what else "")
        value = self.get(
            name, expected,
            lambda v: isinstance(v, list) and len(v) == size and all(_is_number(x) for x in v)
            and check(v),
            **kw,
        )
        return None if value is None else np.array(value, dtype=float)

    def table(self, name: str) -> "_Table":
        self.used.add(name)
        if name not in self.data:
            raise self.error(name, "a table (the key is missing)", show_got=False)
        return _Table(self.path, self.data[name], self.key(name))

    def tables(self, name: str, what: str) -> list["_Table"]:
        self.used.add(name)
        if name not in self.data:
            raise self.error(name, f"one or more [[{self.key(name)}]] tables ({what}), the key "
                             "is missing", show_got=False)
        items = self.data[name]
        if not isinstance(items, list) or not items or not all(isinstance(t, dict) for t in items):
            raise self.error(name, f"one or more [[{self.key(name)}]] tables ({what})", items)
        return [_Table(self.path, t, f"{self.key(name)}[{i}]") for i, t in enumerate(items)]

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            known = ", ".join(sorted(self.used))
            raise self.error(unknown[0], f"no such key here (known keys: {known})",
                             show_got=False)


def _rpy_matrix(rpy: np.ndarray) -> np.ndarray:
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
    """Positive definite with principal moments obeying the triangle inequality."""
    moments = np.linalg.eigvalsh(inertia_matrix(np.array(six, dtype=float)))
    if moments[0] <= 0.0:
        return False
    a, b, c = moments
    slack = 1e-12 * c
    return a + b >= c - slack


# --------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------


def _read_joint(t: _Table, parent_length: float) -> Joint:
    jtype = t.string("type", ("revolute", "prismatic"))
    axis = t.vector("axis", 3, "the joint frame", check=lambda v: np.linalg.norm(v) > 1e-9,
                    what="(a non-zero direction)")
    axis = axis / np.linalg.norm(axis)
    origin_xyz = t.vector("origin_xyz_m", 3, "m", required=False)
    if origin_xyz is None:
        origin_xyz = np.array([parent_length, 0.0, 0.0])
    origin_rpy = t.vector("origin_rpy_deg", 3, "deg", required=False)
    origin_rpy = np.zeros(3) if origin_rpy is None else np.radians(origin_rpy)

    ordered = lambda v: v[0] < v[1]  # noqa: E731
    if jtype == "revolute":
        lo, hi = np.radians(t.vector("position_limits_deg", 2, "deg", check=ordered,
                                     what="as [lower, upper] with lower < upper"))
        velocity = t.number("velocity_limit_rad_s", "a positive number (rad/s)", lambda v: v > 0)
        effort = t.number("torque_limit_Nm", "a positive number (N m)", lambda v: v > 0)
    else:
        lo, hi = t.vector("position_limits_m", 2, "m", check=ordered,
                          what="as [lower, upper] with lower < upper")
        velocity = t.number("velocity_limit_m_s", "a positive number (m/s)", lambda v: v > 0)
        effort = t.number("force_limit_N", "a positive number (N)", lambda v: v > 0)
    t.done()
    return Joint(jtype, axis, origin_xyz, origin_rpy, (float(lo), float(hi)), velocity, effort)


def _read_motor(t: _Table) -> Motor:
    model = t.string("model", tuple(MOTOR_MODELS))
    motor_id = t.get("id", f"an integer Dynamixel ID in 0..{MAX_MOTOR_ID}",
                     lambda v: isinstance(v, int) and not isinstance(v, bool)
                     and 0 <= v <= MAX_MOTOR_ID)
    f = t.table("fit")
    fit = MotorFit(
        a=f.number("a", "a non-zero number (slope of y = a x + b)", lambda v: v != 0),
        b=f.number("b", "a number (offset of y = a x + b)"),
        x=f.string("x", FIT_INPUTS),
        y=f.string("y", FIT_OUTPUTS),
    )
    f.done()
    direction = t.get("direction", "1 or -1 (the motor turns with the joint, or against it)",
                      lambda v: isinstance(v, int) and not isinstance(v, bool) and v in (1, -1),
                      default=1, required=False)
    zero_offset = t.number("zero_offset_deg", "a number (deg): the motor angle (Present "
                           "Position x 0.088 deg) at which the joint coordinate is zero",
                           default=0.0, required=False)
    largest = MOTOR_SPECS[model].max_current_mA
    current_limit = t.number("current_limit_mA", f"a positive number (mA) up to the {model}'s "
                             f"{largest:g} mA", lambda v: 0 < v <= largest, required=False)
    t.done()
    return Motor(model, motor_id, fit, direction, math.radians(zero_offset), current_limit)


def _read_link(t: _Table, parent_length: float) -> Link:
    name = t.string("name")
    length = t.number("length_m", "a non-negative number (m)", lambda v: v >= 0)
    mass = t.number("mass_kg", "a positive number (kg)", lambda v: v > 0)
    com = t.vector("com_m", 3, "m", what="in the link frame")
    inertia = t.vector(
        "inertia_com_kgm2", 6, "kg m^2",
        check=_physical_inertia,
        what="as [Ixx, Iyy, Izz, Ixy, Ixz, Iyz] about the centre of mass, forming a positive "
             "definite matrix whose principal moments obey the triangle inequality",
    )
    joint = _read_joint(t.table("joint"), parent_length)
    motor = _read_motor(t.table("motor"))
    t.done()
    return Link(name, length, mass, com, inertia_matrix(inertia), joint, motor)


def _read_arm(t: _Table) -> Arm:
    name = t.string("name")
    base_xyz = t.vector("base_xyz_m", 3, "m", what="in the world (cochlea) frame")
    base_yaw = math.radians(t.number("base_yaw_deg", "a number (deg)"))
    links = []
    parent_length = 0.0  # the first joint sits at the base origin unless told otherwise
    for lt in t.tables("link", "the links from base to tip"):
        link = _read_link(lt, parent_length)
        links.append(link)
        parent_length = link.length
    t.done()
    names = [link.name for link in links]
    for i, n in enumerate(names):
        if n in names[:i]:
            raise DescriptionError(t.path, f"{t.where}.link[{i}].name",
                                   "a link name unique within the arm", n)
    return Arm(name, base_xyz, base_yaw, tuple(links))


def _read_toml(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DescriptionError(path, "(file)", "an existing robot description file") from None
    except OSError as exc:
        raise DescriptionError(path, "(file)", "a readable file", str(exc)) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise DescriptionError(path, "(syntax)", "valid TOML", str(exc)) from None


def resolve_path(name_or_path: str | Path) -> Path:
    """A bare name such as ``"serial"`` means ``models/serial.toml``; anything else is a path."""
    candidate = Path(name_or_path)
    if candidate.suffix != ".toml" and candidate.parent == Path("."):
        return MODELS_DIR / f"{candidate}.toml"
    return candidate


def open_description(path: Path, kind: str, gravity_size: int, gravity_frame: str,
                     keep_out_around: str) -> tuple[_Table, str, np.ndarray, float]:
    """The part every description shares: ``format`` and the ``[system]`` table (name, kind,
    gravity, the keep-out radius R_m). Returns the top-level table for the rest."""
    top = _Table(path, _read_toml(path), "")
    top.get("format", f"the string {FORMAT!r}", lambda v: v == FORMAT)
    system = top.table("system")
    name = system.string("name")
    system.string("kind", (kind,))
    gravity = system.vector("gravity_m_s2", gravity_size, "m/s^2", what=gravity_frame)
    keep_out = system.number("keep_out_radius_m", f"a positive number (m): R_m, the radius "
                             f"around {keep_out_around} must not enter", lambda v: v > 0)
    system.done()
    return top, name, gravity, keep_out


def load_serial(name_or_path: str | Path = "serial") -> SerialSystem:
    """Load and validate a description of serial arms (``kind = "serial"``)."""
    path = resolve_path(name_or_path)
    top, name, gravity, keep_out = open_description(
        path, "serial", 3, "in the world frame", "the cochlea centre that the tools")
    arms = tuple(_read_arm(a) for a in top.tables("arm", "one per serial arm"))
    top.done()

    arm_names = [a.name for a in arms]
    for i, n in enumerate(arm_names):
        if n in arm_names[:i]:
            raise DescriptionError(path, f"arm[{i}].name", "an arm name unique in the file", n)
    seen: dict[int, str] = {}
    for i, arm in enumerate(arms):
        for j, link in enumerate(arm.links):
            where = f"arm[{i}].link[{j}].motor.id"
            if link.motor.id in seen:
                raise DescriptionError(
                    path, where, f"a motor ID not already used (by {seen[link.motor.id]})",
                    link.motor.id)
            seen[link.motor.id] = f"{arm.name}.{link.name}"
    return SerialSystem(name, path, gravity, arms, keep_out)


def joint_rotation(joint: Joint) -> np.ndarray:
    """Rotation of the joint frame in the parent frame, from ``origin_rpy``."""
    return _rpy_matrix(joint.origin_rpy)
