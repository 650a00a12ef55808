"""``cochlea-codegen``: the symbolic models and controllers as C kernels in ``generated_c/``.

The four stages of the fast path, one module each (describe -> generate -> build -> load):

1. ``cochlea/data/codegen/kernels.toml`` says which kernels to export and with which CasADi options
   (:class:`CodegenConfig`, read by :func:`load_config`);
2. this module builds the CasADi Functions from the descriptions in ``cochlea/data/robots/``
   and writes C
   with ``casadi.CodeGenerator`` (:func:`generate`);
3. the Makefile compiles ``generated_c/*.c`` into ``build/libcochlea.so`` (no Python needed);
4. :mod:`cochlea.kernels.library` loads the library through ctypes.

What is generated, per robot unit (``serial_arm1``, ``serial_arm2``, ``parallel``):

* ``<unit>.c``: the model's kernels (``<unit>_M``, ``_C``, ``_G``, ``_fk``, ``_J``, ...,
  ``_forward_dynamics``, the ``*_p`` kernels in the full inertial parameters) and
  ``<unit>_plant_step``, one RK4 control period of the plant (``cochlea.robots.plant.plant_step``);
* ``<unit>_<kind>[_thesis].c``: controller ``kind`` (and its thesis variant): the regressor
  ``_Y``, the law ``_law`` (torque, estimate rate, errors), the update law ``_update`` (estimate
  rate alone) and the fused ``_step`` (torque, next estimate, errors);
* ``closed_loop.c``: ``<unit>_<kind>[_thesis]_closed_loop``, N periods of controller, estimate
  update and plant in C (from the template ``cochlea/data/codegen/closed_loop.c.in``);
* ``manifest.c`` (``cochlea_manifest()``: every kernel's signature and the SHA-256 of the CasADi
  Function it came from, so a caller can tell a stale library), ``cochlea.h`` (includes every
  header) and ``README.md`` (each function's inputs, outputs, sizes, units and work memory).

Every output is dense (column-major for matrices) and every kernel is generic in what a scenario
chooses: gains, adaptation gain, projection bound, period, plant parameters, friction.
Generation is deterministic: the same inputs give byte-identical files.
"""

from __future__ import annotations

import filecmp
import json
import re
import tempfile
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from string import Template

import casadi as ca

from ..control import KINDS, VARIANTS, Controller, build
from ..errors import CochleaError
from ..resources import CODEGEN_DIR, checkout
from ..robots import model
from ..robots.model import RobotModel
from ..robots.plant import plant_step
from .naming import MANIFEST_FORMAT, controller_kernel_name, source_hash, unit_prefix
from .readme import readme

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
    """What to generate for one robot of ``cochlea/data/robots/`` (a ``[[robot]]`` table)."""

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


@dataclass(frozen=True)
class CodegenConfig:
    """The generator's whole configuration, from ``cochlea/data/codegen/kernels.toml``."""

    path: Path
    output: Path
    library: str
    casadi: dict = field(default_factory=dict)  # casadi.CodeGenerator options
    function: dict = field(default_factory=dict)  # casadi.Function options
    robots: tuple[RobotConfig, ...] = ()


_ROBOT_KEYS = {"name": str, "units": list, "kernels": list, "plant_substeps": int,
               "controller_parameterisation": str, "controllers": list, "variants": list,
               "task": list, "task_angles": list, "pose": str}


def _fail(path: Path, key: str, expected: str, got: object) -> CodegenError:
    return CodegenError(f"{path}: {key}: expected {expected}, got {got!r}")


def load_config(path: str | Path = CONFIG) -> CodegenConfig:
    """Read and validate the generator's configuration."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise CodegenError(f"{path}: cannot read the codegen configuration: {exc}") from exc
    top = {"format", "output", "library", "casadi", "function", "robot"}
    for key in data:
        if key not in top:
            raise _fail(path, key, "one of " + ", ".join(sorted(top)), key)
    if data.get("format") != FORMAT:
        raise _fail(path, "format", repr(FORMAT), data.get("format"))
    for key in ("output", "library"):
        if not isinstance(data.get(key), str) or not data[key]:
            raise _fail(path, key, "a non-empty string", data.get(key))
    robots = []
    for i, table in enumerate(data.get("robot", [])):
        where = f"robot[{i}]"
        for key in table:
            if key not in _ROBOT_KEYS:
                raise _fail(path, f"{where}.{key}", "one of " + ", ".join(_ROBOT_KEYS), key)
        for key, kind in _ROBOT_KEYS.items():
            if not isinstance(table.get(key), kind):
                raise _fail(path, f"{where}.{key}", f"a {kind.__name__}", table.get(key))
        for kind in table["controllers"]:
            if kind not in KINDS or KINDS[kind][0] != table["name"]:
                raise _fail(path, f"{where}.controllers", f"controllers of {table['name']}",
                            kind)
        for variant in table["variants"]:
            if variant not in VARIANTS:
                raise _fail(path, f"{where}.variants", "one of " + ", ".join(VARIANTS),
                            variant)
        if table["plant_substeps"] < 1:
            raise _fail(path, f"{where}.plant_substeps", "a positive integer",
                        table["plant_substeps"])
        if len(table["task"]) != 2:
            raise _fail(path, f"{where}.task", "[fk, J]", table["task"])
        robots.append(RobotConfig(
            table["name"], tuple(table["units"]), tuple(table["kernels"]),
            table["plant_substeps"], table["controller_parameterisation"],
            tuple(table["controllers"]), tuple(table["variants"]), tuple(table["task"]),
            tuple(table["task_angles"]), table["pose"]))
    if not robots:
        raise _fail(path, "robot", "at least one [[robot]] table", [])
    # The output folder is relative to the checkout (or, installed, the working directory).
    root = checkout() or Path.cwd()
    return CodegenConfig(path, (root / data["output"]).resolve(), data["library"],
                         dict(data.get("casadi", {})), dict(data.get("function", {})),
                         tuple(robots))


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
    units: dict[str, str] = field(default_factory=dict)  # argument name -> unit text


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
            info = _Units(plant)
            for key in robot.kernels:
                if key not in plant.functions:
                    raise CodegenError(f"{config.path}: {robot.name} has no Function {key!r}; "
                                       "choose from " + ", ".join(sorted(plant.functions)))
                f = plant.functions[key]
                kernels.append(Kernel(f.name(), export(f, f.name(), opts), f, prefix, "model",
                                      robot.name, prefix, units=info.of(f)))
            step = plant_step(plant, robot.plant_substeps)
            kernels.append(Kernel(step.name(), export(step, step.name(), opts), step, prefix,
                                  "plant", robot.name, prefix, units=info.of(step)))
            pose = ctrl_model.functions[robot.pose]
            for kind in robot.controllers:
                for variant in robot.variants:
                    c = controller_for(robot, ctrl_model, kind, variant)
                    group = controller_kernel_name(prefix, kind, variant, "")[:-1]
                    cinfo = _Units(ctrl_model, c)
                    for part, f in _controller_parts(c).items():
                        name = controller_kernel_name(prefix, kind, variant, part)
                        kernels.append(Kernel(name, export(f, name, opts), f, group,
                                              "controller", robot.name, prefix, kind, variant,
                                              cinfo.of(f)))
                    loops.append(ClosedLoop(
                        f"{group}_closed_loop", controller_kernel_name(prefix, kind, variant,
                                                                        "step"),
                        step.name(), pose.name(), c.nq, c.n_params, c.n_desired,
                        c.n_desired + c.nq, pose.size1_out(0), len(plant.param_names),
                        sum(c.gain_sizes)))
    names = [k.name for k in kernels]
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise CodegenError(f"{config.path}: kernels generated twice: {', '.join(duplicates)}")
    return kernels, loops


# --------------------------------------------------------------------------------------------
# Units of every argument (for the README)
# --------------------------------------------------------------------------------------------


class _Units:
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
                "errors": self._errors(), "Y": f"regressor: {self.tau} per parameter unit",
            })
        return {name: table.get(name, "") for name in list(f.name_in()) + list(f.name_out())}


# --------------------------------------------------------------------------------------------
# Writing the files
# --------------------------------------------------------------------------------------------

_DEFINITION = re.compile(r"^(?:static |CASADI_SYMBOL_EXPORT )?[\w\*\s]+?\b\w+\(([^()]*)\)\s*\{$")


def _mark_unused_parameters(text: str) -> str:
    """Add ``(void)name;`` for each parameter a generated function does not use, so the code
    compiles cleanly with -Wall -Wextra (CasADi leaves e.g. ``iw, w, mem`` unused)."""
    lines = text.split("\n")
    out = []
    i = 0
    while i < len(lines):
        line = lines[i]
        out.append(line)
        match = _DEFINITION.match(line)
        i += 1
        if not match or match.group(1).strip() in ("", "void"):
            continue
        body = []
        j = i
        while j < len(lines) and lines[j] != "}":
            body.append(lines[j])
            j += 1
        if j == len(lines):  # a one-line body or no closing brace at column 0: leave it
            continue
        text_body = "\n".join(body)
        names = [p.strip().split()[-1].lstrip("*") for p in match.group(1).split(",")]
        unused = [n for n in names if not re.search(rf"\b{re.escape(n)}\b", text_body)]
        if unused:
            out.append("  " + " ".join(f"(void){n};" for n in unused))
    return "\n".join(out)


def _work_sizes(text: str, name: str) -> dict[str, int]:
    match = re.search(rf"int {re.escape(name)}_work\(.*?\{{(.*?)\n\}}", text, flags=re.S)
    if not match:
        raise CodegenError(f"no work-size function for {name} in the generated code")
    return {key: int(value) for key, value in
            re.findall(r"if \(sz_(\w+)\) \*sz_\w+ = (\d+);", match.group(1))}


def _signature(f: ca.Function) -> dict:
    def args(n, name, size1, size2):
        return [{"name": name(i), "rows": size1(i), "cols": size2(i)} for i in range(n)]

    return {"inputs": args(f.n_in(), f.name_in, f.size1_in, f.size2_in),
            "outputs": args(f.n_out(), f.name_out, f.size1_out, f.size2_out)}


def _generate_group(stem: str, kernels: list[Kernel], out: Path, options: dict) -> str:
    gen = ca.CodeGenerator(f"{stem}.c", dict(options))
    for k in kernels:
        gen.add(k.function)
    gen.generate(str(out) + "/")
    c_file = out / f"{stem}.c"
    text = _mark_unused_parameters(c_file.read_text())
    c_file.write_text(text)
    return text


def _c_string(text: str) -> str:
    lines = []
    for line in text.split("\n"):
        escaped = line.replace("\\", "\\\\").replace('"', '\\"')
        lines.append(f'  "{escaped}\\n"')
    return "\n".join(lines)


def _preamble(title: str) -> str:
    return (f"/* {title}\n * Generated by cochlea-codegen from cochlea/data/codegen/kernels.toml: "
            "do not edit; run cochlea-codegen. */\n")


_EXPORT = """#ifndef CASADI_SYMBOL_EXPORT
  #if defined(_WIN32) || defined(__WIN32__) || defined(__CYGWIN__)
    #define CASADI_SYMBOL_EXPORT __declspec(dllexport)
  #elif defined(__GNUC__) && defined(GCC_HASCLASSVISIBILITY)
    #define CASADI_SYMBOL_EXPORT __attribute__ ((visibility ("default")))
  #else
    #define CASADI_SYMBOL_EXPORT
  #endif
#endif
"""

_LOOP_ARGS = ("casadi_int n, casadi_int delay, const casadi_real* x0, const casadi_real* p_hat0, "
              "const casadi_real* xd, const casadi_real* xd_dot, const casadi_real* xd_ddot, "
              "const casadi_real* noise, const casadi_real* gains, const casadi_real* Gamma, "
              "casadi_real bound, casadi_real h, const casadi_real* plant_p, "
              "const casadi_real* friction, casadi_real* x_log, casadi_real* p_hat_log, "
              "casadi_real* tau_log, casadi_real* errors_log, casadi_real* pose_log, "
              "casadi_int* rows")


def _write_closed_loops(loops: list[ClosedLoop], kernels: list[Kernel], out: Path) -> None:
    by_name = {k.name: k for k in kernels}
    groups = sorted({by_name[n].group for loop in loops for n in (loop.step, loop.plant,
                                                                  loop.pose)})
    template = Template(TEMPLATE.read_text())
    parts = [_preamble("N periods of the closed loop in C, one function per controller."),
             "#include <math.h>\n", _EXPORT]
    parts += [f'#include "{g}.h"\n' for g in groups]
    for loop in loops:
        parts.append("\n" + template.substitute(
            name=loop.name, step=loop.step, plant=loop.plant, pose=loop.pose, nq=loop.nq,
            np=loop.n_params, nd=loop.n_desired, ne=loop.n_errors, npose=loop.n_pose))
    (out / "closed_loop.c").write_text("".join(parts))
    header = [_preamble("Closed-loop drivers (closed_loop.c); see README.md."),
              "#ifndef COCHLEA_CLOSED_LOOP_H\n#define COCHLEA_CLOSED_LOOP_H\n",
              "#ifdef __cplusplus\nextern \"C\" {\n#endif\n",
              "#ifndef casadi_real\n#define casadi_real double\n#endif\n",
              "#ifndef casadi_int\n#define casadi_int long long int\n#endif\n"]
    header += [f"int {loop.name}({_LOOP_ARGS});\n" for loop in loops]
    header.append("#ifdef __cplusplus\n}\n#endif\n#endif\n")
    (out / "closed_loop.h").write_text("".join(header))


def _manifest(config: CodegenConfig, kernels: list[Kernel], loops: list[ClosedLoop],
              work: dict[str, dict[str, int]]) -> dict:
    return {
        "format": MANIFEST_FORMAT,
        "casadi": ca.__version__,
        "library": config.library,
        "kernels": {k.name: {
            "group": k.group, "role": k.role, "robot": k.robot, "unit": k.unit,
            "kind": k.kind, "variant": k.variant, "source": k.source.name(),
            "sha256": source_hash(k.source), "work": work[k.name], **_signature(k.function),
        } for k in kernels},
        "closed_loops": {loop.name: {
            "step": loop.step, "plant": loop.plant, "pose": loop.pose, "nq": loop.nq,
            "n_params": loop.n_params, "n_desired": loop.n_desired, "n_errors": loop.n_errors,
            "n_pose": loop.n_pose, "n_plant_params": loop.n_plant_params,
            "n_gains": loop.n_gains,
        } for loop in loops},
    }


def generate(config: CodegenConfig | None = None, out: str | Path | None = None) -> list[Path]:
    """Write every file of ``generated_c/`` (or ``out``); return the paths written."""
    config = config or load_config()
    out = Path(out) if out is not None else config.output
    out.mkdir(parents=True, exist_ok=True)
    for old in out.iterdir():  # the folder holds generated files only
        if old.is_file():
            old.unlink()
    kernels, loops = collect(config)
    groups: dict[str, list[Kernel]] = {}
    for k in kernels:
        groups.setdefault(k.group, []).append(k)
    work: dict[str, dict[str, int]] = {}
    for stem, members in groups.items():
        text = _generate_group(stem, members, out, config.casadi)
        for k in members:
            work[k.name] = _work_sizes(text, k.name)
    _write_closed_loops(loops, kernels, out)
    manifest = _manifest(config, kernels, loops, work)
    manifest_text = json.dumps(manifest, indent=1, sort_keys=True)
    (out / "manifest.c").write_text(
        _preamble("The kernels' manifest: signatures and source hashes, as JSON.")
        + _EXPORT + "static const char manifest[] =\n" + _c_string(manifest_text) + ";\n\n"
        "CASADI_SYMBOL_EXPORT const char* cochlea_manifest(void) { return manifest; }\n")
    umbrella = [_preamble(f"Every kernel of lib{config.library}.so; see README.md."),
                "#ifndef COCHLEA_H\n#define COCHLEA_H\n"]
    umbrella += [f'#include "{stem}.h"\n' for stem in groups]
    umbrella += ['#include "closed_loop.h"\n',
                 "#ifdef __cplusplus\nextern \"C\" {\n#endif\n",
                 "/* The manifest (JSON): every kernel's signature and source hash. */\n",
                 "const char* cochlea_manifest(void);\n",
                 "#ifdef __cplusplus\n}\n#endif\n#endif\n"]
    (out / f"{config.library}.h").write_text("".join(umbrella))
    (out / "README.md").write_text(readme(config, kernels, loops, work))
    return sorted(out.iterdir())


def check(config: CodegenConfig | None = None) -> list[str]:
    """Regenerate into a temporary folder; return the files that differ (empty: fresh)."""
    config = config or load_config()
    with tempfile.TemporaryDirectory(prefix="cochlea-codegen-") as tmp:
        generate(config, tmp)
        fresh = {p.name for p in Path(tmp).iterdir()}
        committed = ({p.name for p in config.output.iterdir() if p.is_file()}
                     if config.output.is_dir() else set())
        differ = sorted(fresh ^ committed)
        differ += sorted(name for name in fresh & committed
                         if not filecmp.cmp(Path(tmp) / name, config.output / name,
                                            shallow=False))
    return sorted(set(differ))
