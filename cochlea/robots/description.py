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
import re
import tomllib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import files
from ..dynamixel.control_table import MODELS as MOTOR_SPECS
from ..errors import DescriptionError
from ..resources import ROBOTS_DIR, shipped

#: Value of the top-level ``format`` key this loader reads.
FORMAT = "cochlea-robot/1"

#: Quantities a motor's linear fit ``y = a x + b`` may relate (name_unit).
FIT_INPUTS = ("current_A", "current_mA")
FIT_OUTPUTS = ("torque_Ncm", "torque_Nm")
#: Where a motor's fit comes from (optional key ``source``): ``placeholder`` (a guess to
#: replace; ``cochlea-identify`` fits these from logs that carry the measured current),
#: ``datasheet``, ``measured`` (on the bench, e.g. ``cochlea-dxl calibrate --torque-fit``) or
#: ``identified`` (written back by ``cochlea-identify``).
FIT_SOURCES = ("placeholder", "datasheet", "measured", "identified")

#: Largest Dynamixel ID usable by a motor (253..255 are reserved by Protocol 2.0).
MAX_MOTOR_ID = 252

#: Bounds on what a description may say, physically generous but finite: a value beyond them
#: is a typo or a unit mistake, and refusing it here keeps CasADi from overflowing to inf/NaN
#: in a model built from it (docs/runtime.md, "Bad input").
MAX_FILE_BYTES = 1024 * 1024  # a description or scenario file (the shipped ones: ~10 KiB)
MAX_NESTING = 32  # levels of tables and lists
MAX_LENGTH_M = 10.0  # any length, position or offset
#: The smallest keep-out radius (m): a circle of less than a millimetre is within the arms'
#: positioning error (a joint's encoder count on a 0.1 m link is 0.15 mm) and keeps the tool
#: from nothing; ``keep_out_radius_m = 1e-300`` was a description with no protection that read
#: as one. A description without a circle leaves the key out (a user's serial arm).
MIN_KEEP_OUT_M = 1e-3
MIN_MASS_KG, MAX_MASS_KG = 1e-6, 1000.0
MIN_INERTIA_KGM2, MAX_INERTIA_KGM2 = 1e-12, 1000.0
MAX_GRAVITY_M_S2 = 100.0  # about 10 g
MAX_ANGLE_DEG = 3600.0  # ten turns: joint limits, offsets, base and frame angles
MAX_VELOCITY = {"revolute": 1000.0, "prismatic": 100.0}  # rad/s, m/s
MAX_EFFORT = {"revolute": 1000.0, "prismatic": 10000.0}  # N m, N
MAX_ARMATURE = {"revolute": 1000.0, "prismatic": 10000.0}  # kg m^2, kg
MAX_FIT = 1e6  # |a| and |b| of a motor's fit
MIN_FIT_SLOPE = 1e-6
#: Names of systems, arms, links and joints: they become column names, parameter names
#: (``link2.Izz``), file names (``arm1_tracking.png``) and the names of CasADi Functions and
#: generated C functions (``robot_arm1_M_p``), joined with ``_``. CasADi accepts a letter, then
#: letters, digits and single underscores; a ``-``, a doubled or trailing ``_`` would make the
#: joined name invalid (the model's build stopped with CasADi's own error), so none is a name.
NAME_PATTERN = re.compile(r"(?=.{1,64}$)[A-Za-z](?:_?[A-Za-z0-9])*")
NAME_RULE = ("a name of at most 64 letters, digits and single underscores, starting with a "
             "letter and not ending with _ (it names C and CasADi functions)")


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
    source: str | None = None  # one of FIT_SOURCES; None: not said (trusted)

    @property
    def placeholder(self) -> bool:
        return self.source == "placeholder"


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

    def name(self, name: str, **kw) -> str:
        """A name that can become a column, a parameter's prefix and part of a file name."""
        return self.get(name, NAME_RULE, lambda v: isinstance(v, str)
                        and NAME_PATTERN.fullmatch(v) is not None, **kw)

    def bounded(self, name: str, expected: str, check, lo: float, hi: float, unit: str,
                **kw) -> float | None:
        """:meth:`number`, then within [lo, hi]: a finite value beyond the bounds is refused
        with the range in the message."""
        value = self.number(name, expected, check, **kw)
        if value is not None and not lo <= value <= hi:
            raise self.error(name, f"{expected}, within [{lo:g}, {hi:g}] {unit}", value)
        return value

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
    def ordered(bound):
        return lambda v: v[0] < v[1] and -bound <= v[0] and v[1] <= bound

    vmax, emax = MAX_VELOCITY[jtype], MAX_EFFORT[jtype]
    positive = lambda v: v > 0  # noqa: E731
    if jtype == "revolute":
        what = f"as [lower, upper] with lower < upper, within +-{MAX_ANGLE_DEG:g} deg"
        lo, hi = np.radians(t.vector("position_limits_deg", 2, "deg",
                                     check=ordered(MAX_ANGLE_DEG), what=what))
        velocity = t.bounded("velocity_limit_rad_s", "a positive number (rad/s)", positive, 0,
                             vmax, "rad/s")
        effort = t.bounded("torque_limit_Nm", "a positive number (N m)", positive, 0, emax,
                           "N m")
    else:
        what = f"as [lower, upper] with lower < upper, within +-{MAX_LENGTH_M:g} m"
        lo, hi = t.vector("position_limits_m", 2, "m", check=ordered(MAX_LENGTH_M), what=what)
        velocity = t.bounded("velocity_limit_m_s", "a positive number (m/s)", positive, 0, vmax,
                             "m/s")
        effort = t.bounded("force_limit_N", "a positive number (N)", positive, 0, emax, "N")
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
    top = {"armature": MAX_ARMATURE[jtype], "viscous": MAX_EFFORT[jtype],
           "coulomb": MAX_EFFORT[jtype]}
    values = {field: t.bounded(key, f"a non-negative number ({meaning})", lambda v: v >= 0, 0,
                               top[field], meaning.split(",")[0], required=False)
              for field, (key, meaning) in ACTUATOR_KEYS[jtype].items()}
    return Actuator(**values)


#: Kinds of transmission between a motor and a prismatic joint, and the key of their size:
#: a pinion on a rack or a belt on a pulley (the pitch radius, m: m of travel per motor rad),
#: a lead screw (its lead, m of travel per motor revolution), or any mechanism given by its
#: ratio (m of travel per motor radian; what a URDF's ``mechanicalReduction`` gives).
TRANSMISSIONS = {"pinion": "radius_m", "belt": "radius_m", "lead_screw": "lead_m",
                 "ratio": "m_per_rad"}
#: The sizes a transmission may have (m): a lead of 0.1 mm per turn or a radius of 0.1 mm
#: is below any real screw or pulley, one metre above any; beyond them it is a typo or a unit
#: mistake (mm written as m) that would scale every position the motor reports.
TRANSMISSION_RANGE_M = (1e-4, 1.0)


@dataclass(frozen=True)
class Transmission:
    """How a motor moves a prismatic joint, ideal (lossless, no backlash): ``kind`` (one of
    :data:`TRANSMISSIONS`) and ``size``: m, a pinion's or pulley's pitch radius, or a lead
    screw's lead (travel per motor revolution); m/rad for ``ratio``. Its sign is the motor's
    ``direction``."""

    kind: str
    size: float  # m (m/rad for "ratio")

    @property
    def ratio(self) -> float:
        """Joint travel per motor angle, m/rad (> 0)."""
        return self.size / (2.0 * math.pi) if self.kind == "lead_screw" else self.size


def read_transmission(t: Table) -> Transmission:
    """A prismatic joint's ``[...transmission]`` table: ``kind`` and its size key
    (:data:`TRANSMISSIONS`), a finite number within :data:`TRANSMISSION_RANGE_M`."""
    kind = t.string("kind", tuple(TRANSMISSIONS))
    lo, hi = TRANSMISSION_RANGE_M
    if kind == "lead_screw":
        what = "a positive number (m, the screw's lead: joint travel per motor revolution)"
    elif kind == "ratio":
        what = "a positive number (m/rad: joint travel per motor radian)"
    else:
        what = f"a positive number (m, the {'pinion' if kind == 'pinion' else 'pulley'}'s " \
               "pitch radius: joint travel per motor radian)"
    size = t.bounded(TRANSMISSIONS[kind], what, lambda v: v > 0, lo, hi, "m")
    t.done()
    return Transmission(kind, size)


def read_motor(t: Table) -> Motor:
    model = t.string("model", tuple(MOTOR_SPECS))
    # Every joint is driven in Current Control mode: a model without it, or whose current unit
    # and largest Current Limit no source gave yet, is refused here, by name.
    problem = MOTOR_SPECS[model].current_control_problem()
    if problem:
        raise t.error("model", f"a model a current-controlled joint can use: {problem}", model)
    motor_id = t.get("id", f"an integer Dynamixel ID in 0..{MAX_MOTOR_ID}",
                     lambda v: isinstance(v, int) and not isinstance(v, bool)
                     and 0 <= v <= MAX_MOTOR_ID)
    f = t.table("fit")
    fit = MotorFit(
        a=f.number("a", f"a number with {MIN_FIT_SLOPE:g} <= |a| <= {MAX_FIT:g} (slope of "
                   "y = a x + b)", lambda v: MIN_FIT_SLOPE <= abs(v) <= MAX_FIT),
        b=f.bounded("b", "a number (offset of y = a x + b)", lambda v: True, -MAX_FIT, MAX_FIT,
                    "(the fit's unit)"),
        x=f.string("x", FIT_INPUTS),
        y=f.string("y", FIT_OUTPUTS),
        source=f.string("source", FIT_SOURCES, required=False),
    )
    f.done()
    direction = t.get("direction", "1 or -1 (the motor turns with the joint, or against it)",
                      lambda v: isinstance(v, int) and not isinstance(v, bool) and v in (1, -1),
                      default=1, required=False)
    zero_offset = t.bounded("zero_offset_deg", "a number (deg): the motor angle (Present "
                            "Position x 0.088 deg) at which the joint coordinate is zero",
                            lambda v: True, -MAX_ANGLE_DEG, MAX_ANGLE_DEG, "deg", default=0.0,
                            required=False)
    largest = MOTOR_SPECS[model].max_current_mA
    current_limit = t.number("current_limit_mA", f"a positive number (mA) up to the {model}'s "
                             f"{largest:g} mA", lambda v: 0 < v <= largest, required=False)
    t.done()
    return Motor(model, motor_id, fit, direction, math.radians(zero_offset), current_limit)


def read_toml(path: Path, what: str = "robot description") -> dict:
    """The TOML file at ``path`` (a ``what``: "robot description", "scenario") as a dict; any
    file that is missing, unreadable, too large, not UTF-8, not TOML or nested too deep is one
    :class:`DescriptionError` naming the file."""
    try:
        # Bounded, a regular file only: a huge file never fills memory, a FIFO or a device
        # never blocks the tool.
        raw = files.read_regular(path, MAX_FILE_BYTES)
    except FileNotFoundError:
        raise DescriptionError(path, "(file)", f"an existing {what} file") from None
    except IsADirectoryError:
        raise DescriptionError(path, "(file)", f"a {what} file, not a folder") from None
    except OSError as exc:
        raise DescriptionError(path, "(file)", f"a readable {what} file",
                               exc.strerror or str(exc)) from None
    except ValueError:  # a NUL byte in the path
        raise DescriptionError(path, "(file)", f"a {what} file name without NUL bytes") \
            from None
    return parse_toml(raw, path, what)


def parse_toml(raw: bytes, path: Path, what: str = "robot description") -> dict:
    """:func:`read_toml` of a file's bytes already read (``path`` names it in the messages):
    the same checks, the same refusals."""
    if len(raw) > MAX_FILE_BYTES:
        raise DescriptionError(path, "(file)", f"a {what} file of at most "
                               f"{MAX_FILE_BYTES // 1024} KiB")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise DescriptionError(path, f"(line {line})", "UTF-8 text (save the file as UTF-8)",
                               f"byte 0x{raw[exc.start]:02x}") from None
    try:
        data = tomllib.loads(text)
    except ValueError as exc:  # TOMLDecodeError, or an integer of over 4300 digits
        raise DescriptionError(path, "(syntax)", "valid TOML", str(exc)) from None
    except RecursionError:
        raise DescriptionError(path, "(syntax)", f"tables and lists nested at most "
                               f"{MAX_NESTING} deep") from None
    check_structure(path, data)
    return data


def check_structure(path: Path, data: dict) -> None:
    """Refuse structures deeper than MAX_NESTING, which no description or scenario needs and
    which recursive code (printing a value, copying it) could not handle; and integers beyond
    64 bits, which TOML itself rules out (tomllib reads them whole) and which end any check
    that takes them as a float (``math.isfinite``) in an OverflowError."""
    stack = [("", data, 0)]
    while stack:
        key, value, depth = stack.pop()
        if depth > MAX_NESTING:
            raise DescriptionError(path, key, f"tables and lists nested at most {MAX_NESTING} "
                                   "deep")
        if isinstance(value, int) and not -2**63 <= value < 2**63:
            digits = len(str(abs(value)))
            raise DescriptionError(path, key, "an integer within 64 bits (TOML's range; a "
                                   "float such as 1e30 for a large number)",
                                   f"an integer of {digits} digits")
        if isinstance(value, dict):
            stack.extend((f"{key}.{k}" if key else str(k), v, depth + 1)
                         for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((f"{key}[{i}]", v, depth + 1) for i, v in enumerate(value))


def resolve_path(name_or_path: str | Path) -> Path:
    """A bare name such as ``"serial"`` means the shipped ``serial.toml``; anything else is a
    path."""
    return shipped(ROBOTS_DIR, name_or_path)


def open_description(path: Path, kind: str, gravity_size: int, gravity_frame: str,
                     keep_out_around: str, keep_out_required: bool = True
                     ) -> tuple[Table, str, np.ndarray, float | None]:
    """The part every description shares: ``format`` and the ``[system]`` table (name, kind,
    gravity, the keep-out radius R_m; None when absent and ``keep_out_required`` is False).
    Returns the top-level table for the rest."""
    top = Table(path, read_toml(path), "")
    top.get("format", f"the string {FORMAT!r}", lambda v: v == FORMAT)
    system = top.table("system")
    name = system.name("name")
    system.string("kind", (kind,))
    gravity = system.vector("gravity_m_s2", gravity_size, "m/s^2",
                            check=lambda v: math.hypot(*v) <= MAX_GRAVITY_M_S2,
                            what=f"{gravity_frame}, of magnitude at most {MAX_GRAVITY_M_S2:g}")
    keep_out = system.bounded("keep_out_radius_m", f"a positive number (m): R_m, the radius "
                              f"around {keep_out_around} must not enter", lambda v: v > 0,
                              MIN_KEEP_OUT_M, MAX_LENGTH_M, "m", required=keep_out_required)
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
