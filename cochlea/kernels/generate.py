"""``cochlea-codegen``: the symbolic models and controllers as C kernels in ``generated_c/``.

The four stages of the fast path, one module each (describe -> generate -> build -> load):

1. ``codegen/kernels.toml`` says which kernels to export and with which CasADi options
   (:class:`CodegenConfig`, read by :func:`load_config`);
2. this module builds the CasADi Functions from the descriptions in ``models/robots/``
   and writes C
   with ``casadi.CodeGenerator`` (:func:`generate`);
3. the Makefile compiles ``generated_c/*.c`` into ``build/libcochlea.so`` (no Python needed);
4. :mod:`cochlea.kernels.library` loads the library through ctypes.

What is generated, per robot unit (``serial_arm1``, ``serial_arm2``, ``parallel``):

* ``<unit>.c``: the model's kernels (``<unit>_M``, ``_C``, ``_G``, ``_fk``, ``_J``, ...,
  ``_forward_dynamics``, the ``*_p`` kernels in the full inertial parameters) and
  ``<unit>_plant_step``, one RK4 control period of the plant (``cochlea.robots.plant.plant_step``),
  and ``<unit>_plant_step_coulomb``, the same with dry friction (``plant_coulomb`` in the
  configuration); ``<unit>_armature_plant_step[_coulomb]``, the plant with its drives'
  reflected rotor inertia (``plant_actuators``);
* ``<unit>_<kind>[_thesis|_actuated].c``: controller ``kind`` (and its thesis variant, and the
  variant whose model carries the drives' armature and friction, ``controller_actuators``): the
  regressor ``_Y``, the law ``_law`` (torque, estimate rate, errors), the update law ``_update``
  (estimate rate alone) and the fused ``_step`` (torque, next estimate, errors);
* ``closed_loop.c``: ``<unit>_<kind>[_thesis|_actuated]_closed_loop[_armature][_coulomb]``, N
  periods of controller, estimate update and plant (``_armature``: with the drives' rotor
  inertia; ``_coulomb``: with dry friction) in C (from the template
  ``codegen/closed_loop.c.in``);
* ``embedded/<scenario>.{h,c}`` (the ``[embedded]`` table, when ``cochlea-codegen`` passes
  :func:`cochlea.sim.embedded.write_embedded`): each listed scenario's whole controller (desired
  trajectory, law, estimate update) for an embedded target, float or double at compile time
  (:mod:`cochlea.kernels.embedded`, ``docs/embedded.md``); ``make lib`` does not build them;
* ``manifest.c`` (``cochlea_manifest()``: every kernel's signature and the SHA-256 of the CasADi
  Function it came from, so a caller can tell a stale library), ``cochlea.h`` (includes every
  header) and ``README.md`` (each function's inputs, outputs, sizes, units and work memory);
* ``cochlea_trig.h`` (a copy of ``codegen/cochlea_trig.h``): the inline ``cochlea_sincos`` the
  ideal plant steps take each angle's sin and cos from (:mod:`cochlea.kernels.trig`; not the
  geared plant, the controllers or the model kernels, which keep libm).

In every file CasADi's helpers (``casadi_sq``, ``casadi_fmin``, ...) are ``static``, so the
compiler inlines them even in the ``-fPIC`` library, and ``casadi_fmin``/``casadi_fmax`` compare
where both arguments are numbers instead of calling libm (:mod:`cochlea.kernels.helpers`: the
same bits as libm's, but for the sign of a zero where +0 ties -0).

No body is generated twice: a kernel that computes exactly what an earlier one does (the same
:func:`~cochlea.kernels.naming.computation_hash`) is an *alias*. It has no C of its own; the
manifest keeps its entry (name, signature, source hash) with ``"symbol"``, the kernel whose C it
runs, and :mod:`cochlea.kernels.library` resolves it. So ``serial_arm2.c`` holds only what differs
from arm 1 (the base pose: ``fk_world``), a file whose every kernel is an alias
(``serial_arm1_e_thesis``, ``serial_arm2_e``, ...) is not written, and a driver making the same
calls as an earlier one is an alias of it in ``closed_loops``.

Every output is dense (column-major for matrices) and every kernel is generic in what a scenario
chooses: gains, adaptation gain, projection bound, period, plant parameters, friction.
Generation is deterministic: the same inputs give byte-identical files.
"""

from __future__ import annotations

import filecmp
import json
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from string import Template

import casadi as ca

from ..console import signals_held
from .catalogue import (
    CONFIG,
    TEMPLATE,
    ClosedLoop,
    CodegenConfig,
    CodegenError,
    Kernel,
    collect,
    load_config,
)
from .helpers import static_helpers
from .naming import MANIFEST_FORMAT, source_hash
from .readme import readme
from .trig import HEADER as TRIG_HEADER
from .trig import HEADER_NAME as TRIG_HEADER_NAME
from .trig import inline_trig

__all__ = ["CONFIG", "CodegenError", "load_config", "generate", "check", "write_kernels"]

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
    """Write ``<stem>.c`` and ``.h``; CasADi's helpers static, min and max inline
    (:mod:`.helpers`), the ideal plant steps' sin and cos inline (:mod:`.trig`; with
    ``cochlea_trig.h`` beside them)."""
    gen = ca.CodeGenerator(f"{stem}.c", dict(options))
    for k in kernels:
        gen.add(k.function)
    gen.generate(str(out) + "/")
    c_file = out / f"{stem}.c"
    text = static_helpers(_mark_unused_parameters(c_file.read_text()))
    text, sincos = inline_trig(text, [k.name for k in kernels if k.inline_trig])
    if sincos:
        (out / TRIG_HEADER_NAME).write_text(TRIG_HEADER.read_text())
    c_file.write_text(text)
    return text


def _c_string(text: str) -> str:
    lines = []
    for line in text.split("\n"):
        escaped = line.replace("\\", "\\\\").replace('"', '\\"')
        lines.append(f'  "{escaped}\\n"')
    return "\n".join(lines)


def _preamble(title: str, source: str | None = None) -> str:
    """A generated file's opening comment; ``source``: what it was generated from (default:
    the shipped configuration)."""
    if source is None:
        return (f"/* {title}\n * Generated by cochlea-codegen from codegen/"
                "kernels.toml: do not edit; run cochlea-codegen. */\n")
    return f"/* {title}\n * Generated by cochlea-codegen from {source}: do not edit. */\n"


def _source(config: CodegenConfig) -> str | None:
    """What a configuration's files say they come from: None for the shipped configuration;
    for a user's scenario (no ``robots``), its file's name and the command."""
    if config.robots:
        return None
    return (f"scenario {config.path.name} (cochlea-codegen --scenario {config.path.name} "
            "--out DIR)")


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

_LOOP_ARGS = ("casadi_int n, casadi_int delay, const casadi_int* delays, "
              "const casadi_real* x0, const casadi_real* p_hat0, "
              "const casadi_real* xd, const casadi_real* xd_dot, const casadi_real* xd_ddot, "
              "const casadi_real* noise, const casadi_real* quantum, const casadi_real* offset, "
              "const casadi_real* gains, const casadi_real* Gamma, "
              "casadi_real bound, casadi_real h, const casadi_real* robust, "
              "const casadi_real* plant_p, "
              "const casadi_real* friction, const casadi_real* drive, "
              "const casadi_real* effort_limit, const casadi_real* effort_quantum, "
              "const casadi_real* effort_bound, const casadi_real* effort_offset, "
              "const casadi_real* effort_ramp, const casadi_real* torque_scale, "
              "casadi_int n_keep_out, const casadi_int* keep_out_index, "
              "const casadi_real* keep_out_centre, "
              "casadi_real* x_log, casadi_real* p_hat_log, "
              "casadi_real* tau_log, casadi_real* errors_log, casadi_real* pose_log, "
              "casadi_int* rows, casadi_real* reductions")


def _write_closed_loops(loops: list[ClosedLoop], kernels: list[Kernel], out: Path,
                        source: str | None = None) -> None:
    by_name = {k.name: k for k in kernels}
    drivers = [loop for loop in loops if not loop.is_alias]
    groups = sorted({by_name[n].group for loop in drivers for n in loop.calls})
    template = Template(TEMPLATE.read_text())
    parts = [_preamble("N periods of the closed loop in C, one function per controller "
                       "(a controller computing what another does shares its driver).", source),
             "#include <math.h>\n", _EXPORT]
    parts += [f'#include "{g}.h"\n' for g in groups]
    for loop in drivers:
        step, plant, pose = loop.calls
        parts.append("\n" + template.substitute(
            name=loop.name, step=step, plant=plant, pose=pose, nq=loop.nq,
            np=loop.n_params, nd=loop.n_desired, ne=loop.n_errors, npose=loop.n_pose,
            nxp=loop.nx, n_drive=loop.n_drive, nr=loop.n_reductions,
            coulomb_arg="plant_arg[5] = drive;" if loop.coulomb else "(void)drive;"))
    (out / "closed_loop.c").write_text("".join(parts))
    header = [_preamble("Closed-loop drivers (closed_loop.c); see README.md.", source),
              "#ifndef COCHLEA_CLOSED_LOOP_H\n#define COCHLEA_CLOSED_LOOP_H\n",
              "#ifdef __cplusplus\nextern \"C\" {\n#endif\n",
              "#ifndef casadi_real\n#define casadi_real double\n#endif\n",
              "#ifndef casadi_int\n#define casadi_int long long int\n#endif\n"]
    header += [f"int {loop.name}({_LOOP_ARGS});\n" for loop in drivers]
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
            "kind": k.kind, "variant": k.variant, "actuators": k.actuators,
            "source": k.source.name(),
            "sha256": source_hash(k.source), "work": work[k.symbol], "symbol": k.symbol,
            **_signature(k.function),
        } for k in kernels},
        "closed_loops": {loop.name: {
            "symbol": loop.symbol,
            "step": loop.step, "plant": loop.plant, "pose": loop.pose, "nq": loop.nq,
            "n_params": loop.n_params, "n_desired": loop.n_desired, "n_errors": loop.n_errors,
            "n_pose": loop.n_pose, "n_plant_params": loop.n_plant_params,
            "nx": loop.nx, "n_drive": loop.n_drive,
            "n_gains": loop.n_gains, "n_reductions": loop.n_reductions,
        } for loop in loops},
    }


#: Writes the ``[embedded]`` scenarios' controllers into a folder: ``(config, folder) -> paths``
#: (:func:`cochlea.sim.embedded.write_embedded`; a scenario is the simulation layer's, so the
#: caller, ``cochlea-codegen``, passes it in).
EmbeddedWriter = Callable[[CodegenConfig, Path], list[Path]]


def generate(config: CodegenConfig | None = None, out: str | Path | None = None,
             embedded: EmbeddedWriter | None = None) -> list[Path]:
    """Write every file of ``generated_c/`` (or ``out``); return the paths written.

    ``embedded``: also write the per-scenario embedded controllers of ``config.embedded`` into
    the subfolder ``config.embedded.folder`` (without it, that subfolder is left alone).

    All or nothing: everything is written into a temporary folder beside ``out`` first, so a
    configuration that fails to build, a full disk or an interrupt leaves the old files whole;
    only then are the new files renamed into ``out`` (renames need no space) and the stale ones
    removed, with SIGINT and SIGTERM held off for those few milliseconds.
    """
    config = config or load_config()
    out = Path(out) if out is not None else config.output
    kernels, loops = collect(config)
    return write_kernels(config, kernels, loops, out, embedded)


def write_kernels(config: CodegenConfig, kernels: list[Kernel], loops: list[ClosedLoop],
                  out: Path, embedded: EmbeddedWriter | None = None) -> list[Path]:
    """Write ``kernels`` and ``loops`` (from :func:`~cochlea.kernels.catalogue.collect` or
    :func:`~cochlea.kernels.catalogue.collect_units`) into ``out``, all or nothing (see
    :func:`generate`), with ``config``'s CasADi options and library name."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.new-", dir=out.parent))
    try:
        written = _write_all(config, kernels, loops, staging, embedded)
        return _install(staging, out, [p.relative_to(staging) for p in written])
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _install(staging: Path, out: Path, names: list[Path]) -> list[Path]:
    """Move the files ``names`` (relative paths) from ``staging`` into ``out``, replacing what
    is there, and remove ``out``'s other files in the folders written (its generated files
    only: see ``cochlea-codegen``'s check of ``--out``)."""
    with signals_held():
        folders = {out / name.parent for name in names}
        for folder in sorted(folders):
            folder.mkdir(parents=True, exist_ok=True)
        for name in names:
            os.replace(staging / name, out / name)
        kept = {out / name for name in names}
        for folder in folders:
            for old in folder.iterdir():
                if old.is_file() and old not in kept:
                    old.unlink()
    return sorted(out / name for name in names)


def _write_all(config: CodegenConfig, kernels, loops, out: Path,
               embedded: EmbeddedWriter | None) -> list[Path]:
    """Write every generated file into the (new, empty) folder ``out``."""
    groups: dict[str, list[Kernel]] = {}
    for k in kernels:
        if not k.is_alias:  # an alias runs its symbol's C: nothing of its own to write
            groups.setdefault(k.group, []).append(k)
    work: dict[str, dict[str, int]] = {}
    for stem, members in groups.items():
        text = _generate_group(stem, members, out, config.casadi)
        for k in members:
            work[k.name] = _work_sizes(text, k.name)
    source = _source(config)
    _write_closed_loops(loops, kernels, out, source)
    manifest = _manifest(config, kernels, loops, work)
    manifest_text = json.dumps(manifest, indent=1, sort_keys=True)
    (out / "manifest.c").write_text(
        _preamble("The kernels' manifest: signatures and source hashes, as JSON.", source)
        + _EXPORT + "static const char manifest[] =\n" + _c_string(manifest_text) + ";\n\n"
        "CASADI_SYMBOL_EXPORT const char* cochlea_manifest(void) { return manifest; }\n")
    umbrella = [_preamble(f"Every kernel of lib{config.library}.so; see README.md.", source),
                "#ifndef COCHLEA_H\n#define COCHLEA_H\n"]
    umbrella += [f'#include "{stem}.h"\n' for stem in groups]
    umbrella += ['#include "closed_loop.h"\n',
                 "#ifdef __cplusplus\nextern \"C\" {\n#endif\n",
                 "/* The manifest (JSON): every kernel's signature and source hash. */\n",
                 "const char* cochlea_manifest(void);\n",
                 "#ifdef __cplusplus\n}\n#endif\n#endif\n"]
    (out / f"{config.library}.h").write_text("".join(umbrella))
    (out / "README.md").write_text(readme(config, kernels, loops, work))
    written = sorted(p for p in out.iterdir() if p.is_file())
    if embedded is not None and config.embedded.scenarios:
        written += embedded(config, out / config.embedded.folder)
    return written


def _files(folder: Path, embedded: str | None) -> set[str]:
    """The generated files under ``folder``: its own, and ``<embedded>/<name>`` if asked."""
    if not folder.is_dir():
        return set()
    names = {p.name for p in folder.iterdir() if p.is_file()}
    if embedded is not None and (folder / embedded).is_dir():
        names |= {f"{embedded}/{p.name}" for p in (folder / embedded).iterdir() if p.is_file()}
    return names


def check(config: CodegenConfig | None = None, embedded: EmbeddedWriter | None = None
          ) -> list[str]:
    """Regenerate into a temporary folder; return the files that differ (empty: fresh).
    With ``embedded``, the embedded controllers' subfolder is compared too (as
    ``embedded/<file>``)."""
    config = config or load_config()
    sub = config.embedded.folder if embedded is not None else None
    with tempfile.TemporaryDirectory(prefix="cochlea-codegen-") as tmp:
        generate(config, tmp, embedded)
        fresh = _files(Path(tmp), sub)
        committed = _files(config.output, sub)
        differ = sorted(fresh ^ committed)
        differ += sorted(name for name in fresh & committed
                         if not filecmp.cmp(Path(tmp) / name, config.output / name,
                                            shallow=False))
    return sorted(set(differ))
