"""Simulation scenarios: load a TOML file (a shipped one from ``models/scenarios/``) and
validate it.

A scenario names the robot and the space, the duration, the control settings, the leader's
desired trajectory (formulas in ``t`` with a unit, exactly as printed in the thesis), each
controlled unit's initial state and gains, and optionally how the simulated plant differs from
the controller's nominal model. Every quantity with a dimension is written with its unit, e.g.
``"73 deg"``, ``"0.03*cos(a1) m"``; degrees are converted to radians on loading.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import math
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from .. import files
from ..control.gains import controller_of
from ..errors import CochleaError, DescriptionError
from ..resources import ROBOTS_DIR, SCENARIOS_DIR, shipped, shipped_file
from ..robots import ROBOTS
from ..robots import robot as robot_adapter
from ..robots.adapter import sampled
from ..robots.description import MAX_FILE_BYTES, MAX_NESTING, Table, parse_toml, read_toml
from ..robots.description import check_structure as check_nesting
from ..robots.description import resolve_path as resolve_description
from ..robots.model import ACTUATORS
from .expressions import FUNCTIONS, ExpressionError, parse

FORMAT = "cochlea-scenario/1"
#: ``[plant] plant = "<preset>"``: defaults for the plant's keys, each still settable.
#: realistic: the geared Dynamixels as the description and the datasheets give them -- the
#: rotor (armature) behind a gear with the datasheet's backlash, the encoder on the output side
#: (``gearbox``), viscous and Coulomb friction with static friction 1.5x Coulomb (Stribeck) in
#: the gearbox -- measured on the encoder grid and in velocity-register counts, driven through
#: the bridge's current conversion (its offset current where the bridge adds it:
#: ``bridge_offset = "auto"``) in whole Goal Current LSBs up to the Current Limit, one period of
#: measurement delay. (Before the gearbox: rigid links with the armature, Coulomb friction
#: without static friction, no bridge offset, and a Current Limit net of friction.)
#: Issue 24's "everything at once" case adds, in a study's own ``[plant]`` table (the preset
#: leaves them off): ``delay_jitter_periods = 2`` (with ``delay_periods = 1``: 1..3 periods
#: old), ``encoder_noise_counts = 1`` (+-1 count) and ``torque_constant_error = 0.05`` (5 %);
#: docs/robustness.md, "The disturbances of the everything-at-once case".
PLANT_PRESETS = {
    "ideal": {},
    "realistic": {"armature": True, "friction_from_description": True,
                  "position_encoder": True, "velocity_register": True,
                  "current_quantisation": True, "delay_periods": 1, "gearbox": True,
                  "static_friction_ratio": 1.5, "bridge_offset": "auto"},
}
#: ``[plant] bridge_offset``: whether the bridge adds the fit's offset current to the
#: controller's effort; "auto": what the bridge does for the scenario's controller
#: (:func:`cochlea.robots.motor_fit.bridge_compensates_friction`).
BRIDGE_OFFSET = ("auto", True, False)
UNITS = {"deg": ("angle", np.pi / 180.0), "rad": ("angle", 1.0), "m": ("length", 1.0),
         "mm": ("length", 1e-3)}

#: Bounds on what a scenario may ask (docs/runtime.md, "Bad input"): generous for the lab,
#: finite so that no value exhausts the machine or overflows the maths.
MIN_RATE_HZ, MAX_RATE_HZ = 1.0, 20_000.0
#: RK4 steps per period: each adds a full step to every period's plant (and the symbolic
#: plant grows with it); 1000 already costs seconds to build and milliseconds per period.
MAX_PLANT_SUBSTEPS = 1000
#: Periods of one run: 24 h at 1 kHz. Longer runs are split into several.
MAX_PERIODS = 86_400_000
MAX_GAIN = 1e6  # every controller gain, Gamma's scale, the estimate bound (SI)
MAX_MASS_SCALE = 100.0
MAX_PAYLOAD_KG = 100.0
MAX_FRICTION = 1e4  # N m (s/rad) or N (s/m)
MAX_NOISE_Q, MAX_NOISE_QD = 1.0, 100.0  # rad or m; rad/s or m/s
MAX_DELAY_PERIODS = 1000
#: ``encoder_noise_counts``: whole encoder counts of noise (4096 per motor turn).
MAX_ENCODER_NOISE_COUNTS = 1000
#: ``torque_constant_error``: the motor's torque over the fit's, 1 + e with |e| at most this.
MAX_TORQUE_CONSTANT_ERROR = 0.5
MAX_BACKLASH = 0.1  # rad (5.7 deg) or m, at the joint
MAX_GEAR_STIFFNESS = 1e7  # N m/rad or N/m
MAX_STATIC_FRICTION_RATIO = 10.0
MAX_STRIBECK_VELOCITY = 100.0  # rad/s or m/s
MAX_DEFINITIONS = 100
#: Names a definition may not take: they already mean something in a formula.
RESERVED_NAMES = frozenset({"t", "pi", *FUNCTIONS})
@dataclass(frozen=True)
class Quantity:
    """A formula in t (s) with its unit; ``expression(t)`` gives SI values (rad or m)."""

    text: str
    kind: str  # "angle" | "length"
    scale: float  # to SI

    def expression(self, t: ca.SX, definitions: dict[str, ca.SX]) -> ca.SX:
        return self.scale * parse(self.text, t, definitions)


@dataclass(frozen=True)
class Unit:
    """One controlled unit: an arm of the serial system, or the parallel mechanism."""

    name: str
    initial_joint: np.ndarray | None  # SI
    initial_task: np.ndarray | None  # SI
    initial_velocity: np.ndarray | None  # SI per second (joint space)
    elbow: int | None  # IK branch (serial: sign of th2)
    gains: dict[str, np.ndarray]
    #: The unit's own desired joint path (joint space only): tracked instead of what the
    #: leader and the dual-arm / mirror rule would give it, e.g. one serial arm excited for
    #: identification while the other holds still (``cochlea-excite``). None: the rule.
    desired_joint: tuple[Quantity, ...] | None = None


@dataclass(frozen=True)
class Plant:
    """How the simulated robot differs from the controller's nominal description."""

    mass_scale: np.ndarray | None = None  # per link / body: all its inertial parameters scale
    payload_kg: float = 0.0  # point mass at each tool point
    viscous_friction: np.ndarray | None = None  # N m s/rad or N s/m per joint
    coulomb_friction: np.ndarray | None = None  # N m or N per joint, with sticking
    noise_q_std: float = 0.0  # rad (or m), Gaussian, on measured positions
    noise_qd_std: float = 0.0  # rad/s (or m/s), on measured velocities
    delay_periods: int = 0  # whole control periods between measurement and command
    seed: int = 0
    #: Measured positions on the motor's encoder grid (4096 counts per motor turn).
    position_encoder: bool = False
    #: Measured velocities in the motor's Present Velocity units (0.229 rpm per count).
    velocity_register: bool = False
    #: Applied efforts as the motors produce them: whole Goal Current LSBs through each joint's
    #: fit, saturated at the Current Limit (see :func:`cochlea.robots.motor_fit.effort_grid`).
    current_quantisation: bool = False
    #: The preset the table started from (:data:`PLANT_PRESETS`).
    preset: str = "ideal"
    #: The description's armature (reflected rotor inertia) in the plant's mass matrix.
    armature: bool = False
    #: Viscous and Coulomb friction from the description's actuators wherever the scenario
    #: gives no ``viscous_friction_SI`` / ``coulomb_friction_SI``.
    friction_from_description: bool = False
    #: The geared drive (:func:`cochlea.robots.plant.gear_plant_step`): per joint a rotor (the
    #: armature) coupled to the link through a gear with backlash, the encoder on the link.
    gearbox: bool = False
    #: Per joint (rad or m at the joint), the gear's full backlash, stiffness (N m/rad or N/m)
    #: and damping (N m s/rad or N s/m); None: the motor model's datasheet figures and
    #: estimates (:class:`cochlea.dynamixel.control_table.Gearbox`) through the joint's ratio.
    backlash: np.ndarray | None = None
    gear_stiffness: np.ndarray | None = None
    gear_damping: np.ndarray | None = None
    #: Static over Coulomb friction (breakaway level / sliding level), 1: plain Coulomb.
    static_friction_ratio: float = 1.0
    #: Per joint (rad/s or m/s), the Stribeck velocity; None: the motor model's, through the
    #: joint's ratio.
    stribeck_velocity: np.ndarray | None = None
    #: Whether the bridge's offset current reaches the motors: "auto", True or False
    #: (:data:`BRIDGE_OFFSET`).
    bridge_offset: str | bool = False
    #: Whole periods the delay jitters by: each period's measurement is ``delay_periods + j``
    #: periods old, ``j`` uniform in 0..this, drawn from ``seed`` (its own stream:
    #: :func:`cochlea.sim.setup.delay_ages`); 0: a fixed delay.
    delay_jitter_periods: int = 0
    #: Whole encoder counts of position noise: each joint's measured position off by an integer
    #: uniform in -N..N counts of its encoder, per period, from ``seed`` (its own stream:
    #: :func:`cochlea.sim.setup.encoder_noise`); only with ``position_encoder``. 0: none.
    encoder_noise_counts: int = 0
    #: Per joint of a unit (every unit alike), the motor's torque constant error ``e``
    #: (dimensionless): the motor gives ``1 + e`` times the effort the bridge's fit assumes,
    #: applied after the drive's rounding and saturation (the Current Limit bounds the
    #: current, so the torque at saturation scales too); None: none.
    torque_constant_error: np.ndarray | None = None


#: Bounds of the robust-adaptation keys of ``[control]`` (:class:`RobustOptions`).
MAX_DEADZONE = 100.0  # rad/s or m/s
MAX_STATIC_RATIO = 10.0  # static over Coulomb friction
MAX_STRIBECK_VELOCITY = 100.0  # rad/s or m/s
MAX_RAMP_S = 3600.0
#: The Stribeck velocity a joint's static friction fades over when the scenario gives none:
#: about 4 counts of the MX-64's velocity register at a revolute joint; at the slider, the
#: same motor speed through its 20 mm pinion.
STRIBECK_VELOCITY = {"angle": 0.1, "length": 0.002}


@dataclass(frozen=True)
class RobustOptions:
    """The controller's robust-adaptation options (``[control]``; docs/controllers.md, "Robust
    adaptation"). The defaults leave the thesis's law as it is."""

    #: Per joint of a unit (every unit alike): the width of the adaptation's dead zone on its
    #: signal (r, e_v or e_d), rad/s or m/s. None: no dead zone.
    deadzone: np.ndarray | None = None
    #: Each estimate within ``p_nominal +- box_relative * max(|p_nominal|, 1e-3 max|p_nominal|)``;
    #: None: no box beyond the ball.
    box_relative: float | None = None
    #: "physical": masses, inertias, armatures and frictions never below zero; "free": any sign.
    sign: str = "free"
    #: Per joint: static over Coulomb friction (>= 1) compensated on the Stribeck curve; None:
    #: Coulomb only.
    static_ratio: np.ndarray | None = None
    #: Per joint: the Stribeck velocity the static excess fades over (rad/s or m/s).
    stribeck_velocity: np.ndarray | None = None
    #: s: the desired path blended from the initial pose onto the planned one (quintic); 0: none.
    startup_ramp: float = 0.0


@dataclass(frozen=True)
class Scenario:
    path: Path
    name: str
    robot: str
    space: str
    #: A shipped description's bare name ("serial"), or the path of a file; a relative path
    #: in the file is relative to the scenario's folder, and is held here joined with it.
    description: str
    duration: float  # s
    rate_hz: float
    plant_substeps: int
    variant: str
    parameterisation: str
    adaptation_gain: float
    #: How Gamma spreads over the parameters: "uniform" (``adaptation_gain`` each, the
    #: thesis) or "relative" (``adaptation_gain * p_nominal_i^2``: every estimate moves at the
    #: same rate relative to its size, whatever its unit).
    adaptation: str
    initial_estimate: str  # "zero" | "nominal"
    estimate_bound: float  # relative to |p_nominal|
    #: The dual-arm rule's source (robots with one: ``RobotAdapter.mirror_modes``): "desired",
    #: the leader's desired pose, a smooth function of t; "measured", the leader's measured
    #: pose, period by period (docs/controllers.md, "The dual-arm rule").
    mirror: str
    #: What the controller's model carries of the drives (:data:`cochlea.robots.model.ACTUATORS`)
    controller_actuators: str
    definitions: dict[str, str]
    leader: tuple[Quantity, ...]
    units: tuple[Unit, ...]
    plant: Plant = field(default_factory=Plant)
    #: The robot's description, loaded once with the scenario (SerialSystem or ParallelSystem).
    system: Any = field(default=None, repr=False, compare=False)
    #: The controller's robust-adaptation options (``[control]``).
    robust: RobustOptions = field(default_factory=RobustOptions)
    #: ``[control] task``: the tool coordinates of a robot that offers a choice (a serial
    #: arm: "planar", "planar_yaw" (the default), "position", "pose"; docs/models.md, "Task
    #: spaces"); None for a robot with one task space.
    task: str | None = None

    @property
    def controller(self) -> str:
        return controller_of(self.robot, self.space).kind

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def plant_actuators(self) -> str:
        """What the simulated plant's model carries of the drives: its friction is the plant
        step's own input, so at most the armature; with the gearbox the armature is the
        rotor's own coordinate, so the links' model is rigid."""
        return "armature" if self.plant.armature and not self.plant.gearbox else "none"

    def desired_leader(self) -> ca.Function:
        """``t -> (x_d, x_d', x_d'')`` of the leader, derivatives exact (symbolic)."""
        t = ca.SX.sym("t")
        definitions: dict[str, ca.SX] = {}
        for name, text in self.definitions.items():
            definitions[name] = parse(text, t, definitions)
        x = ca.vertcat(*[q.expression(t, definitions) for q in self.leader])
        xd = ca.jacobian(x, t)
        xdd = ca.jacobian(xd, t)
        return ca.Function("desired_leader", [t], [x, xd, xdd], ["t"], ["x", "x_dot", "x_ddot"])

    def unit_desired(self, name: str, t: ca.SX) -> ca.SX | None:
        """Unit ``name``'s own desired joint path (``desired_joint``) as an expression of the
        symbol ``t`` (SI), the ``[desired] define`` names applied; None when the unit follows
        the leader."""
        unit = next(u for u in self.units if u.name == name)
        if unit.desired_joint is None:
            return None
        definitions: dict[str, ca.SX] = {}
        for key, text in self.definitions.items():
            definitions[key] = parse(text, t, definitions)
        return ca.vertcat(*[q.expression(t, definitions) for q in unit.desired_joint])


def check_desired(sc: Scenario) -> None:
    """Every leader coordinate and its first two derivatives finite at every period of the
    scenario's run (``sc.duration``; sampled, :func:`cochlea.robots.adapter.sample_times`):
    a formula that divides by zero, overflows or leaves its domain at some t is refused with
    the file and the key, before anything moves."""
    names = ("", "its velocity ", "its acceleration ")
    for times, outputs in sampled(sc.desired_leader(), sc.duration, sc.period):
        for order, values in enumerate(outputs):
            bad = np.argwhere(~np.isfinite(values))
            if bad.size:
                i, k = bad[0]
                raise DescriptionError(
                    sc.path, f"desired.leader[{i}]", "a formula finite at every t of the run",
                    f"{names[order]}{values[i, k]} at t = {times[k]:.6g} s "
                    f"({sc.leader[i].text})")


def stressed(sc: Scenario, mass_scale: float, delay_periods: int = 2,
             payload_kg: float = 0.05) -> Scenario:
    """``sc`` with its plant's errors of the robustness studies: every body's inertial
    parameters scaled by ``mass_scale``, a payload (kg) at each tool, whole periods of
    measurement delay; the rest of its ``[plant]`` as it was."""
    n_bodies = robot_adapter(sc.robot).layout(sc.system, sc.space).n_bodies
    plant = replace(sc.plant, delay_periods=delay_periods, payload_kg=payload_kg,
                    mass_scale=np.full(n_bodies, float(mass_scale)))
    return replace(sc, plant=plant)


#: Descriptions a process keeps loaded (:func:`load_system`).
SYSTEM_CACHE_SIZE = 8
_SYSTEMS: OrderedDict[tuple, Any] = OrderedDict()


def load_system(robot: str, description: str | Path):
    """The robot's description (``robot(robot).load(description)``), read and validated once
    per process for each file content: a sweep loads thousands of scenarios naming the same
    file. The key holds the file's bytes' hash, so an edited file is read again; the systems
    are frozen dataclasses, safe to share. Errors are the loader's own (nothing is cached)."""
    adapter = robot_adapter(robot)
    named = (robot, description, os.getcwd())  # a relative path is the working folder's
    seen = _SEEN.get(named)
    if seen is not None and seen[0] is adapter and _unchanged(seen[1], seen[2]):
        return seen[3]
    path = resolve_description(description if description is not None else robot)
    try:
        before = _file_state(path)
        raw = files.read_regular(path, MAX_FILE_BYTES)
    except (OSError, ValueError):
        return adapter.load(description)  # the loader's error, naming the file
    key = (robot, str(path), os.path.abspath(path), hashlib.sha256(raw).digest())
    system = _SYSTEMS.get(key)
    if system is None:
        system = _SYSTEMS[key] = adapter.load(description)
        while len(_SYSTEMS) > SYSTEM_CACHE_SIZE:
            _SYSTEMS.popitem(last=False)
    else:
        _SYSTEMS.move_to_end(key)
    if before is not None and before[3] < time.time_ns() - _SETTLED_NS:
        _SEEN[named] = (adapter, str(path), before, system)
        while len(_SEEN) > SYSTEM_CACHE_SIZE:
            with contextlib.suppress(KeyError, RuntimeError, StopIteration):
                _SEEN.pop(next(iter(_SEEN)))
    return system


#: :func:`load_system`'s descriptions by how they were named (robot, description, working
#: folder): the adapter, the file's path and its state when read (:func:`_file_state`), the
#: system. The file is not read again while its state is the same.
_SEEN: dict[tuple, tuple[Any, str, tuple, Any]] = {}
#: A file changed less than this long before it was read (ns) is read again every time: a
#: file system's clock may not tell two writes within it apart (git's "racily clean" files).
_SETTLED_NS = 2_000_000_000


def _file_state(path) -> tuple | None:
    """What tells a file's content changed without reading it: device, inode, size and the
    times of its last change (of data and of status, nanoseconds); None for no file."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _unchanged(path: str, state: tuple) -> bool:
    return _file_state(path) == state


def resolve(name_or_path: str | Path) -> Path:
    """A bare name (``"serial_task"``) is a shipped scenario; anything else a path."""
    return shipped(SCENARIOS_DIR, name_or_path)


def _quantity(table: Table, key: str, text, kinds: tuple[str, ...] | None, index: int,
              definitions: tuple[str, ...]) -> Quantity:
    where = f"{key}[{index}]"
    expected = ("a string '<formula in t> <unit>' with unit one of " + ", ".join(UNITS)
                + (f" (a{'n' if kinds[0][0] in 'aeiou' else ''} {kinds[0]})" if kinds else ""))
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        raise table.error(where, expected, text)
    if not isinstance(text, str) or len(text.rsplit(None, 1)) != 2:
        raise table.error(where, expected, text)
    formula, unit = text.rsplit(None, 1)
    if unit not in UNITS or (kinds and UNITS[unit][0] != kinds[0]):
        raise table.error(where, expected, text)
    reason = _formula_problem(formula, tuple(definitions))
    if reason is not None:
        raise table.error(where, f"a valid formula ({reason})", text) from None
    return Quantity(formula, UNITS[unit][0], UNITS[unit][1])


# A formula's verdict and a constant's value are functions of their text alone: a sweep loads
# thousands of scenarios that differ in their plant and gains, not in their formulas.
@lru_cache(maxsize=4096)
def _formula_problem(formula: str, definitions: tuple[str, ...]) -> str | None:
    """Why the parser refuses ``formula`` (the names ``definitions`` defined), or None."""
    try:
        parse(formula, ca.SX.sym("t"), {n: ca.SX(0) for n in definitions})
    except ExpressionError as exc:
        return exc.reason
    return None


@lru_cache(maxsize=256)
def _definitions_problem(items: tuple[tuple[str, str], ...]) -> tuple[str, str, str] | None:
    """``(name, formula, reason)`` of the first ``[desired] define`` the parser refuses (each
    formula may use the names before it), or None."""
    t = ca.SX.sym("t")
    defs: dict[str, ca.SX] = {}
    for name, text in items:
        try:
            defs[name] = parse(text, t, defs)
        except ExpressionError as exc:
            return name, text, exc.reason
    return None


def quantities(table: Table, key: str, kinds: tuple[str, ...], required: bool = True,
               definitions: tuple[str, ...] = ()) -> tuple[Quantity, ...] | None:
    """A list of quantities of the given kinds (``angle`` / ``length``), one per coordinate."""
    table.used.add(key)
    if key not in table.data:
        if required:
            raise table.error(key, f"a list of {len(kinds)} quantities (the key is missing)",
                              show_got=False)
        return None
    items = table.data[key]
    if not isinstance(items, list) or len(items) != len(kinds):
        raise table.error(key, f"a list of {len(kinds)} quantities ("
                          + ", ".join(kinds) + ")", items)
    return tuple(_quantity(table, key, item, (kind,), i, definitions)
                 for i, (item, kind) in enumerate(zip(items, kinds)))


def constant_values(qs: tuple[Quantity, ...] | None) -> np.ndarray | None:
    """Values of quantities that must not depend on t (initial states), each finite."""
    if qs is None:
        return None
    values = _constant_values(qs)
    if isinstance(values, str):
        raise ExpressionError(values)
    return np.array(values)


@lru_cache(maxsize=1024)
def _constant_values(qs: tuple[Quantity, ...]) -> tuple[float, ...] | str:
    """:func:`constant_values`'s values, or the message of its ExpressionError."""
    try:
        return tuple(_evaluate_constants(qs))
    except ExpressionError as exc:
        return str(exc)


def _evaluate_constants(qs: tuple[Quantity, ...]) -> list[float]:
    t = ca.SX.sym("t")
    values = []
    for q in qs:
        expr = q.expression(t, {})
        if ca.depends_on(expr, t):
            raise ExpressionError(f"{q.text!r} must be a constant")
        value = float(ca.evalf(expr))
        if not np.isfinite(value):
            raise ExpressionError(f"{q.text!r} is {value}, not a finite number")
        values.append(value)
    return values


def _positive_list(table: Table, key: str, size: int) -> np.ndarray:
    return table.vector(key, size, "the gain's SI unit",
                        check=lambda v: all(0 < x <= MAX_GAIN for x in v),
                        what=f"(all positive, at most {MAX_GAIN:g})")


def _check_run_length(top: Table, duration: float, rate: float) -> None:
    """A scenario's own run: at least one period, at most MAX_PERIODS."""
    periods = duration * rate
    if periods < 1.0:
        raise top.error("duration_s", f"at least one control period ({1.0 / rate:g} s at "
                        f"[control] rate_Hz = {rate:g})", duration)
    if periods > MAX_PERIODS:
        raise top.error("duration_s", f"at most {MAX_PERIODS:,} control periods "
                        f"({MAX_PERIODS / rate:g} s at {rate:g} Hz): split a longer session "
                        "into several runs", duration)


def load(name_or_path: str | Path, plant_preset: str | None = None, *,
         text: str | None = None, data: dict | None = None) -> Scenario:
    """Load a scenario and the robot description it names; the robot's adapter tells the
    kinds and sizes of its coordinates (:class:`~cochlea.robots.adapter.Layout`).

    ``plant_preset`` (``cochlea-run --plant``) replaces the preset of the scenario's
    ``[plant]`` table (or gives one where there is none); its other keys still apply.
    ``text``: the scenario file's text, already in memory (a sweep's sample): read as the
    file at ``name_or_path`` would be, which names it in messages and is where a relative
    description is found from, but is not read. ``data``: the file's TOML data, already
    parsed (a sweep's sample, built from its base scenario's data without writing and reading
    its text back: ``tomllib.loads`` of the text gives the same data); checked and read as the
    parsed file's would be, and not changed.

    A scenario whose data differs from one this process loaded before only in its
    ``[plant]`` table and its units' gains (a sweep's samples, a tuning search's candidates)
    has everything else taken from that one (:func:`_known`): only those tables are read
    and checked again; the same scenario, bit for bit, and any error the same."""
    path = resolve(name_or_path)
    if data is not None:
        if text is not None:
            raise CochleaError("load: give a scenario's text or its data, not both")
    else:
        data = read_toml(path, "scenario") if text is None else \
            parse_toml(text.encode("utf-8"), path, "scenario")
    gains: list = []  # each unit's gains table as frozen in the key
    key = _frame_key(path, data, gains)  # None: a structure check_nesting refuses, or not TOML's
    if key is not None:
        known = _known(key, tuple(gains), path, plant_preset, data)
        if known is not None:
            return known
    check_nesting(path, data)
    scenario, layout = _load(path, plant_preset, data)
    if key is None:
        return scenario
    _FRAMES[key] = (scenario, layout, robot_adapter(scenario.robot),
                    controller_of(scenario.robot, scenario.space), {})
    while len(_FRAMES) > FRAME_CACHE_SIZE:
        with contextlib.suppress(KeyError):  # a dask worker's threads load at once
            _FRAMES.popitem(last=False)
    # The template keeps its own arrays: what a caller does to its scenario stays there.
    return _instance(scenario, path, [u.gains for u in scenario.units], scenario.plant)


def _load(path: Path, plant_preset: str | None, data: dict) -> tuple[Scenario, Any]:
    """:func:`load` of checked-nesting TOML data, every key read and checked; the scenario
    and its robot's layout."""
    top = Table(path, data, "")
    top.get("format", f"the string {FORMAT!r}", lambda v: v == FORMAT)
    robot = top.string("robot", tuple(ROBOTS))
    space = top.string("space", ("joint", "task"))
    description = top.string("description", required=False, default=robot)
    named = Path(description)
    if (named.suffix == ".toml" or named.parent != Path(".")) and not named.is_absolute():
        # A file of the user's, relative to the scenario that names it (not to the working
        # directory); a bare name is a shipped description, an absolute path stays as it is.
        description = str(path.parent / named)
    duration = top.number("duration_s", "a positive number (s)", lambda v: v > 0)
    adapter = robot_adapter(robot)
    # No description key: the shipped one, by its path (a bare name is refused where a file
    # or folder of that name is in the working directory: cochlea.resources.shipped).
    system = load_system(robot, description if "description" in data
                         else shipped_file(ROBOTS_DIR, robot))

    c = top.table("control")
    task = None
    if adapter.task_spaces:  # the tool coordinates, where the robot offers a choice
        task = c.string("task", adapter.task_spaces, required=False,
                        default=adapter.default_task)
    layout = (adapter.layout(system, space) if task is None
              else adapter.layout(system, space, task=task))
    rate = c.number("rate_Hz", f"a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] (Hz)",
                    lambda v: MIN_RATE_HZ <= v <= MAX_RATE_HZ, required=False, default=1000.0)
    substeps = c.get("plant_substeps", f"an integer in 1..{MAX_PLANT_SUBSTEPS} (RK4 steps per "
                     "period)", lambda v: isinstance(v, int) and not isinstance(v, bool)
                     and 0 < v <= MAX_PLANT_SUBSTEPS, required=False, default=1)
    variant = c.string("variant", ("corrected", "thesis"), required=False, default="corrected")
    parameterisation = c.string("parameterisation", ("base", "inertial", "mass"),
                                required=False, default="base")
    adaptation_gain = c.number("adaptation_gain", f"a positive number up to {MAX_GAIN:g} "
                               "(Gamma's scale)", lambda v: 0 < v <= MAX_GAIN, required=False,
                               default=1.0)
    adaptation = c.string("adaptation", ("uniform", "relative"), required=False,
                          default="uniform")
    initial_estimate = c.string("initial_estimate", ("zero", "nominal"), required=False,
                                default="zero")
    bound = c.number("estimate_bound", f"a positive number up to {MAX_GAIN:g} (times "
                     "|p_nominal|)", lambda v: 0 < v <= MAX_GAIN, required=False, default=10.0)
    mirror = c.string("mirror", adapter.mirror_modes, required=False, default="desired")
    controller_actuators = c.string("actuators", ACTUATORS, required=False, default="none")
    robust = _robust(c, layout, controller_actuators)
    c.done()
    _check_run_length(top, duration, rate)

    d = top.table("desired")
    definitions = d.get("define", f"a table of at most {MAX_DEFINITIONS} named formulas in t "
                        "(dimensionless), each name a plain identifier other than t, pi and "
                        "the functions",
                        lambda v: isinstance(v, dict) and len(v) <= MAX_DEFINITIONS
                        and all(isinstance(x, str) for x in v.values())
                        and all(k.isidentifier() and k not in RESERVED_NAMES for k in v),
                        required=False, default={})
    problem = _definitions_problem(tuple(definitions.items()))
    if problem is not None:
        name, text, reason = problem
        raise d.error(f"define.{name}", f"a valid formula ({reason})", text) from None
    leader = quantities(d, "leader", layout.leader, definitions=tuple(definitions))
    d.done()

    gain_set = controller_of(robot, space)
    units = []
    unit_tables = top.tables("unit", "one per controlled unit: "
                             + ", ".join(layout.units))
    if [u.data.get("name") for u in unit_tables] != list(layout.units):
        raise DescriptionError(path, "unit", "units named, in order, "
                               + ", ".join(repr(u) for u in layout.units),
                               [u.data.get("name") for u in unit_tables])
    for u in unit_tables:
        name = u.string("name")
        joint_q = quantities(u, "initial_joint", layout.joint, required=False)
        task_q = quantities(u, "initial_task", layout.task, required=False)
        if (joint_q is None) == (task_q is None):
            raise u.error("initial_joint", "exactly one of initial_joint or initial_task",
                          show_got=False)
        velocity_q = quantities(u, "initial_velocity", layout.joint, required=False)
        own_q = quantities(u, "desired_joint", layout.joint, required=False,
                           definitions=tuple(definitions))
        if own_q is not None and space != "joint":
            raise u.error("desired_joint", "no desired_joint in a task-space scenario (a "
                          "unit's own joint path is for space = \"joint\")", show_got=False)
        elbow = u.get("elbow", "+1 or -1 (inverse-kinematics branch)", lambda v: v in (1, -1)
                      and not isinstance(v, bool), required=False)
        gains = _gains(u, gain_set, layout)
        u.done()
        initial = {}
        for key, qs in (("initial_joint", joint_q), ("initial_task", task_q),
                        ("initial_velocity", velocity_q)):
            try:
                initial[key] = constant_values(qs)
            except ExpressionError as exc:
                raise u.error(key, f"constant, finite values ({exc})", show_got=False) from None
        units.append(Unit(name, initial["initial_joint"], initial["initial_task"],
                          initial["initial_velocity"], elbow, gains, own_q))

    plant = _plant(top.table("plant") if "plant" in top.data else None, layout, plant_preset)
    top.done()
    return Scenario(path, path.stem, robot, space, description, duration, rate, substeps,
                    variant, parameterisation, adaptation_gain, adaptation, initial_estimate,
                    bound, mirror,
                    controller_actuators, dict(definitions), leader, tuple(units), plant, system,
                    robust=robust, task=task), layout


def _gains(u: Table, gain_set, layout) -> dict[str, np.ndarray]:
    """A ``[[unit]]`` table's ``gains``, each list of its size, positive and bounded."""
    g = u.table("gains")
    gains = {k: _positive_list(g, k, gain_set.size(k, layout.n_joint, layout.n_task))
             for k in gain_set.required}
    weight = gain_set.weight
    if weight:
        size = gain_set.size(weight, layout.n_joint, layout.n_task)
        given = g.vector(weight, size, "the gain's SI unit", required=False,
                         check=lambda v: all(0 < x <= MAX_GAIN for x in v),
                         what=f"(all positive, at most {MAX_GAIN:g})")
        gains[weight] = np.ones(size) if given is None else given
    g.done()
    return gains


#: Scenarios a process keeps as templates (:func:`load`): a sweep's worker meets one.
FRAME_CACHE_SIZE = 8
#: By :func:`_frame_key`: the scenario first loaded with it, its robot's layout, the adapter
#: and gain set it was read with, and the units' gains tables read with them (by their frozen
#: data: up to :data:`GAINS_CACHE_SIZE`).
_FRAMES: OrderedDict[tuple, tuple[Scenario, Any, Any, Any, dict]] = OrderedDict()
GAINS_CACHE_SIZE = 256
#: What stands in a frame key for a part read again every time: the ``[plant]`` table and
#: each unit's ``gains``.
_READ_AGAIN = ("read again",)
_SCALARS = (str, int, float, bool, datetime.datetime, datetime.date, datetime.time)


def _frozen(value, depth: int, variable: str | None = None, gains: list | None = None):
    """TOML data as a hashable value equal only for equal data of the same types (a float
    by its bits: ``-0.0`` is not ``0.0``; ``1``, ``1.0`` and ``true`` differ), or None where
    :func:`~cochlea.robots.description.check_structure` refuses it or it is not TOML's.
    ``variable``: at the top level, the parts read again (the plant table, each unit's
    gains) stand as :data:`_READ_AGAIN`, though they are checked here like the rest; each
    unit's gains, frozen, are appended to ``gains``."""
    if depth > MAX_NESTING:
        return None
    kind = type(value)
    if kind is dict:
        items = []
        for k, v in value.items():
            if type(k) is not str:
                return None
            f = _frozen(v, depth + 1, "unit" if variable == "top" and k == "unit" else None,
                        gains)
            if f is None:
                return None
            if variable == "unit" and k == "gains" and gains is not None:
                gains.append(f)
            if (variable == "top" and k == "plant") or (variable == "unit" and k == "gains"):
                f = _READ_AGAIN
            items.append((k, f))
        return (dict, tuple(items))
    if kind is list:
        items = []
        for v in value:
            f = _frozen(v, depth + 1, variable if type(v) is dict else None, gains)
            if f is None:
                return None
            items.append(f)
        return (list, tuple(items))
    if kind is float:
        return (float, value.hex())
    if kind is int:
        return (int, value) if -2**63 <= value < 2**63 else None
    if kind in _SCALARS:
        return (kind, value)
    return None


def _frame_key(path: Path, data, gains: list | None = None) -> tuple | None:
    """The key of a scenario's template in :data:`_FRAMES`: its path and its data as far as
    :func:`_known` does not read it again; None when the data is not TOML's or
    check_nesting refuses it (the full load then says why). ``gains``: each unit's gains
    table, frozen, appended (:func:`_known` reads a table once per template)."""
    if type(data) is not dict:
        return None
    frozen = _frozen(data, 0, "top", gains)
    return None if frozen is None else (type(path), str(path), frozen)


def _known(key: tuple, frozen_gains: tuple, path: Path, plant_preset: str | None,
           data: dict) -> Scenario | None:
    """The scenario of ``data`` from the template loaded with the same :func:`_frame_key`:
    its plant table and its units' gains read and checked as :func:`_load` reads them, the
    rest the template's (each array a copy of its own); the robot's description loaded again
    (:func:`load_system`: its file's content), and the template used only if that gives the
    template's system, with the same adapter and gain set. None where anything differs or
    raises: the full load then reads everything (and raises the same error as ever). A
    unit's gains table read before with this template (``frozen_gains``, its data frozen as
    in the key) is not read again: its gains are copies of what it read as."""
    hit = _FRAMES.get(key)
    if hit is None:
        return None
    template, layout, adapter, gain_set, known_gains = hit
    try:
        if (robot_adapter(template.robot) is not adapter
                or controller_of(template.robot, template.space) is not gain_set
                or load_system(template.robot, template.description) is not template.system):
            return None
        top = Table(path, data, "")
        unit_tables = top.tables("unit", "")
        if len(unit_tables) != len(template.units) or len(frozen_gains) != len(unit_tables):
            return None
        gains = []
        for table, frozen in zip(unit_tables, frozen_gains):
            read = known_gains.get(frozen)
            if read is None:
                read = _gains(table, gain_set, layout)
                if len(known_gains) >= GAINS_CACHE_SIZE:
                    known_gains.clear()
                known_gains[frozen] = read
            gains.append({k: v.copy() for k, v in read.items()})
        plant = _plant(top.table("plant") if "plant" in top.data else None, layout, plant_preset)
    except Exception:  # noqa: BLE001 (the full load raises it, with its own message)
        return None
    with contextlib.suppress(KeyError):  # another thread may have let it go meanwhile
        _FRAMES.move_to_end(key)
    return _instance(template, path, gains, plant)


def _instance(template: Scenario, path: Path, gains: list[dict], plant: Plant) -> Scenario:
    """``template`` at ``path`` with each unit's ``gains`` and the ``plant``, every other
    array a copy of the template's (its initial states, the robust options' vectors) and its
    definitions a dict of their own."""
    units = tuple(_replace(
        unit, initial_joint=_copy(unit.initial_joint), initial_task=_copy(unit.initial_task),
        initial_velocity=_copy(unit.initial_velocity), gains=g)
        for unit, g in zip(template.units, gains, strict=True))
    robust = template.robust
    robust = _replace(robust, deadzone=_copy(robust.deadzone),
                      static_ratio=_copy(robust.static_ratio),
                      stribeck_velocity=_copy(robust.stribeck_velocity))
    return _replace(template, path=path, name=path.stem, definitions=dict(template.definitions),
                    units=units, plant=plant, robust=robust)


def _copy(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else a.copy()


def _replace(obj, **changes):
    """``dataclasses.replace(obj, **changes)`` of a frozen dataclass whose fields are only
    stored (no ``__post_init__``, every field in ``__init__``): its fields copied, without
    calling ``__init__`` (several times faster; a sample's scenario makes four)."""
    new = object.__new__(type(obj))
    new.__dict__.update(obj.__dict__)
    for name, value in changes.items():
        if name not in new.__dict__:
            raise TypeError(f"{type(obj).__name__} has no field {name!r}")
        new.__dict__[name] = value
    return new


def _robust(c: Table, layout, actuators: str) -> RobustOptions:
    """The robust-adaptation keys of ``[control]`` (:class:`RobustOptions`)."""
    n = layout.n_joint
    velocity = "rad/s (revolute) or m/s (prismatic)"
    deadzone = c.vector("adaptation_deadzone_SI", n, velocity, required=False,
                        check=lambda v: all(0 <= x <= MAX_DEADZONE for x in v),
                        what=f"(one per joint of a unit, each in [0, {MAX_DEADZONE:g}])")
    box = c.number("estimate_box_relative", f"a positive number up to {MAX_GAIN:g} (each "
                   "estimate within its nominal value +- this many times its size)",
                   lambda v: 0 < v <= MAX_GAIN, required=False)
    sign = c.string("estimate_sign", ("free", "physical"), required=False, default="free")
    ratio = c.vector("static_friction_ratio", n, "(dimensionless: static over Coulomb "
                     "friction)", required=False,
                     check=lambda v: all(1 <= x <= MAX_STATIC_RATIO for x in v),
                     what=f"(one per joint of a unit, each in [1, {MAX_STATIC_RATIO:g}])")
    stribeck = c.vector("stribeck_velocity_SI", n, velocity, required=False,
                        check=lambda v: all(0 < x <= MAX_STRIBECK_VELOCITY for x in v),
                        what="(one per joint of a unit, each positive, at most "
                        f"{MAX_STRIBECK_VELOCITY:g})")
    if ratio is not None and np.any(ratio > 1) and actuators != "all":
        raise c.error("static_friction_ratio", 'ones, or [control] actuators = "all" (the '
                      "static friction shapes the Coulomb friction the controller's model "
                      "estimates; this one has none)", ratio.tolist())
    if stribeck is None and ratio is not None:
        stribeck = np.array([STRIBECK_VELOCITY[kind] for kind in layout.joint])
    ramp = c.number("startup_ramp_s", f"a number in [0, {MAX_RAMP_S:g}] (s)",
                    lambda v: 0 <= v <= MAX_RAMP_S, required=False, default=0.0)
    return RobustOptions(deadzone, box, sign, ratio, stribeck, ramp)


def _torque_constant_error(p: Table, n: int, default) -> np.ndarray | None:
    """``[plant] torque_constant_error``: one number for every joint or one per joint of a
    unit, each within +-:data:`MAX_TORQUE_CONSTANT_ERROR`; a per-joint array or None."""
    bound = MAX_TORQUE_CONSTANT_ERROR
    value = p.get("torque_constant_error", f"a number in [-{bound:g}, {bound:g}] or a list of "
                  f"{n} such numbers, one per joint of a unit (dimensionless: the motor gives "
                  "1 + e times the fit's torque)",
                  lambda v: all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                and math.isfinite(x) and abs(x) <= bound
                                for x in (v if isinstance(v, list) else [v]))
                  and (not isinstance(v, list) or len(v) == n),
                  required=False, default=default)
    if value is None:
        return None
    return np.broadcast_to(np.asarray(value, dtype=float), (n,)).copy()


#: The ``[plant]`` keys the rules between keys at the end of :func:`_plant` read (each key's
#: own range is checked on its own), the preset that sets their defaults among them. A sweep
#: checks every combination of the values its spec gives these keys before anything runs
#: (:func:`cochlea.sweep.sampling.cases`). The rules on integers are thresholds
#: (``delay_periods + delay_jitter_periods`` at most :data:`MAX_DELAY_PERIODS`;
#: ``encoder_noise_counts`` zero or not), so each integer key's smallest and largest values
#: stand for all of its values. The gear keys (``backlash_SI`` & co.) count by being there
#: or not, the same in every sample of a sweep. A new rule's keys go here.
CROSS_KEYS = ("plant", "delay_periods", "delay_jitter_periods", "encoder_noise_counts",
              "position_encoder", "gearbox", "armature")


def _plant(p: Table | None, layout, preset_override: str | None) -> Plant:
    """The ``[plant]`` table: a preset's defaults (:data:`PLANT_PRESETS`), then its keys."""
    if preset_override is not None and preset_override not in PLANT_PRESETS:
        raise CochleaError(f"unknown plant preset {preset_override!r}; choose one of "
                           + ", ".join(PLANT_PRESETS))
    preset = "ideal"
    if p is not None:
        preset = p.string("plant", tuple(PLANT_PRESETS), required=False, default="ideal")
    preset = preset_override or preset
    d = {**Plant().__dict__, **PLANT_PRESETS[preset], "preset": preset}
    if p is None:
        return Plant(**d)

    def flag(key: str, meaning: str) -> bool:
        return p.get(key, f"true or false ({meaning})", lambda v: isinstance(v, bool),
                     required=False, default=d[key])

    n_bodies = layout.n_bodies
    plant = Plant(
        mass_scale=p.vector("mass_scale", n_bodies, "(dimensionless)", required=False,
                            check=lambda v: all(0 < x <= MAX_MASS_SCALE for x in v),
                            what=f"(one positive factor per body: {n_bodies}, each at most "
                            f"{MAX_MASS_SCALE:g})"),
        payload_kg=p.number("payload_kg", f"a non-negative number (kg) up to {MAX_PAYLOAD_KG:g}",
                            lambda v: 0 <= v <= MAX_PAYLOAD_KG, required=False, default=0.0),
        viscous_friction=p.vector("viscous_friction_SI", layout.n_joint,
                                  "N m s/rad (revolute) or N s/m (prismatic)",
                                  check=lambda v: all(0 <= x <= MAX_FRICTION for x in v),
                                  what=f"(each in [0, {MAX_FRICTION:g}])", required=False),
        coulomb_friction=p.vector("coulomb_friction_SI", layout.n_joint,
                                  "N m (revolute) or N (prismatic)",
                                  check=lambda v: all(0 <= x <= MAX_FRICTION for x in v),
                                  what=f"(each in [0, {MAX_FRICTION:g}])", required=False),
        noise_q_std=p.number("noise_q_std_SI", f"a non-negative number (rad or m) up to "
                             f"{MAX_NOISE_Q:g}", lambda v: 0 <= v <= MAX_NOISE_Q, required=False,
                             default=0.0),
        noise_qd_std=p.number("noise_qd_std_SI", f"a non-negative number (rad/s or m/s) up to "
                              f"{MAX_NOISE_QD:g}", lambda v: 0 <= v <= MAX_NOISE_QD,
                              required=False, default=0.0),
        delay_periods=p.get("delay_periods", f"an integer in 0..{MAX_DELAY_PERIODS}",
                            lambda v: isinstance(v, int) and not isinstance(v, bool)
                            and 0 <= v <= MAX_DELAY_PERIODS, required=False,
                            default=d["delay_periods"]),
        seed=p.get("seed", "a non-negative integer below 2**63",
                   lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v < 2**63,
                   required=False, default=0),
        position_encoder=flag("position_encoder", "measured positions on the encoder grid"),
        velocity_register=flag("velocity_register", "measured velocities in 0.229 rpm counts"),
        current_quantisation=flag("current_quantisation", "applied efforts in whole Goal Current "
                                  "LSBs, saturated at the Current Limit"),
        preset=preset,
        armature=flag("armature", "the description's armature in the plant"),
        friction_from_description=d["friction_from_description"],
        gearbox=flag("gearbox", "the geared drive with backlash, the encoder on the output"),
        backlash=p.vector("backlash_SI", layout.n_joint, "rad (revolute) or m (prismatic)",
                          check=lambda v: all(0 <= x <= MAX_BACKLASH for x in v),
                          what=f"(each the gear's full backlash at the joint, in [0, "
                          f"{MAX_BACKLASH:g}])", required=False),
        gear_stiffness=p.vector("gear_stiffness_SI", layout.n_joint,
                                "N m/rad (revolute) or N/m (prismatic)",
                                check=lambda v: all(0 < x <= MAX_GEAR_STIFFNESS for x in v),
                                what=f"(each positive, at most {MAX_GEAR_STIFFNESS:g})",
                                required=False),
        gear_damping=p.vector("gear_damping_SI", layout.n_joint,
                              "N m s/rad (revolute) or N s/m (prismatic)",
                              check=lambda v: all(0 <= x <= MAX_FRICTION for x in v),
                              what=f"(each in [0, {MAX_FRICTION:g}])", required=False),
        static_friction_ratio=p.number(
            "static_friction_ratio", f"a number in [1, {MAX_STATIC_FRICTION_RATIO:g}] (static "
            "over Coulomb friction: breakaway level / sliding level)",
            lambda v: 1 <= v <= MAX_STATIC_FRICTION_RATIO, required=False,
            default=d["static_friction_ratio"]),
        stribeck_velocity=p.vector("stribeck_velocity_SI", layout.n_joint,
                                   "rad/s (revolute) or m/s (prismatic)",
                                   check=lambda v: all(0 < x <= MAX_STRIBECK_VELOCITY
                                                       for x in v),
                                   what=f"(each positive, at most {MAX_STRIBECK_VELOCITY:g})",
                                   required=False),
        bridge_offset=p.get("bridge_offset", '"auto", true or false (whether the bridge adds '
                            "the fit's offset current; auto: unless the controller models "
                            "friction)", lambda v: isinstance(v, bool) or v == "auto",
                            required=False, default=d["bridge_offset"]),
        delay_jitter_periods=p.get(
            "delay_jitter_periods", f"an integer in 0..{MAX_DELAY_PERIODS} (whole periods the "
            "measurement's delay jitters above delay_periods)",
            lambda v: isinstance(v, int) and not isinstance(v, bool)
            and 0 <= v <= MAX_DELAY_PERIODS, required=False, default=d["delay_jitter_periods"]),
        encoder_noise_counts=p.get(
            "encoder_noise_counts", f"an integer in 0..{MAX_ENCODER_NOISE_COUNTS} (whole "
            "encoder counts of position noise, uniform in -N..N)",
            lambda v: isinstance(v, int) and not isinstance(v, bool)
            and 0 <= v <= MAX_ENCODER_NOISE_COUNTS, required=False,
            default=d["encoder_noise_counts"]),
        torque_constant_error=_torque_constant_error(p, layout.n_joint,
                                                     d["torque_constant_error"]),
    )
    if plant.delay_periods + plant.delay_jitter_periods > MAX_DELAY_PERIODS:
        raise p.error("delay_jitter_periods", f"delay_periods + delay_jitter_periods at most "
                      f"{MAX_DELAY_PERIODS}", plant.delay_jitter_periods)
    if plant.encoder_noise_counts and not plant.position_encoder:
        raise p.error("encoder_noise_counts", "0 without the encoder grid (the noise is in "
                      "whole encoder counts: set position_encoder = true)",
                      plant.encoder_noise_counts)
    if not plant.gearbox:
        for key in ("backlash_SI", "gear_stiffness_SI", "gear_damping_SI"):
            if key in p.data:
                raise p.error(key, "no gear keys without the gearbox (set gearbox = true)",
                              show_got=False)
    elif not plant.armature:
        raise p.error("gearbox", "the gearbox only with the rotor's inertia (armature = true)",
                      plant.gearbox)
    p.done()
    return plant
