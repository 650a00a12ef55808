"""What ``cochlea-codegen`` generates: the configuration, and the kernels it asks for.

Stage 1, ``codegen/kernels.toml`` (:func:`load_config`) says which model Functions
to export per robot unit, which controllers and variants, and with which CasADi options.
Stage 2 (:func:`collect`) builds those CasADi Functions from the robot descriptions and names
each kernel; a kernel that computes exactly what an earlier one does (the thesis variant of
controller e, the second arm's copy of a model Function that does not depend on the base pose,
...) becomes an *alias*: it keeps its name, signature and source hash in the manifest but runs
the earlier kernel's C (its ``symbol``), so no body is generated twice. Writing the files is
:mod:`cochlea.kernels.generate`.
"""

from __future__ import annotations

import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca

from .. import files
from ..control import KINDS, VARIANTS, Controller, build
from ..errors import CochleaError
from ..resources import CODEGEN_DIR, checkout
from ..robots import model
from ..robots.description import MAX_FILE_BYTES
from ..robots.model import ACTUATORS, RobotModel
from ..robots.plant import gear_plant_step, plant_step
from .naming import closed_loop_name, computation_hash, controller_kernel_name, unit_prefix

CONFIG = CODEGEN_DIR / "kernels.toml"
TEMPLATE = CODEGEN_DIR / "closed_loop.c.in"
FORMAT = "cochlea-codegen/1"
CONTROLLER_PARTS = ("Y", "law", "update", "step")


class CodegenError(CochleaError):
    """The generator's configuration is wrong, or generated_c/ is stale."""


# --------------------------------------------------------------------------------------------
# Stage 1: the configuration
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RobotConfig:
    """What to generate for one robot of ``models/robots/`` (a ``[[robot]]`` table)."""

    name: str  # "serial" | "parallel"
    units: tuple[str, ...]  # serial arms; empty for the parallel mechanism
    kernels: tuple[str, ...]  # model Functions exported as they are (names in RobotModel)
    plant_substeps: int
    controller_parameterisation: str
    controllers: tuple[str, ...]
    variants: tuple[str, ...]
    task: tuple[str, str]  # (fk, J) of the task-space controllers
    task_angles: tuple[int, ...]
    pose: str  # the model Function whose value the closed loop logs
    #: Also the plant with Coulomb friction (``<prefix>_plant_step_coulomb``) and, per
    #: controller, a closed loop on it (``<group>_closed_loop_coulomb``).
    plant_coulomb: bool = False
    #: The plant models generated (``cochlea.robots.model.ACTUATORS``): "none", the rigid
    #: links; "armature", with the drives' reflected rotor inertia (``--plant realistic``).
    plant_actuators: tuple[str, ...] = ("none",)
    #: The controllers' models generated: "none" (every variant) and, for the corrected
    #: variant only, "all" (armature and friction estimated: the realistic studies).
    controller_actuators: tuple[str, ...] = ("none",)
    #: Also the geared plant with backlash (``<prefix>_gear_plant_step``,
    #: :func:`cochlea.robots.plant.gear_plant_step`: the realistic preset's) and, per
    #: controller, a closed loop on it (``<group>_closed_loop_gear``).
    plant_gear: bool = False


@dataclass(frozen=True)
class EmbeddedConfig:
    """The ``[embedded]`` table: the per-scenario embedded controllers written to
    ``<output>/<folder>/<scenario>.{h,c}`` (:mod:`cochlea.kernels.embedded`)."""

    folder: str = "embedded"
    scenarios: tuple[str, ...] = ()  # shipped scenario names (models/scenarios/)
    function: dict = field(default_factory=lambda: {"cse": True})  # casadi.Function options


@dataclass(frozen=True)
class CodegenConfig:
    """The generator's whole configuration, from ``codegen/kernels.toml``."""

    path: Path
    output: Path
    library: str
    casadi: dict = field(default_factory=dict)  # casadi.CodeGenerator options
    function: dict = field(default_factory=dict)  # casadi.Function options
    robots: tuple[RobotConfig, ...] = ()
    embedded: EmbeddedConfig = field(default_factory=EmbeddedConfig)


_ROBOT_KEYS = {"name": str, "units": list, "kernels": list, "plant_substeps": int,
               "controller_parameterisation": str, "controllers": list, "variants": list,
               "task": list, "task_angles": list, "pose": str, "plant_coulomb": bool,
               "plant_actuators": list, "controller_actuators": list, "plant_gear": bool}
#: Keys a [[robot]] table may leave out, and their defaults.
_OPTIONAL = {"plant_actuators": ["none"], "controller_actuators": ["none"], "plant_gear": False}


def _fail(path: Path, key: str, expected: str, got: object) -> CodegenError:
    shown = repr(got)
    shown = shown if len(shown) <= 120 else shown[:120] + "..."
    return CodegenError(f"{path}: {key}: expected {expected}, got {shown}")


#: Most RK4 sub-steps a period a configuration may ask for: each is a copy of the dynamics in
#: the generated C (the shipped kernels use 1).
MAX_PLANT_SUBSTEPS = 100
_NOUN = {str: "a string", int: "an integer", bool: "a boolean", list: "a list"}
#: The element type of each list of a [[robot]] table.
_LIST_ITEMS = {"units": str, "kernels": str, "controllers": str, "variants": str, "task": str,
               "task_angles": int, "plant_actuators": str, "controller_actuators": str}


def _casadi_message(exc: Exception) -> str:
    """CasADi's refusal in a few words: its lines without the source locations."""
    lines = [re.sub(r"^.*?\.(?:cpp|hpp):\d+:\s*", "", line).strip()
             for line in str(exc).splitlines()]
    lines = [line for line in lines if line and not line.startswith("Error in ")]
    for i, line in enumerate(lines):  # CasADi's list of every option that exists
        if line.startswith("Did you mean"):
            lines = lines[:i]
            break
    return "; ".join(lines)[:200] or type(exc).__name__


def _options(path: Path, key: str, table: object, kind: str) -> dict:
    """A table of CasADi options, checked by CasADi itself now (an unknown option or a wrong
    type), not after kernels are generated: ``kind`` ``"codegen"`` (casadi.CodeGenerator's) or
    ``"function"`` (casadi.Function's)."""
    if not isinstance(table, dict):
        raise _fail(path, key, "a table of CasADi options", table)
    options = dict(table)
    try:
        if kind == "codegen":
            ca.CodeGenerator("check.c", dict(options))
        else:
            x = ca.SX.sym("x")
            ca.Function("check", [x], [x], ["x"], ["y"], dict(options))
    except (RuntimeError, TypeError, ValueError, NotImplementedError, OverflowError) as exc:
        raise CodegenError(f"{path}: {key}: CasADi refuses these options: "
                           f"{_casadi_message(exc)}") from None
    return options


def load_config(path: str | Path = CONFIG) -> CodegenConfig:
    """Read and validate the generator's configuration."""
    path = Path(path)
    try:
        # A regular file only (a FIFO or a device would block), bounded like a description.
        raw = files.read_regular(path, MAX_FILE_BYTES)
        if len(raw) > MAX_FILE_BYTES:
            raise ValueError(f"larger than {MAX_FILE_BYTES // 1024} KiB")
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise  # cochlea-codegen says "not UTF-8" itself
    except (OSError, ValueError) as exc:  # ValueError: TOML's, or a 4300-digit integer
        raise CodegenError(f"{path}: cannot read the codegen configuration: {exc}") from exc
    except RecursionError:  # tables or arrays nested thousands deep
        raise CodegenError(f"{path}: cannot read the codegen configuration: nested too "
                           "deep") from None
    top = {"format", "output", "library", "casadi", "function", "robot", "embedded"}
    for key in data:
        if key not in top:
            raise _fail(path, key, "one of " + ", ".join(sorted(top)), key)
    if data.get("format") != FORMAT:
        raise _fail(path, "format", repr(FORMAT), data.get("format"))
    for key in ("output", "library"):
        if not isinstance(data.get(key), str) or not data[key]:
            raise _fail(path, key, "a non-empty string", data.get(key))
    robots = []
    tables = data.get("robot", [])
    if not isinstance(tables, list) or not all(isinstance(t, dict) for t in tables):
        raise _fail(path, "robot", "[[robot]] tables (an array of tables; [robot] is one table)",
                    tables)
    for i, table in enumerate(tables):
        where = f"robot[{i}]"
        for key in table:
            if key not in _ROBOT_KEYS:
                raise _fail(path, f"{where}.{key}", "one of " + ", ".join(_ROBOT_KEYS), key)
        table = {**_OPTIONAL, **table}
        for key, kind in _ROBOT_KEYS.items():
            if not isinstance(table.get(key), kind) or (kind is int
                                                        and isinstance(table[key], bool)):
                raise _fail(path, f"{where}.{key}", _NOUN[kind], table.get(key))
            item = _LIST_ITEMS.get(key)
            if item is not None and not all(isinstance(v, item) and not isinstance(v, bool)
                                            for v in table[key]):
                raise _fail(path, f"{where}.{key}", f"a list of {_NOUN[item].split()[1]}s",
                            table[key])
        for kind in table["controllers"]:
            if kind not in KINDS or KINDS[kind][0] != table["name"]:
                raise _fail(path, f"{where}.controllers", f"controllers of {table['name']}",
                            kind)
        for variant in table["variants"]:
            if variant not in VARIANTS:
                raise _fail(path, f"{where}.variants", "one of " + ", ".join(VARIANTS),
                            variant)
        for key in ("plant_actuators", "controller_actuators"):
            if not table[key] or any(a not in ACTUATORS for a in table[key]) \
                    or len(set(table[key])) != len(table[key]):
                raise _fail(path, f"{where}.{key}", "distinct options of "
                            + ", ".join(ACTUATORS), table[key])
        if not 1 <= table["plant_substeps"] <= MAX_PLANT_SUBSTEPS:
            raise _fail(path, f"{where}.plant_substeps",
                        f"an integer in 1..{MAX_PLANT_SUBSTEPS}", table["plant_substeps"])
        if len(table["task"]) != 2:
            raise _fail(path, f"{where}.task", "[fk, J]", table["task"])
        robots.append(RobotConfig(
            table["name"], tuple(table["units"]), tuple(table["kernels"]),
            table["plant_substeps"], table["controller_parameterisation"],
            tuple(table["controllers"]), tuple(table["variants"]), tuple(table["task"]),
            tuple(table["task_angles"]), table["pose"], table["plant_coulomb"],
            tuple(table["plant_actuators"]), tuple(table["controller_actuators"]),
            table["plant_gear"]))
    if not robots:
        raise _fail(path, "robot", "at least one [[robot]] table", [])
    embedded = _embedded_config(path, data.get("embedded", {}))
    casadi = _options(path, "casadi", data.get("casadi", {}), "codegen")
    function = _options(path, "function", data.get("function", {}), "function")
    # The output folder is relative to the checkout (or, installed, the working directory).
    root = checkout() or Path.cwd()
    return CodegenConfig(path, (root / data["output"]).resolve(), data["library"],
                         casadi, function, tuple(robots), embedded)


def _embedded_config(path: Path, table: object) -> EmbeddedConfig:
    keys = {"folder": str, "scenarios": list, "function": dict}
    if not isinstance(table, dict):
        raise _fail(path, "embedded", "a table", table)
    for key, value in table.items():
        if key not in keys:
            raise _fail(path, f"embedded.{key}", "one of " + ", ".join(keys), key)
        if not isinstance(value, keys[key]):
            raise _fail(path, f"embedded.{key}", f"a {keys[key].__name__}", value)
    folder = table.get("folder", "embedded")
    if not re.fullmatch(r"[A-Za-z0-9_]+", folder):
        raise _fail(path, "embedded.folder", "a plain folder name", folder)
    scenarios = table.get("scenarios", [])
    for name in scenarios:
        if not isinstance(name, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", name):
            raise _fail(path, "embedded.scenarios", "scenario names (C identifiers)", name)
    if len(set(scenarios)) != len(scenarios):
        raise _fail(path, "embedded.scenarios", "distinct names", scenarios)
    function = _options(path, "embedded.function", table.get("function", {"cse": True}),
                        "function")
    return EmbeddedConfig(folder, tuple(scenarios), function)


# --------------------------------------------------------------------------------------------
# Stage 2: which Functions become which C functions
# --------------------------------------------------------------------------------------------


@dataclass
class Kernel:
    """One exported C function and the CasADi Function it comes from."""

    name: str
    function: ca.Function  # exported: renamed if needed, every output dense
    source: ca.Function  # as cochlea builds it; its hash identifies the kernel
    group: str  # the .c/.h file stem
    role: str  # "model" | "plant" | "controller"
    robot: str
    unit: str  # the robot unit's prefix (serial_arm1, parallel)
    kind: str | None = None
    variant: str | None = None
    si_units: dict[str, str] = field(default_factory=dict)  # argument name -> its SI unit
    #: The kernel whose C runs this one: itself, or an earlier kernel computing the same.
    symbol: str = ""
    #: What the kernel's model carries of the drives (``cochlea.robots.model.ACTUATORS``).
    actuators: str = "none"

    @property
    def is_alias(self) -> bool:
        return self.symbol != self.name

    @property
    def inline_trig(self) -> bool:
        """Whether its C takes each angle's sin and cos from one inline ``cochlea_sincos``
        (:mod:`cochlea.kernels.trig`): the ideal plants' RK4 steps (``<unit>_plant_step``,
        ``_plant_step_coulomb``, ``<unit>_armature_plant_step[_coulomb]``), not the geared
        plant (``<unit>_gear_plant_step``: its backlash grows an ulp to 1e-2 rad over a
        study), the controllers or the model's kernels, which keep libm bit for bit."""
        return self.role == "plant" and not self.name.endswith("_gear_plant_step")


@dataclass
class ClosedLoop:
    """One generated closed-loop driver: controller step + plant step + logged pose."""

    name: str
    step: str
    plant: str
    pose: str
    nq: int
    n_params: int
    n_desired: int
    n_errors: int
    n_pose: int
    n_plant_params: int
    n_gains: int
    #: The C the driver calls: the symbols of its step, plant and pose kernels.
    calls: tuple[str, str, str] = ("", "", "")
    #: Whether the plant has a 6th input (the driver's ``drive``): the rigid plant's dry
    #: friction (``dry``) or the gear plant's ``drive``.
    coulomb: bool = False
    #: The driver whose C runs this one: itself, or an earlier one making the same calls.
    symbol: str = ""
    #: The plant's state size (``2 nq``, or ``4 nq`` with the gearbox) and its 6th input's.
    nx: int = 0
    n_drive: int = 0
    gear: bool = False

    @property
    def is_alias(self) -> bool:
        return self.symbol != self.name

    @property
    def n_reductions(self) -> int:
        """The size of the driver's ``reductions`` output: the measured state's column
        extremes (2 x 2 nq), the applied efforts' (2 nq), two largest estimate row squares,
        the keep-out tool points' nearest squared distance."""
        return closed_loop_reductions(self.nq)


def closed_loop_reductions(nq: int) -> int:
    """:attr:`ClosedLoop.n_reductions` of a driver of ``nq`` joints."""
    return 2 * (2 * nq) + 2 * nq + 3


def export(function: ca.Function, name: str, options: dict | None = None) -> ca.Function:
    """The same computation as ``function`` under ``name``, every output dense."""
    if not function.is_a("SXFunction"):
        function = function.expand()
    inputs = function.sx_in()
    outputs = function.call(inputs)
    return ca.Function(name, inputs, [ca.densify(o) for o in outputs], function.name_in(),
                       function.name_out(), dict(options or {}))


def controller_for(robot: RobotConfig, m: RobotModel, kind: str, variant: str) -> Controller:
    """The controller as the simulation builds it (same task map and wrapped angles)."""
    fk, J = robot.task
    return build(m, kind, variant=variant, task_angles=robot.task_angles,
                 task=(m.functions[fk], m.functions[J]))


def _controller_parts(c: Controller) -> dict[str, ca.Function]:
    law = c.law
    inputs = law.sx_in()
    update = ca.Function(law.name().replace("_law", "_update"), inputs,
                         [law.call(inputs)[1]], law.name_in(), ["p_hat_dot"])
    return {"Y": c.regressor, "law": law, "update": update, "step": c.step}


def _controller_kernels(robot: RobotConfig, ctrl_model: RobotModel, kind: str, variant: str,
                        prefix: str, pose: ca.Function, plants: list, opts: dict,
                        kernels: list[Kernel]) -> list[ClosedLoop]:
    """Append one controller's kernels; its closed loops, one per plant step."""
    c = controller_for(robot, ctrl_model, kind, variant)
    return _controller_group(robot.name, ctrl_model, c, prefix, pose, plants, opts, kernels)


def _controller_group(robot: str, ctrl_model: RobotModel, c: Controller, prefix: str,
                      pose: ca.Function, plants: list, opts: dict,
                      kernels: list[Kernel]) -> list[ClosedLoop]:
    """Append the kernels of controller ``c`` (built on ``ctrl_model``); its closed loops, one
    per plant step."""
    actuators = ctrl_model.actuators
    kind, variant = c.kind, c.variant
    group = controller_kernel_name(prefix, kind, variant, "", actuators)[:-1]
    cinfo = _ArgumentUnits(ctrl_model, c)
    for part, f in _controller_parts(c).items():
        name = controller_kernel_name(prefix, kind, variant, part, actuators)
        kernels.append(Kernel(name, export(f, name, opts), f, group, "controller", robot,
                              prefix, kind, variant, cinfo.of(f), actuators=actuators))
    loops = []
    for plant_model, step in plants:
        gear = "drive" in step.name_in()
        coulomb = gear or "dry" in step.name_in()
        loops.append(ClosedLoop(
            closed_loop_name(group, plant_model, coulomb and not gear, gear), f"{group}_step",
            step.name(), pose.name(), c.nq, c.n_params, c.n_desired, c.n_desired + c.nq,
            pose.size1_out(0), len(plant_model.param_names), sum(c.gain_sizes),
            coulomb=coulomb, nx=step.size1_in(0),
            n_drive=step.size1_in(5) if coulomb else c.nq, gear=gear))
    return loops


def collect(config: CodegenConfig) -> tuple[list[Kernel], list[ClosedLoop]]:
    """Build every kernel the configuration asks for, in a stable order."""
    kernels: list[Kernel] = []
    loops: list[ClosedLoop] = []
    opts = config.function
    for robot in config.robots:
        for unit in robot.units or (None,):
            plant = model(robot.name, arm=unit, parameterisation="inertial")
            ctrl_model = model(robot.name, arm=unit,
                               parameterisation=robot.controller_parameterisation)
            prefix = unit_prefix(plant)
            info = _ArgumentUnits(plant)
            for key in robot.kernels:
                if key not in plant.functions:
                    raise CodegenError(f"{config.path}: {robot.name} has no Function {key!r}; "
                                       "choose from " + ", ".join(sorted(plant.functions)))
                f = plant.functions[key]
                kernels.append(Kernel(f.name(), export(f, f.name(), opts), f, prefix, "model",
                                      robot.name, prefix, si_units=info.of(f)))
            plants = []  # (plant model, its step Function)
            for actuators in robot.plant_actuators:
                plant_model = (plant if actuators == "none" else
                               model(robot.name, arm=unit, parameterisation="inertial",
                                     actuators=actuators))
                for coulomb in (False, True)[:1 + robot.plant_coulomb]:
                    step = plant_step(plant_model, robot.plant_substeps, coulomb=coulomb)
                    plants.append((plant_model, step))
                    kernels.append(Kernel(step.name(), export(step, step.name(), opts), step,
                                          prefix, "plant", robot.name, prefix,
                                          si_units=_ArgumentUnits(plant_model).of(step),
                                          actuators=actuators))
            if robot.plant_gear:  # the rigid links, each behind its rotor and gear
                step = gear_plant_step(plant, robot.plant_substeps)
                plants.append((plant, step))
                kernels.append(Kernel(step.name(), export(step, step.name(), opts), step,
                                      prefix, "plant", robot.name, prefix,
                                      si_units=_ArgumentUnits(plant).of(step)))
            for actuators in robot.controller_actuators:
                ctrl_model = model(robot.name, arm=unit, actuators=actuators,
                                   parameterisation=robot.controller_parameterisation)
                pose = ctrl_model.functions[robot.pose]
                # The thesis's variant reproduces its printed studies: rigid links only.
                variants = robot.variants if actuators == "none" else ("corrected",)
                for kind in robot.controllers:
                    for variant in variants:
                        loops += _controller_kernels(robot, ctrl_model, kind, variant, prefix,
                                                     pose, plants, opts, kernels)
    names = [k.name for k in kernels]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise CodegenError(f"{config.path}: kernels generated twice: {', '.join(duplicates)}")
    _share_bodies(kernels, loops)
    return kernels, loops


#: The model Functions generated for a user's scenario besides what its run calls (cheap
#: ones: the dynamics' terms and the kinematics; the run's own pose is ``fk_world``).
UNIT_MODEL_KERNELS = ("M", "C", "G", "fk", "J", "fk_world", "J_world")


@dataclass(frozen=True)
class UnitSpec:
    """One controlled unit of a user's scenario, as the simulation builds it: what its run
    calls (controller, plant steps, logged pose), so the generated kernels' source hashes are
    those the run checks (:func:`cochlea.sim.compiled.unit_kernels`)."""

    robot: str  # the adapter's name ("serial", "parallel")
    controller_model: RobotModel
    controller: Controller
    pose: ca.Function  # the logged pose (the setup's ``fk_world``)
    plant_model: RobotModel  # full inertial parameterisation, rigid links
    #: ``(plant model, step Function)`` per plant the runs may use.
    plants: tuple[tuple[RobotModel, ca.Function], ...]


def collect_units(units: list[UnitSpec], opts: dict, where: str
                  ) -> tuple[list[Kernel], list[ClosedLoop]]:
    """The kernels and closed loops of a user's scenario (``where``: its path, for messages):
    per unit the model kernels :data:`UNIT_MODEL_KERNELS`, every plant step, the controller's
    parts and a closed loop per plant. A kernel asked twice (two plant presets share a step)
    is generated once; the same name for another computation is refused."""
    kernels: list[Kernel] = []
    loops: list[ClosedLoop] = []
    seen: dict[str, str] = {}

    def fresh(name: str, function: ca.Function) -> bool:
        digest = computation_hash(function)
        if name in seen:
            if seen[name] != digest:
                raise CodegenError(f"{where}: two different computations are both named {name}")
            return False
        seen[name] = digest
        return True

    for u in units:
        prefix = unit_prefix(u.controller_model)
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", prefix):
            raise CodegenError(f"{where}: unit {u.controller_model.name!r} gives the C prefix "
                               f"{prefix!r}, not a C identifier: rename the system or arm in "
                               "the description (letters, digits, underscores)")
        info = _ArgumentUnits(u.plant_model)
        for key in UNIT_MODEL_KERNELS:
            f = u.pose if key == "fk_world" else u.plant_model.functions.get(key)
            if f is None or not fresh(f.name(), f):
                continue
            kernels.append(Kernel(f.name(), export(f, f.name(), opts), f, prefix, "model",
                                  u.robot, prefix, si_units=info.of(f)))
        plants = []
        for plant_model, step in u.plants:
            plants.append((plant_model, step))
            if fresh(step.name(), step):
                kernels.append(Kernel(step.name(), export(step, step.name(), opts), step,
                                      prefix, "plant", u.robot, prefix,
                                      si_units=_ArgumentUnits(plant_model).of(step),
                                      actuators=plant_model.actuators))
        c = u.controller
        group: list[Kernel] = []
        unit_loops = _controller_group(u.robot, u.controller_model, c, prefix, u.pose,
                                       plants, opts, group)
        for k in group:
            if fresh(k.name, k.function):
                kernels.append(k)
        for loop in unit_loops:
            if loop.name not in {known.name for known in loops}:
                loops.append(loop)
    if not loops:
        raise CodegenError(f"{where}: the scenario has no unit to generate kernels for")
    # One file per kernel: a spatial chain's kernels are large (UR5's controller parts are
    # hundreds of KiB of C each), and separate files compile on every core at once.
    for k in kernels:
        k.group = k.name
    _share_bodies(kernels, loops)
    return kernels, loops


def _share_bodies(kernels: list[Kernel], loops: list[ClosedLoop]) -> None:
    """Point every kernel (and driver) at the first one that computes the same thing."""
    first: dict[str, str] = {}
    for k in kernels:
        k.symbol = first.setdefault(computation_hash(k.function), k.name)
    symbol = {k.name: k.symbol for k in kernels}
    drivers: dict[tuple[str, str, str], str] = {}
    for loop in loops:
        loop.calls = (symbol[loop.step], symbol[loop.plant], symbol[loop.pose])
        loop.symbol = drivers.setdefault(loop.calls, loop.name)


# --------------------------------------------------------------------------------------------
# Units of every argument (for the README)
# --------------------------------------------------------------------------------------------


def law_units(m: RobotModel, controller: Controller) -> dict[str, str]:
    """The SI unit text of every argument of ``controller.law`` (built on model ``m``)."""
    return _ArgumentUnits(m, controller).of(controller.law)


class _ArgumentUnits:
    """Unit text of each argument name, for one robot model (and controller)."""

    def __init__(self, m: RobotModel, controller: Controller | None = None):
        types = [j.type for j in m.joints]
        self.m, self.c = m, controller

        def per_joint(revolute: str, prismatic: str) -> str:
            units = [revolute if t == "revolute" else prismatic for t in types]
            return units[0] if len(set(units)) == 1 else ", ".join(units)

        self.q = per_joint("rad", "m")
        self.qd = per_joint("rad/s", "m/s")
        self.qdd = per_joint("rad/s^2", "m/s^2")
        self.tau = per_joint("N m", "N")
        self.damping = per_joint("N m s/rad", "N s/m")
        self.stiffness = per_joint("N m/rad", "N/m")
        task_units = ("m", "m", "rad")
        self.task = ", ".join(task_units * (m.functions["fk"].size1_out(0) // 3))
        self.params = ", ".join(dict.fromkeys(m.parameters.si_units)) + " (see the parameter list)"

    def _desired(self, rate: str) -> str:
        if self.c is not None and self.c.space == "task":
            base = self.task
        else:
            base = self.q
        if not rate:
            return base
        return ", ".join(f"{u}{rate}" for u in base.split(", "))

    def _gains(self) -> str:
        unit = {"alpha": "1/s", "K_p": "1/s", "G_g": "1/s", "G_e": self.damping,
                "G_f": self.damping, "G_a": self.damping, "G_d": self.damping,
                "K_e": self.stiffness}
        parts = []
        for name, size in zip(self.c.gain_names, self.c.gain_sizes):
            parts.append(f"{name}[{size}] {unit.get(name, 'SI')}")
        return "; ".join(parts)

    def _errors(self) -> str:
        first, second = self.c.error_names
        return (f"{first}[{self.c.n_desired}] {self._desired('')}; "
                f"{second}[{self.c.nq}] {self.qd}")

    def of(self, f: ca.Function) -> dict[str, str]:
        table = {
            "q": self.q, "qd": self.qd, "qdd": self.qdd, "tau": self.tau,
            "qd_r": self.qd, "qdd_r": self.qdd,
            "x": f"[q; qd]: {self.q}; {self.qd}", "x_next": f"[q; qd]: {self.q}; {self.qd}",
            "p": self.params, "friction": f"viscous coefficients, {self.damping}",
            "coulomb": f"Coulomb friction levels, {self.tau}",
            "dry": f"[Coulomb levels; static levels], {self.tau}; Stribeck velocities, "
                   f"{self.qd}",
            "drive": f"rows armature, backlash, gear stiffness, gear damping, Coulomb, static "
                     f"friction, Stribeck velocity (SI per joint: {self.q} for the backlash)",
            "h": "s (control period)",
            "M": "kg m^2 (revolute pairs), kg (prismatic), kg m (mixed)",
            "C": "N m s/rad (revolute), N s/m (prismatic): C(q, qd) qd is a torque",
            "G": self.tau, "fk": self.task, "fk_world": self.task,
            "J": "d fk / d q (task unit per joint unit)",
            "J_world": "d fk_world / d q (task unit per joint unit)",
            "A": "(J'J)^-1 J' (joint unit per task unit)",
            "Y": f"regressor: {self.tau} per parameter unit",
        }
        if self.c is not None:
            table.update({
                "xd": self._desired(""), "xd_dot": self._desired("/s"),
                "xd_ddot": self._desired("/s^2"), "p_hat": self.params,
                "p_hat_next": self.params, "p_hat_dot": "parameter units per s",
                "gains": self._gains(), "Gamma": "adaptation gain per parameter (diagonal)",
                "bound": "projection radius of |p_hat|, parameter units",
                "deadzone": f"dead-zone width of the adaptation's signal per joint, {self.qd} "
                            "(0: none)",
                "p_min": "lower face of each estimate's box, parameter units (-inf: none)",
                "p_max": "upper face of each estimate's box, parameter units (inf: none)",
                "static_excess": "static over Coulomb friction minus 1 per joint, "
                                 "dimensionless (0: none)",
                "stribeck_velocity": f"Stribeck velocity per joint, {self.qd}",
                "errors": self._errors(), "Y": f"regressor: {self.tau} per parameter unit",
            })
        return {name: table.get(name, "") for name in list(f.name_in()) + list(f.name_out())}


