"""What every robot description shares: the TOML reader, the table that checks each key once,
the ``format`` line and ``[system]`` table, and the motors (Dynamixel model, ID, fit).

Every dimensional key carries its unit as a suffix (``_m``, ``_kg``, ``_kgm2``, ``_deg``,
``_rad_s``, ``_Nm``, ``_m_s2``, ...). Degrees exist only in the file: the dataclasses hold SI
values (metres, kilograms, radians). Any mistake -- a missing key, an unknown key, a wrong type,
a non-physical value -- raises one :class:`~cochlea.errors.DescriptionError` naming the file,
the key and what was expected. Each robot's own tables are read by its package
(:mod:`cochlea.robots.serial.description`, :mod:`cochlea.robots.parallel.description`).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..dynamixel.control_table import MODELS as MOTOR_SPECS
from ..errors import DescriptionError
from ..resources import ROBOTS_DIR, shipped

#: Value of the top-level ``format`` key this loader reads.
FORMAT = "cochlea-robot/1"

#: Quantities a motor's linear fit ``y = a x + b`` may relate (name_unit).
FIT_INPUTS = ("current_A", "current_mA")
FIT_OUTPUTS = ("torque_Ncm", "torque_Nm")

#: Largest Dynamixel ID usable by a motor (253..255 are reserved by Protocol 2.0).
MAX_MOTOR_ID = 252


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
    """The Dynamixel driving a joint and how the bridge maps it (``cochlea.dynamixel.drives``).

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


# --------------------------------------------------------------------------------------------
# Validation helpers
# --------------------------------------------------------------------------------------------


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class Table:
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

    def table(self, name: str) -> Table:
        self.used.add(name)
        if name not in self.data:
            raise self.error(name, "a table (the key is missing)", show_got=False)
        return Table(self.path, self.data[name], self.key(name))

    def tables(self, name: str, what: str) -> list[Table]:
        self.used.add(name)
        if name not in self.data:
            raise self.error(name, f"one or more [[{self.key(name)}]] tables ({what}), the key "
                             "is missing", show_got=False)
        items = self.data[name]
        if not isinstance(items, list) or not items or not all(isinstance(t, dict) for t in items):
            raise self.error(name, f"one or more [[{self.key(name)}]] tables ({what})", items)
        return [Table(self.path, t, f"{self.key(name)}[{i}]") for i, t in enumerate(items)]

    def done(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            known = ", ".join(sorted(self.used))
            raise self.error(unknown[0], f"no such key here (known keys: {known})",
                             show_got=False)


def read_limits(t: Table, jtype: str) -> tuple[float, float, float, float]:
    """A joint's ``(lower, upper, velocity, effort)`` limits in SI: rad, rad/s, N m for a
    revolute joint (limits written in deg), m, m/s, N for a prismatic one."""
    ordered = lambda v: v[0] < v[1]  # noqa: E731
    what = "as [lower, upper] with lower < upper"
    if jtype == "revolute":
        lo, hi = np.radians(t.vector("position_limits_deg", 2, "deg", check=ordered, what=what))
        velocity = t.number("velocity_limit_rad_s", "a positive number (rad/s)", lambda v: v > 0)
        effort = t.number("torque_limit_Nm", "a positive number (N m)", lambda v: v > 0)
    else:
        lo, hi = t.vector("position_limits_m", 2, "m", check=ordered, what=what)
        velocity = t.number("velocity_limit_m_s", "a positive number (m/s)", lambda v: v > 0)
        effort = t.number("force_limit_N", "a positive number (N)", lambda v: v > 0)
    return float(lo), float(hi), velocity, effort


@dataclass(frozen=True)
class Actuator:
    """What a joint's drive adds to the rigid links, in the joint's own coordinate (SI): the
    reflected rotor inertia (armature; kg m^2, or kg at a prismatic joint), viscous friction
    (N m s/rad or N s/m) and Coulomb friction (N m or N). None where the description gives no
    value. The thesis's rigid links are a model built with ``actuators="none"``."""

    armature: float | None = None
    viscous: float | None = None
    coulomb: float | None = None

    @property
    def declared(self) -> bool:
        return any(v is not None for v in (self.armature, self.viscous, self.coulomb))


#: Per joint type: the description keys of an actuator's terms and what each must be.
ACTUATOR_KEYS = {
    "revolute": {"armature": ("armature_kgm2", "kg m^2, the rotor's inertia times the gear "
                              "ratio squared"),
                 "viscous": ("viscous_friction_Nms_rad", "N m s/rad"),
                 "coulomb": ("coulomb_friction_Nm", "N m")},
    "prismatic": {"armature": ("armature_kg", "kg, the rotor's inertia over the "
                               "transmission's radius squared"),
                  "viscous": ("viscous_friction_Ns_m", "N s/m"),
                  "coulomb": ("coulomb_friction_N", "N")},
}


def read_actuator(t: Table, jtype: str) -> Actuator:
    """A joint's actuator terms, each optional (keys by joint type: :data:`ACTUATOR_KEYS`)."""
    values = {field: t.number(key, f"a non-negative number ({meaning})", lambda v: v >= 0,
                              required=False)
              for field, (key, meaning) in ACTUATOR_KEYS[jtype].items()}
    return Actuator(**values)


def read_motor(t: Table) -> Motor:
    model = t.string("model", tuple(MOTOR_SPECS))
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


def read_toml(path: Path) -> dict:
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
    """A bare name such as ``"serial"`` means the shipped ``serial.toml``; anything else is a
    path."""
    return shipped(ROBOTS_DIR, name_or_path)


def open_description(path: Path, kind: str, gravity_size: int, gravity_frame: str,
                     keep_out_around: str) -> tuple[Table, str, np.ndarray, float]:
    """The part every description shares: ``format`` and the ``[system]`` table (name, kind,
    gravity, the keep-out radius R_m). Returns the top-level table for the rest."""
    top = Table(path, read_toml(path), "")
    top.get("format", f"the string {FORMAT!r}", lambda v: v == FORMAT)
    system = top.table("system")
    name = system.string("name")
    system.string("kind", (kind,))
    gravity = system.vector("gravity_m_s2", gravity_size, "m/s^2", what=gravity_frame)
    keep_out = system.number("keep_out_radius_m", f"a positive number (m): R_m, the radius "
                             f"around {keep_out_around} must not enter", lambda v: v > 0)
    system.done()
    return top, name, gravity, keep_out


def check_unique_motor_ids(path: Path, joints: list[tuple[str, str, Motor]]) -> None:
    """Every motor on one bus needs its own ID: ``joints`` lists ``(key, name, motor)``."""
    seen: dict[int, str] = {}
    for key, name, motor in joints:
        if motor.id in seen:
            raise DescriptionError(path, key, f"a motor ID not already used (by {seen[motor.id]})",
                                   motor.id)
        seen[motor.id] = name
