"""The embedded controller's rows of ``make bench`` (issue 12), and the all-in-C simulation.

1. **The step in double and in float.** Each scenario's generated controller
   (``generated_c/embedded/<scenario>.c``) is built twice into a shared library with a small
   timing harness (``bench/time_embedded_step.c``), once as is and once with
   ``-DCOCHLEA_FLOAT``. Both libraries are loaded into this process and timed turn about, on
   the measurements the simulation's controller saw over its first second (delayed and on the
   encoder grid where the scenario says so): ns per ``<scenario>_step`` call, and their ratio.
   For comparison, the Python real-time loop's controller work per period on the same scenario
   (``RealTimeLoop`` as fast as possible on the sim backend: its compute time less the
   backend's read and write).
2. **The all-in-C simulation** (``embedded/sim/simulate.c``): the embedded controller (its own
   desired trajectory, evaluated in C every period) and the units' plant periods, specialised
   to the scenario's constants (:func:`specialised_plant`; the geared plant: its general kernel
   in ``generated_c/<group>.c``), one process, no Python and no CasADi. Its real-time factor is
   taken end to end: from starting the process to its exit, log written.

Build the programs with ``python bench/embedded_bench.py build [SCENARIO ...]`` (or
``make embedded-sim``); ``python bench/embedded_bench.py bench`` runs only these rows and writes
``build/embedded-bench.json``. ``bench/run.py`` calls :func:`bench_embedded_steps`,
:func:`bench_embedded_sims`, :func:`verdicts` and :func:`markdown`.

A program's scenario is compiled in: :func:`sim_scenario_header` writes its
``sim_scenario.h`` (``embedded/sim/sim.h`` says what it defines) and ``sim_plant.c`` from
``unit_setups`` -- the plant's parameters, the initial state, the grids -- once, at build time.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import gc
import hashlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import casadi as ca
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from cochlea.kernels import library as ckernels
from cochlea.kernels.generate import _mark_unused_parameters, _work_sizes
from cochlea.robots.parallel import ParallelSystem
from cochlea.robots.parallel.forward import forward_dynamics as parallel_forward
from cochlea.robots.plant import plant_step
from cochlea.robots.serial.folded import folded_forward_dynamics
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.result import SimulationResult, simulated_log
from cochlea.sim.setup import (
    ENCODER_STREAM,
    JITTER_STREAM,
    delay_ages,
    disturbance_rng,
    encoder_noise,
    measurements,
)

GENERATED = ROOT / "generated_c"
EMBEDDED = GENERATED / "embedded"
SIM_SOURCE = ROOT / "embedded" / "sim"
HARNESS = ROOT / "bench" / "time_embedded_step.c"
BUILD = ROOT / "build" / "embedded-sim"

#: Every scenario with an embedded controller, the four thesis studies first.
THESIS = ("serial_joint", "serial_task", "parallel_joint", "parallel_task")
SCENARIOS = THESIS + tuple(f"{n}_realistic" for n in THESIS)
PRECISIONS = ("double", "float")
#: Warnings are errors; the optimisation of the rest of the benchmark (make lib).
CFLAGS = ("-std=c99", "-pedantic", "-Wall", "-Wextra", "-Werror", "-O2")
FLOAT_FLAGS = ("-DCOCHLEA_FLOAT",)
#: The simulation is linked statically where the C library allows (else as usual): loading it
#: dynamically took 0.6-1 ms of every run, up to 10 % of a 20 s study at 2000x.
LINK_FLAGS = ("-static", "-pthread", "-lm")
#: The targets of these rows (bench/run.py merges them into its TARGETS): issue 30's real-time
#: factors of the all-in-C simulation end to end, log written, per robot.
TARGETS = {"embedded_sim_serial_rtf": 2000.0, "embedded_sim_parallel_rtf": 1000.0}
#: What the step timing replays: the first second of each scenario (periods).
REPLAY_PERIODS = 1000
#: Fields of a unit's log, compared with the simulation's.
LOG_FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose", "true_q",
              "true_qd", "true_x")


def compiler() -> str:
    cc = os.environ.get("CC", "cc")
    if shutil.which(cc) is None:
        raise RuntimeError(f"no C compiler {cc!r} (set CC)")
    return cc


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------


def _digest(*parts) -> str:
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:16]


def _run_cc(command: list[str]) -> None:
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0 or done.stderr:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")


def _object(source: Path, flags: tuple[str, ...], include: tuple[Path, ...] = (),
            included: tuple[Path, ...] = ()) -> Path:
    """``source`` compiled with ``flags``, cached in build/embedded-sim/obj/ by the compiler,
    the flags and the text of the source, of every header in its include folders and of the
    other sources it includes (``included``)."""
    cc = compiler()
    headers = sorted({h for d in (source.parent, *include) for h in Path(d).glob("*.h")})
    key = _digest(cc, flags, source.read_text(), [(h.name, h.read_text()) for h in headers],
                  [(c.name, c.read_text()) for c in included])
    obj = BUILD / "obj" / f"{source.stem}-{key}.o"
    if not obj.exists():
        obj.parent.mkdir(parents=True, exist_ok=True)
        partial = obj.with_name(f".{obj.name}.{os.getpid()}")
        _run_cc([cc, *flags, *(f"-I{d}" for d in include), "-c", str(source), "-o",
                 str(partial)])
        os.replace(partial, obj)
    return obj


def _c_array(name: str, values) -> str:
    values = [repr(float(v)) for v in np.ravel(values)]
    return f"static const double {name}[{len(values)}] = {{{', '.join(values)}}};"


def _kernel_source(lib: ckernels.Library, kernel: str,
                   generated: Path = GENERATED) -> tuple[str, str]:
    """The C function a library kernel runs and the group (``generated_c/<group>.c``, or
    ``generated``'s) that defines it."""
    symbol = lib.symbol(kernel)
    entry = lib.manifest["kernels"][symbol]
    if entry["work"]["iw"] or entry["work"]["w"]:
        raise RuntimeError(f"{symbol} needs work memory: simulate.c passes none")
    group = entry["group"]
    header = (generated / f"{group}.h").read_text()
    if f"int {symbol}(const casadi_real** arg" not in header:
        raise RuntimeError(f"{symbol} is not declared in generated_c/{group}.h")
    return symbol, group


def sim_scenario(name: str | Path):
    """The scenario ``name`` (or a scenario file) as the all-C simulation runs it: as
    ``simulate()`` does, the realistic preset's geared plant included."""
    return load_scenario(name)


def _stream_seeds(plant) -> list[str]:
    """``sim_jitter_seed`` and ``sim_encoder_seed`` where the plant draws them: each stream's
    numpy PCG64 as it starts (:func:`cochlea.sim.setup.disturbance_rng`), state and increment
    as high and low 64 bits (embedded/sim/sim.h)."""
    lines = []
    for key, stream, label in (("delay_jitter_periods", JITTER_STREAM, "jitter"),
                               ("encoder_noise_counts", ENCODER_STREAM, "encoder")):
        if not getattr(plant, key):
            continue
        state = disturbance_rng(plant, stream).bit_generator.state
        assert state["bit_generator"] == "PCG64", state
        words = []
        for value in (state["state"]["state"], state["state"]["inc"]):
            words += [value >> 64, value & (2 ** 64 - 1)]
        lines.append(f"static const uint64_t sim_{label}_seed[4] = {{"
                     + ", ".join(f"0x{w:016X}ULL" for w in words) + "};")
    return lines


def specialised_plant(u, substeps: int, period: float, name: str,
                      stage_trig: bool = False) -> ca.Function | None:
    """Unit ``u``'s plant period (the Function its general kernel was generated from, which
    :func:`cochlea.sim.compiled.unit_kernels` checks against the library) with the scenario's
    constants folded in: ``(x, tau) -> x_next``, the true plant's parameters, its friction, the
    period ``period`` (s) and, where the plant has one, its dry friction or drive (the 6th
    input) as literals.

    The forward dynamics it integrates (the same RK4 period) is the cheapest exact form at
    those constants: a serial arm's folded sums and ``L D L^T`` solve
    (:func:`cochlea.robots.serial.folded.folded_forward_dynamics`: the shipped arms' plant
    period 520 operations instead of the articulated-body algorithm's 652) where that has
    fewer operations than the general form folded, the parallel mechanism's block form
    (:func:`cochlea.robots.parallel.forward.forward_dynamics`: 369 operations an evaluation
    instead of 1688): equal to the general kernel to rounding (1e-12 relative,
    tests/test_embedded_sim.py), not bit for bit. The geared plant keeps its general form
    (folding its constants moved results by an ulp, which backlash grew to 1e-2 rad).

    ``stage_trig=True``: the same period with its RK4 stages' sines and cosines shifted from
    the first stage's (:mod:`cochlea.robots.stage_trig`), ``(x, tau) -> (x_next, far)``; None
    for the geared plant and a plant that takes no sine or cosine of a joint angle."""
    general = u.plant_function(substeps)
    coulomb = u.drive is not None
    forwards = [None]  # None: the general Function's own forward dynamics
    if not u.gearbox:
        if isinstance(getattr(u.plant_model.geometry, "system", None), ParallelSystem):
            forwards = [parallel_forward(u.plant_model)]
        else:
            folded = folded_forward_dynamics(u.plant_model, u.plant_params)
            forwards += [] if folded is None else [folded]
    x = ca.SX.sym("x", general.size1_in(0))
    tau = ca.SX.sym("tau", general.size1_in(1))
    constants = [u.plant_params, u.friction, period]
    if general.n_in() == 6:
        constants.append(u.drive)
    constants = [ca.DM(np.ravel(c)) for c in constants]

    def specialised(f: ca.Function) -> ca.Function:
        outs = f(x, tau, *constants)
        outs = list(outs) if isinstance(outs, tuple) else [outs]
        return ca.Function(name, [x, tau], outs, ["x", "tau"], f.name_out())

    candidates = [specialised(general if forward is None else
                              plant_step(u.plant_model, substeps, coulomb=coulomb,
                                         forward=forward)) for forward in forwards]
    best = min(range(len(candidates)), key=lambda i: candidates[i].n_instructions())
    if not stage_trig:
        return candidates[best]
    if u.gearbox:
        return None
    stages = plant_step(u.plant_model, substeps, coulomb=coulomb, forward=forwards[best],
                        stage_trig=True)
    if not ca.depends_on(stages(x, tau, *constants)[1], x):
        return None  # no joint angle's sine or cosine to shift
    return specialised(stages)


#: The robots whose all-in-C simulations take sin and cos from sim_sincos (embedded/sim/
#: sim_trig.h, inline, within an ulp of libm's) instead of libm, in the plant and in the
#: double build's controller, and divide by the plant's articulated inertias through shared
#: reciprocals, where :func:`inline_trig_applies`: the serial arms, whose ideal studies do not
#: amplify an ulp (docs/embedded.md). The parallel mechanism keeps libm and its divisions
#: (its general plant kernel takes the inline sincos since issue 30's block form, within
#: rounding of this plant either way): with "parallel" added its ideal studies' logs stayed within
#: rounding of simulate()'s (1.0e-14 and 4.4e-15 absolute over 10 s, as with libm) but were no
#: faster (loop CPU 8.05 -> 8.02 ms and 17.67 -> 17.70 ms, 100 runs each turn about): the
#: inline sincos costs what libm's __sincos_fma did (perf: 12 % of parallel_task moved into the
#: law and the plant), and its block-form plant has no repeated divisor to share.
INLINE_TRIG_ROBOTS = ("serial",)


def rounding_free(sc, setups) -> bool:
    """Whether scenario ``sc``'s results may move by rounding: no geared plant (its backlash
    grew an ulp to 1e-2 rad over a study) and no measurement or effort grid (an ulp may move a
    value across a grid step). Elsewhere the simulation's log is simulate()'s bit for bit."""
    return not any(u.gearbox or u.quantum is not None or u.effort_grid is not None
                   for u in setups)


def inline_trig_applies(sc, setups) -> bool:
    """Whether scenario ``sc``'s simulation takes sin and cos from sim_sincos: a robot of
    :data:`INLINE_TRIG_ROBOTS` whose results may move by rounding (:func:`rounding_free`):
    elsewhere libm."""
    return sc.robot in INLINE_TRIG_ROBOTS and rounding_free(sc, setups)


#: Whether a unit's specialised plant takes its later RK4 stages' sines and cosines from the
#: first stage's (:func:`stage_plant_c`, :mod:`cochlea.robots.stage_trig`): 12 of the parallel
#: plant's 16 sincos a period and 6 of a serial arm's 8 become a few products each; the
#: program's instructions fell by a tenth, its time by 2-9 % (the sincos had mostly run beside
#: the plant's longer chain of dependent operations).
STAGE_TRIG = True


#: What the simulation of a study that may move by rounding (:func:`rounding_free`) is
#: compiled for where the machine building it has x86-64's v3 level (AVX2 and FMA: Intel from
#: 2013, AMD from 2015): that machine's instructions, multiply-adds fused. Every period of the
#: program is one chain of dependent operations (the law's torque into the plant's four RK4
#: stages into the next law), so its speed is the chain's latency, and a fused multiply-add
#: halves a product-and-sum's: parallel_task's loop 7.65 -> 6.26 ms, serial_task's 7.50 ->
#: 6.74 ms (40 runs each turn about; -march=x86-64-v3 alone 7.00 ms, -O3 7.53 ms). The results
#: move by rounding (a fused operation rounds once), within 2e-14 of simulate()'s
#: (tests/test_embedded_sim.py). The program runs where it was built (build/embedded-sim/);
#: ``COCHLEA_SIM_HOST_ISA=0`` builds it for any x86-64 instead.
HOST_ISA_FLAGS = ("-march=x86-64-v3", "-ffp-contract=fast")


@functools.cache
def _host_has_v3(cc: str) -> bool:
    """Whether this machine runs x86-64 v3 code and ``cc`` compiles for it (GCC 12's or
    clang's ``__builtin_cpu_supports("x86-64-v3")``, probed by a program built and run)."""
    probe = BUILD / "obj" / "host-isa"
    probe.mkdir(parents=True, exist_ok=True)
    source = probe / f"probe-{os.getpid()}.c"  # one a process: pytest's workers probe at once
    source.write_text('int main(void) { __builtin_cpu_init(); '
                      'return !__builtin_cpu_supports("x86-64-v3"); }\n')
    binary = probe / f"probe-{os.getpid()}"
    try:
        built = subprocess.run([cc, *HOST_ISA_FLAGS, str(source), "-o", str(binary)],
                               capture_output=True)
        return built.returncode == 0 and subprocess.run([str(binary)]).returncode == 0
    except OSError:
        return False
    finally:
        binary.unlink(missing_ok=True)
        source.unlink(missing_ok=True)


def host_isa_flags(sc, setups) -> tuple[str, ...]:
    """:data:`HOST_ISA_FLAGS` for scenario ``sc``'s simulation where they apply (a study that
    may move by rounding, built on an x86-64 v3 machine, ``COCHLEA_SIM_HOST_ISA`` not 0), else
    none. ``COCHLEA_SIM_HOST_ISA`` is 0 or 1 (unset: 1); any other value is refused."""
    choice = os.environ.get("COCHLEA_SIM_HOST_ISA", "1")
    if choice not in ("0", "1"):
        raise ValueError(f"COCHLEA_SIM_HOST_ISA is {choice!r}: 0 (build for any x86-64) or 1 "
                         "(for this machine's x86-64 v3 level where it has it)")
    if choice == "0" or not rounding_free(sc, setups):
        return ()
    return HOST_ISA_FLAGS if _host_has_v3(compiler()) else ()

_ASSIGN = re.compile(r"^\s*(a\d+)=(.*);$")
_TRIG = re.compile(r"^(\s*)(a\d+)=(sin|cos)\((a\d+)\);$")


def inline_trig(text: str) -> str:
    """CasADi's C of straight-line functions with each ``sin(a)`` and ``cos(a)`` of one value
    of ``a`` (a variable between two assignments) taken from one ``sim_sincos(a, ...)`` at the
    first of them, and a lone ``sin`` or ``cos`` from ``sim_sin`` or ``sim_cos``
    (embedded/sim/sim_trig.h). No other call of sin or cos may be left."""
    lines = text.split("\n")
    version: dict[str, int] = {}
    seen: dict[tuple[str, int], dict] = {}  # (variable, version) -> its sin and cos lines
    pairs = 0
    for i, line in enumerate(lines):
        if line.startswith("static ") or line.startswith("}"):
            version, seen = {}, {}  # a function's variables are its own
            continue
        trig = _TRIG.match(line)
        if trig:
            indent, target, kind, arg = trig.groups()
            uses = seen.setdefault((arg, version.get(arg, 0)), {"lines": {}})
            if kind in uses["lines"]:
                raise RuntimeError(f"inline_trig: {kind}({arg}) twice: {line.strip()}")
            uses["lines"][kind] = (i, indent, target)
            if len(uses["lines"]) == 2:
                (first, f_indent, f_target), (second, s_indent, s_target) = sorted(
                    (uses["lines"]["sin"], uses["lines"]["cos"]))
                first_kind = "sin" if first == uses["lines"]["sin"][0] else "cos"
                second_kind = "cos" if first_kind == "sin" else "sin"
                s_, c_ = f"sim_s{pairs}", f"sim_c{pairs}"
                pairs += 1
                lines[first] = (f"{f_indent}casadi_real {s_}, {c_}; sim_sincos({arg}, &{s_}, "
                                f"&{c_}); {f_target}={s_ if first_kind == 'sin' else c_};")
                lines[second] = (f"{s_indent}{s_target}="
                                 f"{s_ if second_kind == 'sin' else c_};")
        assign = _ASSIGN.match(line)
        if assign:
            version[assign.group(1)] = version.get(assign.group(1), 0) + 1
    for i, line in enumerate(lines):  # the lone ones
        trig = _TRIG.match(line)
        if trig:
            indent, target, kind, arg = trig.groups()
            lines[i] = f"{indent}{target}=sim_{kind}({arg});"
    out = "\n".join(lines)
    if re.search(r"\b(sin|cos|sincos)\(", out):
        raise RuntimeError("inline_trig: a sin or cos of something other than a variable")
    return out


_DIVISION = re.compile(r"^(\s*)(a\d+)=\((a\d+)/(a\d+)\);$")


def shared_reciprocals(text: str) -> str:
    """CasADi's C of straight-line functions with the divisions by one value of a variable
    (between two of its assignments), where there are several, turned into multiplications by
    its reciprocal, formed once at the first: each quotient then differs from the division's
    by an ulp at most (the ABA's articulated inertia divides three times a stage)."""
    lines = text.split("\n")
    version: dict[str, int] = {}
    uses: dict[tuple[int, str, int], list[int]] = {}  # (function, divisor, its version)
    function = 0
    for i, line in enumerate(lines):
        if line.startswith("static ") or line.startswith("}"):
            version, function = {}, function + 1
            continue
        division = _DIVISION.match(line)
        if division:
            divisor = division.group(4)
            uses.setdefault((function, divisor, version.get(divisor, 0)), []).append(i)
        assign = _ASSIGN.match(line)
        if assign:
            version[assign.group(1)] = version.get(assign.group(1), 0) + 1
    count = 0
    for at in uses.values():
        if len(at) < 2:
            continue
        name = f"sim_r{count}"
        count += 1
        for j, i in enumerate(at):
            indent, target, numerator, divisor = _DIVISION.match(lines[i]).groups()
            first = f"casadi_real {name} = 1. / {divisor}; " if j == 0 else ""
            lines[i] = f"{indent}{first}{target}=({numerator}*{name});"
    return "\n".join(lines)


def renamed(f: ca.Function, name: str) -> ca.Function:
    """``f`` (one input, one output) as a Function ``name`` of the same expression (SX)."""
    x = ca.SX.sym(f.name_in(0), f.size1_in(0))
    return ca.Function(name, [x], [f(x)], [f.name_in(0)], [f.name_out(0)])


def plant_source(plants: list[ca.Function], title: str, trig: bool = False) -> str:
    """The C source of the specialised plants (CasADi's calling convention, no work memory),
    unused parameters marked as generated_c/'s are. ``trig``: sin and cos from sim_sincos
    (:func:`inline_trig`) instead of libm, and repeated divisions by one value as one
    reciprocal (:func:`shared_reciprocals`): within an ulp per operation, not bit for bit."""
    gen = ca.CodeGenerator("sim_plant.c", {"with_header": False, "verbose": False,
                                           "casadi_real": "double"})
    for f in plants:
        gen.add(f)
    text = gen.dump()
    for f in plants:
        work = _work_sizes(text, f.name())
        if work["iw"] or work["w"] or work["arg"] > 6 or work["res"] != f.n_out():
            raise RuntimeError(f"{f.name()} needs work memory ({work}): simulate.c passes none")
    text = _mark_unused_parameters(text)
    if trig:
        text = ('#include "sim_trig.h" /* sim_sincos: sin and cos inline */\n'
                + shared_reciprocals(inline_trig(text)))
    return f"/* {title} */\n" + text


def stage_plant_c(plant: str, nx: int) -> str:
    """The C of ``plant``, a unit's plant period: ``<plant>_stages`` (its RK4 stages' sines and
    cosines shifted from the first stage's, :mod:`cochlea.robots.stage_trig`), or
    ``<plant>_plain`` where a stage's offset is past the shift's reach (``far``: a joint
    faster than the series are exact for). Both are in sim_plant.c (:func:`plant_source`)."""
    return f"""
/* {plant}: the unit's plant period, its later RK4 stages' sines and cosines shifted from the
 * first's ({plant}_stages); the plain period ({plant}_plain) where an offset is past the
 * shift's reach (cochlea/robots/stage_trig.py) */
int {plant}(const double **arg, double **res, long long int *iw, double *w, int mem) {{
  double next[{nx}], far = 0.0;
  double *out[2];
  int code, i;
  out[0] = next;
  out[1] = &far;
  code = {plant}_stages(arg, out, iw, w, mem);
  if (code != 0 || far != 0.0) return code != 0 ? code : {plant}_plain(arg, res, iw, w, mem);
  for (i = 0; i < {nx}; ++i) res[0][i] = next[i];
  return 0;
}}
"""


def sim_scenario_header(name: str | Path, lib: ckernels.Library | None = None,
                        generated: Path = GENERATED) -> tuple[str, str, list[str]]:
    """``sim_scenario.h`` of scenario ``name`` for embedded/sim/simulate.c, ``sim_plant.c``
    (each unit's plant specialised to the scenario: :func:`specialised_plant`) and the groups of
    generated_c/ its pose kernels are in.

    The kernels are the ones ``cochlea.sim.simulate`` runs for the scenario (found and checked
    against the setups by :func:`cochlea.sim.compiled.unit_kernels`); the data are the setups'
    (initial state, plant parameters, friction, grids), written as literals that round-trip."""
    lib = lib or ckernels.load()
    sc = sim_scenario(name)
    name = sc.name
    setups = unit_setups(sc)
    if sc.plant.noise_q_std or sc.plant.noise_qd_std:
        raise RuntimeError(f"{name}: simulate.c has no measurement noise")
    upper = name.upper()
    lines = [f"/* Scenario {name} for embedded/sim/simulate.c (see embedded/sim/sim.h).",
             " * Written by bench/embedded_bench.py from cochlea.sim.unit_setups: do not edit. "
             "SI units. */",
             "#ifndef SIM_SCENARIO_H", "#define SIM_SCENARIO_H", "",
             '#include "sim.h"', f'#include "{name}.h"']
    groups, body, table, plants = [], [], [], []
    shifted = []  # (plant, its state's size): periods with shifted stage trig (stage_plant_c)
    n_pose, n_plant, sizes = 0, 0, []
    trig = inline_trig_applies(sc, setups)
    for u in setups:
        kernels = csim.unit_kernels(lib, u, sc.plant_substeps)
        loop = lib.manifest["closed_loops"][kernels.closed_loop]
        plant, plant_group = _kernel_source(lib, kernels.plant, generated)
        if u.gearbox:
            # The geared plant keeps its general kernel: folded, its constants moved results by
            # an ulp (6.7e-16), which backlash and stiction made 1e-2 rad over a study.
            declare = []
            groups += [] if plant_group in groups else [plant_group]
        else:
            plant = f"sim_{u.name}_plant"
            stages = specialised_plant(u, sc.plant_substeps, sc.period, f"{plant}_stages",
                                       stage_trig=True) if STAGE_TRIG else None
            if stages is None:
                plants.append(specialised_plant(u, sc.plant_substeps, sc.period, plant))
            else:
                plants.append(specialised_plant(u, sc.plant_substeps, sc.period,
                                                f"{plant}_plain"))
                plants.append(stages)
                shifted.append((plant, len(u.plant_x0)))
            declare = [f"int {plant}(const double **arg, double **res, long long int *iw, "
                       "double *w, int mem); /* sim_plant.c */"]
        pose, pose_group = _kernel_source(lib, kernels.pose, generated)
        if trig:  # the log's pose with sim_sincos too (the writer thread's largest part)
            pose = f"sim_{u.name}_pose"
            plants.append(renamed(u.fk_world, pose))
            declare = [*declare, f"int {pose}(const double **arg, double **res, long long int "
                       "*iw, double *w, int mem); /* sim_plant.c */"]
        else:
            groups += [] if pose_group in groups else [pose_group]
        n = u.controller_model.nq
        nd, np_, ne = u.controller.n_desired, u.controller.n_params, loop["n_errors"]
        n_pose += loop["n_pose"]
        unit = f"{upper}_{u.name.upper()}"
        sizes += [f"{unit}_NQ == {n}", f"{unit}_NP == {np_}", f"{unit}_ND == {nd}",
                  f"{unit}_NE == {ne}"]
        prefix = f"sim_{u.name}"
        body += [f"/* {u.name}: plant {kernels.plant} (runs {plant}), pose {kernels.pose} "
                 f"(runs {pose}) */",
                 *declare,
                 _c_array(f"{prefix}_x0", u.plant_x0),
                 _c_array(f"{prefix}_plant_p", u.plant_params),
                 _c_array(f"{prefix}_friction", u.friction)]
        fields = {"coulomb": u.drive, "quantum": u.quantum, "offset": u.grid_offset,
                  "effort_quantum": None if u.effort_grid is None else u.effort_grid.quantum,
                  "effort_bound": None if u.effort_grid is None else u.effort_grid.bound,
                  "effort_offset": None if u.effort_grid is None else u.effort_grid.offset,
                  "effort_ramp": None if u.effort_grid is None else u.effort_grid.ramp,
                  "torque_scale": u.torque_scale}
        names = {}
        for key, value in fields.items():
            if value is None:
                names[key] = "NULL"
            else:
                body.append(_c_array(f"{prefix}_{key}", value))
                names[key] = f"{prefix}_{key}"
        table.append(
            f'    {{"{u.name}", {n}, {len(u.plant_x0)}, {np_}, {nd}, {ne}, {loop["n_pose"]}, '
            f"{plant}, {pose}, {prefix}_x0, {prefix}_plant_p, {prefix}_friction, "
            f"{names['coulomb']}, {names['quantum']}, {names['offset']}, "
            f"{names['effort_quantum']}, {names['effort_bound']}, {names['effort_offset']}, "
            f"{names['effort_ramp']}, {names['torque_scale']}}},")
        n_plant += len(u.plant_x0)
    lines += [f'#include "{g}.h"' for g in groups]
    lines += ["", f'#define SIM_NAME "{name}"', f"#define SIM_C(x) {name}##x",
              f'#define SIM_CONTROLLER_SOURCE "{name}.c" /* compiled into simulate.c */']
    for size in ("UNITS", "NQ", "NX", "ND", "NP", "NE"):
        lines.append(f"#define SIM_{size} {upper}_{size}")
    lines += [f"#define SIM_NPOSE {n_pose}",
              f"#define SIM_NXP {n_plant} /* the plants' states */",
              f"#define SIM_PERIOD {sc.period!r} /* s */",
              f"#define SIM_DURATION {float(sc.duration)!r} /* s */",
              f"#define SIM_DELAY {int(sc.plant.delay_periods)} /* periods */",
              f"#define SIM_JITTER {int(sc.plant.delay_jitter_periods)} /* periods */",
              f"#define SIM_ENCODER_COUNTS {int(sc.plant.encoder_noise_counts)} /* counts */",
              f"#define SIM_INLINE_TRIG {int(trig)} /* 1: sin and cos from sim_trig.h */",
              *_stream_seeds(sc.plant),
              "",
              "/* The controller's sizes are the setups' (a negative array size otherwise). */",
              f"typedef char sim_sizes_agree[({' && '.join(sizes)} && {upper}_UNITS == "
              f"{len(setups)}) ? 1 : -1];", ""]
    lines += body
    lines += ["", "static const sim_unit sim_units[SIM_UNITS] = {", *table, "};", "",
              "#endif", ""]
    source = plant_source(plants, f"Scenario {name}: each unit's plant period with the "
                          "scenario's constants folded in (embedded/sim/sim.h). Written by "
                          "bench/embedded_bench.py from cochlea.sim.unit_setups: do not edit.",
                          trig=trig)
    source += "".join(stage_plant_c(plant, nx) for plant, nx in shifted)
    return "\n".join(lines), source, groups


def build_simulation(name: str | Path, precision: str = "double",
                     lib: ckernels.Library | None = None, generated: Path = GENERATED) -> Path:
    """The all-in-C simulation of scenario ``name``: ``build/embedded-sim/<name>/<precision>/
    simulate`` (rebuilt when its scenario header, a source or the flags change).

    A user's scenario (docs/codegen.md): ``name`` its file, ``generated`` the folder
    ``cochlea-codegen --scenario FILE --out DIR --embedded`` wrote (its plant kernels and
    ``embedded/``), ``lib`` its library; the program is ``DIR/embedded-sim/<scenario>/
    <precision>/simulate``."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision: one of {PRECISIONS}")
    header, plant, groups = sim_scenario_header(name, lib, generated)
    sc = sim_scenario(name)
    name = sc.name
    isa = host_isa_flags(sc, unit_setups(sc))
    embedded = generated / "embedded"
    folder = (BUILD if generated == GENERATED else generated / "embedded-sim") / name / precision
    folder.mkdir(parents=True, exist_ok=True)
    for file, text in (("sim_scenario.h", header), ("sim_plant.c", plant)):
        path = folder / file
        if not path.exists() or path.read_text() != text:
            partial = folder / f".{file}.{os.getpid()}"
            partial.write_text(text)
            os.replace(partial, path)
    flags = CFLAGS + isa + (FLOAT_FLAGS if precision == "float" else ())
    include = (SIM_SOURCE, embedded, generated)
    # The controller is compiled into simulate.c (SIM_CONTROLLER_SOURCE): the loop calls its
    # step on the desired sample it evaluated once for the step and the log.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        jobs = [pool.submit(_object, generated / f"{g}.c", CFLAGS + isa) for g in groups]
        # GENERATED: sim_trig.h includes its cochlea_trig.h (the cache key reads its headers)
        jobs.append(pool.submit(_object, folder / "sim_plant.c", CFLAGS + isa,
                                (SIM_SOURCE, GENERATED)))
        jobs.append(pool.submit(_object, SIM_SOURCE / "simulate.c", (*flags, "-Wconversion"),
                                (folder, *include), (embedded / f"{name}.c",)))
        objects = [j.result() for j in jobs]
    binary = folder / "simulate"
    key = _digest([o.name for o in objects], LINK_FLAGS)
    stamp = folder / "simulate.key"
    if not binary.exists() or not stamp.exists() or stamp.read_text() != key:
        partial = folder / f".simulate.{os.getpid()}"
        try:
            _run_cc([compiler(), *map(str, objects), *LINK_FLAGS, "-o", str(partial)])
        except RuntimeError:  # no static C library here: linked as usual
            _run_cc([compiler(), *map(str, objects), "-pthread", "-lm", "-o", str(partial)])
        os.replace(partial, binary)
        stamp.write_text(key)
    return binary


def run_simulation(binary: Path, duration: float | None = None,
                   log: Path | None = None) -> dict:
    """Run a built simulation; its JSON summary (``status``, ``rows``, ``loop_s``, ...)."""
    command = [str(binary)]
    if duration is not None:
        command += ["--duration", repr(float(duration))]
    if log is not None:
        command += ["--log", str(log)]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode == 2:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr}")
    return json.loads(done.stdout)


def read_log(path: Path, info: dict, sc, setups) -> SimulationResult:
    """The log of :func:`run_simulation` as a :class:`SimulationResult` (what
    ``cochlea.sim.simulate`` returns), one UnitLog per unit."""
    data = np.fromfile(path, dtype=np.float64).reshape(-1, info["columns"])
    assert len(data) == info["rows"]
    blocks, start = {}, 0
    for key, width in (("t", 1), ("x", info["nx"]), ("p_hat", info["np"]), ("tau", info["nq"]),
                       ("errors", info["ne"]), ("pose", info["npose"]), ("xd", info["nd"]),
                       ("xd_dot", info["nd"])):
        blocks[key] = data[:, start:start + width]
        start += width
    logs, at = [], dict.fromkeys(("x", "p_hat", "tau", "errors", "pose", "xd", "xd_dot"), 0)
    ages = delay_ages(sc.plant, len(data))
    delay = sc.plant.delay_periods if ages is None else ages
    counts = encoder_noise(sc.plant, len(data), setups)
    for u, size in zip(setups, info["unit_sizes"], strict=True):
        assert size["name"] == u.name
        n = size["nq"]
        part = {}
        for key, width in (("x", 2 * n), ("p_hat", size["np"]), ("tau", n),
                           ("errors", size["ne"]), ("pose", size["npose"]), ("xd", size["nd"]),
                           ("xd_dot", size["nd"])):
            part[key] = blocks[key][:, at[key]:at[key] + width]
            at[key] += width
        # The program logs the plant's true state and pose; what its controller measured is
        # that state delayed (each period's jitter drawn again), its encoder counts of noise
        # added, and on the grids (the program refuses Gaussian noise).
        x = part["x"]
        seen = measurements(x, delay, None if counts[len(logs)] is None else
                            np.hstack([counts[len(logs)], np.zeros_like(counts[len(logs)])]),
                            u.quantum, u.grid_offset)
        logs.append(simulated_log(u, sc.space, x, seen, part["pose"], part["xd"],
                                  part["xd_dot"], part["errors"], part["tau"], part["p_hat"]))
    diverged = {}
    if info["status"] == "diverged":
        diverged = {u.name: float(blocks["t"][-1, 0]) for u in setups}
    return SimulationResult(sc, blocks["t"][:, 0].copy(), logs, diverged)


def max_log_difference(a: SimulationResult, b: SimulationResult) -> float:
    """The largest absolute difference of any logged value (same rows)."""
    worst = 0.0
    for u, r in zip(a.units, b.units):
        for key in LOG_FIELDS:
            x, y = getattr(u, key), getattr(r, key)
            worst = max(worst, float(np.max(np.abs(x - y))) if x.size else 0.0)
    return worst


# --------------------------------------------------------------------------------------------
# 1. The step in double and in float
# --------------------------------------------------------------------------------------------


def build_step_library(name: str, precision: str) -> Path:
    """``build/embedded-sim/<name>/<precision>/libtime_step.so``: the scenario's controller and
    bench/time_embedded_step.c (symbols bound inside the library, so two precisions can share
    one process)."""
    flags = (*CFLAGS, *(FLOAT_FLAGS if precision == "float" else ()), "-fPIC", "-shared",
             "-Wl,-Bsymbolic", f"-DSCENARIO_HEADER=\"{name}.h\"", f"-DSCENARIO={name}",
             f"-DSCENARIO_UPPER={name.upper()}", f"-I{EMBEDDED}")
    sources = (HARNESS, EMBEDDED / f"{name}.c", EMBEDDED / f"{name}.h")
    key = _digest(compiler(), flags, [s.read_text() for s in sources])
    folder = BUILD / name / precision
    library = folder / f"libtime_step-{key}.so"
    if not library.exists():
        folder.mkdir(parents=True, exist_ok=True)
        partial = folder / f".{library.name}.{os.getpid()}"
        _run_cc([compiler(), *flags, str(HARNESS), str(EMBEDDED / f"{name}.c"), "-lm", "-o",
                 str(partial)])
        os.replace(partial, library)
    return library


def recorded_measurements(name: str, periods: int = REPLAY_PERIODS):
    """What the simulation's controller measured over the first ``periods`` (delayed and on the
    measurement grid as the scenario says), unit after unit: ``(times (s), measurements
    (periods, NX), applied commands (periods, NQ), setups)``."""
    sc = sim_scenario(name)
    setups = unit_setups(sc)
    result = simulate(sc, duration=periods * sc.period, setups=setups)
    # The log's measured state: what the controller saw (delayed, on the grids).
    seen = [np.hstack([u.q, u.qd]) for u in result.units]
    return (result.time.copy(), np.ascontiguousarray(np.hstack(seen)),
            np.hstack([u.tau for u in result.units]), setups)


class StepLibrary:
    """One precision's timing library, loaded through ctypes."""

    def __init__(self, path: Path):
        self.lib = ctypes.CDLL(str(path))
        sizes = np.zeros(3, np.intc)
        self.real_bytes = self.lib.bench_sizes(sizes.ctypes.data_as(ctypes.c_void_p))
        self.nx, self.nq, self.ne = map(int, sizes)
        self.lib.bench_time.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_long,
                                        ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]

    def time(self, times: np.ndarray, measurements: np.ndarray, reps: int):
        """``(ns per step of each repetition, the commands of the run)``."""
        ns = np.zeros(reps)
        commands = np.zeros((len(times), self.nq))
        code = self.lib.bench_time(times.ctypes.data, measurements.ctypes.data, len(times), reps,
                                   ns.ctypes.data, commands.ctypes.data)
        if code:
            raise RuntimeError(f"bench_time returned {code}")
        return ns, commands


def python_period_cost(name: str, periods: int = 2000) -> float:
    """The Python real-time loop's controller work per period (s, median): ``RealTimeLoop`` as
    fast as possible on the sim backend, each period's compute time less the backend's read and
    write (what is left: the supervisor's checks, every unit's step through ctypes, the
    copies); a geared study that stops early is timed on its preset before the gearbox (the
    same controller, supervisor and copies)."""
    from cochlea.runtime.loop import RealTimeLoop
    from cochlea.runtime.sim_backend import SimBackend
    from cochlea.runtime.supervisor import build_supervisor

    sc = load_scenario(name)
    for attempt in range(2):
        setups = unit_setups(sc)
        backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant,
                             steps=periods)
        supervisor = build_supervisor(setups, sc.system.keep_out_radius,
                                      substeps=sc.plant_substeps)
        loop = RealTimeLoop(setups, backend, supervisor, sc.period, periods, realtime=False,
                            substeps=sc.plant_substeps)
        stop = loop.run()
        if stop.rule == "completed" or not sc.plant.gearbox or attempt:
            break
        # The serial realistic studies stop on the velocity limit within 30 ms on the geared
        # plant (docs/robustness.md): the controller's work per period is the same on the
        # preset before the gearbox, where they run their length (the backend's I/O, the only
        # part the plant changes, is subtracted anyway).
        sc = dataclasses.replace(sc, plant=dataclasses.replace(
            sc.plant, gearbox=False, static_friction_ratio=1.0))
    if stop.rule != "completed" or loop.kernel_source != "c":
        raise RuntimeError(f"{name}: the Python loop stopped ({stop.rule}) or ran "
                           f"{loop.kernel_source} kernels")
    timing = loop.result(sc).timing
    return float(np.median(timing["compute_s"] - timing["backend_io_s"]))


def bench_embedded_steps(rounds: int = 15, reps: int = 7) -> list[dict]:
    """Per scenario: ns per ``<scenario>_step`` in double and in float (the two libraries
    timed turn about in this process, ``rounds`` x ``reps`` repetitions of REPLAY_PERIODS
    steps each, medians), their ratio, the checks, and the Python loop's cost per period."""
    rows = []
    for name in SCENARIOS:
        times, measured, applied, setups = recorded_measurements(name)
        libs = {p: StepLibrary(build_step_library(name, p)) for p in PRECISIONS}
        samples = {p: [] for p in PRECISIONS}
        commands = {}
        gc.disable()
        try:
            for r in range(rounds):
                order = PRECISIONS if r % 2 == 0 else PRECISIONS[::-1]
                for p in order:
                    ns, commands[p] = libs[p].time(times, measured, reps)
                    samples[p].extend(ns)
        finally:
            gc.enable()
        # The double build's commands, applied as the drives apply them, are the simulation's.
        start, drive = 0, commands["double"].copy()
        for u in setups:
            n = u.controller_model.nq
            if u.effort_grid is not None:
                for row in drive[:, start:start + n]:
                    u.effort_grid.apply(row)
            start += n
        peak = float(np.max(np.abs(commands["double"])))
        row = {"scenario": name, "periods": len(times), "units": len(setups),
               "double_ns": statistics.median(samples["double"]),
               "float_ns": statistics.median(samples["float"]),
               "check_double": float(np.max(np.abs(drive - applied))),
               "float_vs_double": float(np.max(np.abs(commands["float"] - commands["double"]))
                                        / peak),
               "python_period_s": python_period_cost(name)}
        row["float_over_double"] = row["float_ns"] / row["double_ns"]
        row["python_over_double"] = row["python_period_s"] * 1e9 / row["double_ns"]
        rows.append(row)
        print(f"  {name}: step {row['double_ns']:.0f} ns double, {row['float_ns']:.0f} ns "
              f"float ({row['float_over_double']:.2f}x); Python loop "
              f"{row['python_period_s'] * 1e6:.1f} us per period", flush=True)
    return rows


# --------------------------------------------------------------------------------------------
# 2. The all-in-C simulation, end to end
# --------------------------------------------------------------------------------------------


def _timed_run(command: list[str]) -> tuple[float, dict]:
    """Wall time (s) from starting the process to its exit, and its summary. A log the command
    writes over the previous run's is replaced by the program itself (simulate.c's open_log:
    removed, a new file written), inside the time, as a user's second run pays it."""
    t0 = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} exited {done.returncode}:\n{done.stderr}")
    return wall, json.loads(done.stdout)


#: The program :func:`sibling_slowdown` times: one unit, so one thread.
SIBLING_PROGRAM = "parallel_joint"


def _idle_us(cpu: int) -> float | None:
    """Microseconds CPU ``cpu`` has spent idle (its cpuidle states' residency), None where the
    kernel does not say."""
    states = sorted(Path(f"/sys/devices/system/cpu/cpu{cpu}/cpuidle").glob("state*/time"))
    try:
        return float(sum(int(t.read_text()) for t in states)) if states else None
    except OSError:
        return None


def sibling_slowdown(rounds: int = 9, runs: int = 3, program: str = SIBLING_PROGRAM) -> dict:
    """How much a unit thread's work slows when the machine's other vCPU is busy, in one run:
    ``program``'s all-in-C simulation (one thread, no log) pinned to the first CPU this
    process may use, its loop's CPU time alone and while a busy loop (``sh -c 'while :; do :;
    done'``) runs pinned to the second; ``rounds`` rounds turn about of ``runs`` runs each.
    Where the two vCPUs are one physical core's two hardware threads the ratio is well above
    1: two threads on "2 cores" do not get twice one's work done.

    Other work on the machine may keep the second CPU busy during the runs "alone": each run's
    share of idle time on that CPU is taken (cpuidle residency); the runs alone are those with
    it at least 90 % idle where there are ``runs`` such, else all of them, and
    ``other_idle_alone`` (the median share) says how alone they were. Returns the medians (s),
    their ratio (``ratio``: busy / alone) and the CPUs."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise RuntimeError(f"sibling_slowdown needs two CPUs, this process may use {cpus}")
    first, second = cpus[:2]
    command = [str(build_simulation(program))]
    alone, busy = [], []  # (loop CPU s, the other CPU's idle share over the run)

    def timed() -> tuple[float, float]:
        idle0, t0 = _idle_us(second), time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True,
                              preexec_fn=lambda: os.sched_setaffinity(0, {first}))
        wall_us, idle1 = (time.perf_counter() - t0) * 1e6, _idle_us(second)
        if done.returncode != 0:
            raise RuntimeError(f"{command[0]} exited {done.returncode}: {done.stderr.strip()}")
        share = float("nan") if idle0 is None else min(1.0, (idle1 - idle0) / wall_us)
        return float(json.loads(done.stdout)["loop_cpu_s"]), share

    timed()  # warm up: page cache, CPU frequency
    for _ in range(rounds):
        alone += [timed() for _ in range(runs)]
        spinner = subprocess.Popen(["sh", "-c", "while :; do :; done"],
                                   preexec_fn=lambda: os.sched_setaffinity(0, {second}))
        try:
            time.sleep(0.05)  # the loop running on its CPU
            busy += [timed() for _ in range(runs)]
        finally:
            spinner.kill()
            spinner.wait()
    quiet = [c for c, share in alone if share >= 0.9]
    row = {"program": program, "cpus": [first, second], "runs": len(alone),
           "alone_quiet_runs": len(quiet) if len(quiet) >= runs else 0,
           "alone_cpu_s": statistics.median(quiet if len(quiet) >= runs
                                            else [c for c, _ in alone]),
           "busy_cpu_s": statistics.median(c for c, _ in busy),
           "other_idle_alone": statistics.median(share for _, share in alone),
           "other_idle_busy": statistics.median(share for _, share in busy)}
    row["ratio"] = row["busy_cpu_s"] / row["alone_cpu_s"]
    return row


def bench_embedded_sims(runs: int = 11) -> list[dict]:
    """Per scenario, full length: the all-in-C simulation's log against ``simulate()``'s (the
    largest difference of any logged value, double and float builds), then ``runs`` timed runs
    of each variant in turn -- double with its log written, double without a log, float with
    its log -- as wall time from process start to exit (medians), and the loop's own time."""
    rows = []
    work = BUILD / "bench"
    work.mkdir(parents=True, exist_ok=True)
    try:  # the machine's fact the serial rows' why-lines quote
        sibling = sibling_slowdown()
    except (RuntimeError, OSError, subprocess.SubprocessError) as error:
        sibling = {"not_run": f"{type(error).__name__}: {error}"}
    print(f"  a thread beside a busy vCPU: {sibling.get('ratio', 0):.2f}x its CPU time alone",
          flush=True)
    for name in SCENARIOS:
        sc = sim_scenario(name)
        setups = unit_setups(sc)
        binaries = {p: build_simulation(name, p) for p in PRECISIONS}
        log = work / f"{name}.log"
        reference = simulate(sc, setups=setups)
        row = {"scenario": name, "duration_s": float(sc.duration), "units": len(setups),
               "periods": len(reference.time), "delay_periods": int(sc.plant.delay_periods),
               "robot": sc.robot, "gearbox": any(bool(u.gearbox) for u in setups),
               "plant_substeps": int(sc.plant_substeps)}
        for p, binary in binaries.items():
            info = run_simulation(binary, log=log)
            result = read_log(log, info, sc, setups)
            if info["status"] != "completed" or len(result.time) != len(reference.time):
                raise RuntimeError(f"{name} ({p}): {info['status']} after {info['rows']} rows")
            row[f"max_diff_{p}"] = max_log_difference(result, reference)
            row["log_bytes"] = log.stat().st_size
            row["log_writer"] = info.get("log_writer", "thread")
        variants = {"double": [str(binaries["double"]), "--log", str(log)],
                    "double_no_log": [str(binaries["double"])],
                    "float": [str(binaries["float"]), "--log", str(log)]}
        walls = {v: [] for v in variants}
        loops = {v: [] for v in variants}
        cpus = {v: [] for v in variants}
        for command in variants.values():  # warm up: page cache, CPU frequency
            _timed_run(command)
        for _ in range(runs):
            for v, command in variants.items():
                wall, info = _timed_run(command)
                walls[v].append(wall)
                loops[v].append(info["loop_s"])
                cpus[v].append(info["loop_cpu_s"])
        log.unlink(missing_ok=True)
        for v in variants:
            row[f"wall_{v}_s"] = statistics.median(walls[v])
            row[f"loop_{v}_s"] = statistics.median(loops[v])
            # the loop's thread's CPU time: its work, when other work shares the machine
            row[f"loop_cpu_{v}_s"] = statistics.median(cpus[v])
            row[f"rtf_{v}"] = row["duration_s"] / row[f"wall_{v}_s"]
        row["rtf_loop_double"] = row["duration_s"] / row["loop_double_s"]
        row["threads"] = info["threads"]  # the units' threads (one per unit)
        row["sibling"] = sibling
        row["startup_s"] = row["wall_double_no_log_s"] - row["loop_double_no_log_s"]
        rows.append(row)
        print(f"  {name}: all-in-C {row['rtf_double']:.0f}x real time end to end (no log "
              f"{row['rtf_double_no_log']:.0f}x, float {row['rtf_float']:.0f}x); max diff "
              f"{row['max_diff_double']:.1e} (float {row['max_diff_float']:.1e})", flush=True)
    return rows


# --------------------------------------------------------------------------------------------
# Report (bench/run.py writes these into bench/results.md)
# --------------------------------------------------------------------------------------------


def robot(row: dict) -> str:
    """The robot of an all-in-C row, ``serial`` or ``parallel`` (a row before ``robot`` was
    kept: its scenario's name says)."""
    return row.get("robot") or ("serial" if row["scenario"].startswith("serial")
                                else "parallel")


def sim_target(row: dict) -> float:
    """Issue 30's real-time factor for an all-in-C row: 2000x serial, 1000x parallel."""
    return TARGETS[f"embedded_sim_{robot(row)}_rtf"]


def _plant_words(row: dict) -> str:
    """What one unit's plant period is, in words."""
    k = row.get("plant_substeps", 1)
    geared = row.get("gearbox", row["scenario"].endswith("_realistic"))
    if geared:
        return (f"{20 * k} linearly implicit sub-steps of the geared plant (its general "
                "kernel, each sub-step an n x n linear solve)")
    return (f"RK4 plant period ({4 * k} forward-dynamics evaluations, the scenario's constants "
            "folded in)")


def _sibling_words(sibling: dict, threads: int, period: float) -> str:
    """What :func:`sibling_slowdown`'s row says about the unit threads' two vCPUs, for a why-line
    (``period``: the busier thread's CPU time a period, s)."""
    ratio = sibling["ratio"]
    measured = (f"{sibling['program']}'s program pinned to one vCPU took "
                f"{sibling['busy_cpu_s'] * 1e3:.1f} ms of loop CPU time while the other vCPU "
                f"ran a busy loop")
    idle = sibling.get("other_idle_alone", 1.0)
    if idle < 0.9:  # NaN (not known) passes as quiet
        return (f"{measured} and {sibling['alone_cpu_s'] * 1e3:.1f} ms without it, {ratio:.2f}x, "
                f"but the other vCPU was only {idle:.0%} idle in the runs without it (other "
                "work on the machine), so how much the vCPUs slow each other was not measured "
                "in this run")
    words = (f"{measured} and {sibling['alone_cpu_s'] * 1e3:.1f} ms alone: {ratio:.2f}x")
    if ratio < 1.1:
        return words + ", the two vCPUs hardly slow each other"
    return (words + f"; the two vCPUs share one physical core's execution units, so {threads} "
            f"threads get about {2 / ratio:.2f} cores' worth of work done, not 2, and alone on "
            f"the core the period would cost about {period / ratio * 1e6:.2f} us")


def _writer_words(row: dict, threads: int) -> str:
    """Who wrote the row's log (simulate.c's sim_writer), for its why-line."""
    if row.get("log_writer") == "units":
        return ("put together, their poses evaluated and written by the units themselves, "
                "whichever is ahead of the oldest block not written (no third thread on the two "
                "cores; each unit held on its own)")
    return ("handed to the writer thread (which puts the units' rows together, evaluates the "
            f"poses and writes the file: {'a third' if threads > 1 else 'a second'} thread on "
            "the two cores)")


def verdicts(steps: list[dict], sims: list[dict]) -> list[str]:
    """The target lines of the all-in-C rows: each study's real-time factor end to end with
    its log against issue 30's (serial 2000x, parallel 1000x), met, or missed by how much and
    why (the loop's cost a period, its threads, the log's share, the start-up)."""
    lines = []
    by_name = {r["scenario"]: r for r in steps}
    for r in sims:
        rtf, target = r["rtf_double"], sim_target(r)
        head = (f"{r['scenario']} all-in-C simulation (embedded/sim) at {rtf:.0f}x real time "
                "end to end, log written")
        if rtf >= target:
            lines.append(f"- **met**: {head} (target >= {target:g}x).")
            continue
        # The loop's CPU time where the program reports it (other work on the machine stretches
        # its wall time, not its CPU time), its wall time otherwise.
        cpu = "loop_cpu_double_no_log_s" in r
        loop = "loop_cpu_double" if cpu else "loop_double"
        period = r[f"{loop}_no_log_s"] / r["periods"]
        log_period = (r[f"{loop}_s"] - r[f"{loop}_no_log_s"]) / r["periods"]
        threads = r.get("threads", 1)
        plant = _plant_words(r)
        cost = f"{period * 1e6:.2f} us" + (" (its CPU time)" if cpu else "")
        sibling = r.get("sibling") or {}
        if threads > 1:  # a unit a thread: the busier thread's, one unit's work
            why = (f"without a log each period costs {cost} on the busier of its {threads} "
                   f"unit threads: one unit's desired sample, step, {plant} and measurement")
            if "ratio" in sibling:
                why += " (with the other unit's thread on the other vCPU; " + _sibling_words(
                    sibling, threads, period) + ")"
        else:
            why = f"without a log each period costs {cost} in the loop"
            if r["scenario"] in by_name:
                step = by_name[r["scenario"]]["double_ns"] * 1e-9
                units = "the mechanism's" if r["units"] == 1 else f"all {r['units']} units'"
                why += (f": the controller's step {step * 1e6:.2f} us ({units}, the desired "
                        f"trajectory evaluated in C), the rest ({(period - step) * 1e6:.2f} us) "
                        f"the {plant} and the measurement")
            else:
                why += f": the controller's step, the {plant} and the measurement"
        budget = 1e-3 / target  # s of loop a period at the target (h = 1 ms)
        lines.append(
            f"- **missed** by {target / rtf:.2f}x: {head} ({r['rtf_double_no_log']:.0f}x "
            f"without a log; target >= {target:g}x, {budget * 1e6:.2f} us a period). Why: "
            f"{why}, a cap of {1e-3 / period:.0f}x "
            f"{'with a core per unit' if threads > 1 else 'on one core'}. The log adds "
            f"{log_period * 1e6:.2f} us per period to the loop: its rows, "
            f"{r['log_bytes'] / 1e6:.1f} MB {_writer_words(r, threads)}; the process "
            f"start-up {r['startup_s'] * 1e3:.2f} ms.")
    return lines


def markdown(steps: list[dict] | None, sims: list[dict] | None,
             loops: list[dict] | None = None, not_run: dict[str, str] | None = None
             ) -> list[str]:
    """The section of results.md. ``loops``: bench/run.py's closed-loop rows, for the
    real-time factor of ``simulate()``'s all-in-C path on the same scenario. ``steps`` or
    ``sims`` None: those rows were not measured, ``not_run`` (bench/run.py's) says why."""
    not_run = not_run or {}

    def why(section: str) -> list[str]:
        return [f"Not measured in this run: {not_run.get(section, 'no rows')}.", ""]

    out = ["## Embedded controller: the step in double and in float", ""]
    if steps is None:
        out += why("embedded_steps")
    out += [] if steps is None else [
           "Each scenario's generated controller (`generated_c/embedded/<scenario>.c`, -O2) "
           "built twice, as is and with `-DCOCHLEA_FLOAT`, both loaded into the benchmark's "
           "process and timed turn about in C (bench/time_embedded_step.c) on what the "
           f"simulation's controller measured over its first {REPLAY_PERIODS} periods. One "
           "`<scenario>_step` call is every unit's desired trajectory, control law, estimate "
           "update and clip. *Python loop*: the real-time loop's controller work per period on "
           "the same scenario (`RealTimeLoop` as fast as possible on the sim backend, compute "
           "less the backend's read and write: the supervisor's checks, each unit's C step "
           "through ctypes on precomputed desired samples, the copies). *check*: the double "
           "build's commands, applied as the drives apply them, against the simulation's "
           "(largest absolute difference, N m or N); *float*: the float build's commands "
           "against the double build's, relative to the peak command.", "",
           "| scenario | units | double (ns) | float (ns) | float / double | Python loop (us) | "
           "Python / double | check | float |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in steps or []:
        out.append(f"| {r['scenario']} | {r['units']} | {r['double_ns']:.0f} | "
                   f"{r['float_ns']:.0f} | {r['float_over_double']:.2f} | "
                   f"{r['python_period_s'] * 1e6:.1f} | {r['python_over_double']:.0f} | "
                   f"{r['check_double']:.1e} | {r['float_vs_double']:.1e} |")
    c_rtf = {r["scenario"]: r["rtf_c"] for r in loops or []}
    out += ["", "## All-in-C simulation (embedded/sim, real-time factor)", ""]
    if sims is None:
        return out + why("embedded_sims")
    out += ["`embedded/sim/simulate.c` built per scenario (-O2, linked statically): the embedded "
            "controller, which evaluates its desired trajectory in C each period (once, for the "
            "step and the log), and each unit's plant period (RK4, the scenario's sub-steps) "
            "generated with the scenario's constants folded in (the geared plant: its general "
            "kernel), with the scenario's measurement delay and grids; no Python, no CasADi; "
            "each unit on a thread of its own (the serial studies: two); the serial studies' "
            "sin and cos inline (embedded/sim/sim_trig.h, within an ulp of libm). "
            "Full scenario length; wall time from starting the process to its exit (medians of "
            "runs taken turn about), log written (a row of doubles per period, put together "
            "and written by a writer thread, or by the units themselves where they are as many "
            "as the processors: the serial studies here) unless said. *loop*: the program's own "
            "time for "
            "its loop "
            "(log written); *start-up*: process wall time less the loop, without a log; "
            "*simulate()*: the all-in-C path of `cochlea.sim.simulate` on the same scenario, end "
            "to end (its set-up samples the desired trajectory with CasADi; units on threads), "
            "from the closed-loop table above. *max diff*: the largest absolute difference of "
            "any logged value from `simulate()`'s log (double; float build).", "",
            "| scenario | s | units | end to end | no log | loop | float | start-up (ms) | "
            "simulate() | max diff (double / float) |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for r in sims:
        ref = c_rtf.get(r["scenario"])
        out.append(f"| {r['scenario']} | {r['duration_s']:g} | {r['units']} | "
                   f"{r['rtf_double']:.0f}x | {r['rtf_double_no_log']:.0f}x | "
                   f"{r['rtf_loop_double']:.0f}x | {r['rtf_float']:.0f}x | "
                   f"{r['startup_s'] * 1e3:.2f} | "
                   f"{f'{ref:.0f}x' if ref is not None else '-'} | "
                   f"{r['max_diff_double']:.1e} / {r['max_diff_float']:.1e} |")
    out.append("")
    return out


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="build the all-in-C simulations into build/embedded-sim/")
    build.add_argument("scenarios", nargs="*", default=list(SCENARIOS))
    build.add_argument("--kernels", type=Path, metavar="DIR",
                       help="a user's scenario (each SCENARIO a file): the folder "
                            "cochlea-codegen --scenario FILE --out DIR --embedded wrote")
    sub.add_parser("bench", help="run only these rows; write build/embedded-bench.json")
    sub.add_parser("sibling", help="a thread's slowdown while the other vCPU is busy")
    args = parser.parse_args(argv)
    if args.command == "sibling":
        try:
            row = sibling_slowdown()
        except (RuntimeError, OSError, subprocess.SubprocessError) as error:
            print(f"embedded_bench.py: sibling: {error}", file=sys.stderr)
            return 2
        print(f"{row['program']} pinned to CPU {row['cpus'][0]}: loop CPU "
              f"{row['alone_cpu_s'] * 1e3:.2f} ms alone, {row['busy_cpu_s'] * 1e3:.2f} ms with "
              f"CPU {row['cpus'][1]} busy ({row['runs']} runs each, turn about; alone: "
              f"{row['alone_quiet_runs']} runs with CPU {row['cpus'][1]} >= 90 % idle, its "
              f"idle share {row['other_idle_alone']:.0%} alone, {row['other_idle_busy']:.0%} "
              f"busy): {row['ratio']:.2f}x")
        return 0
    if args.command == "build":
        try:
            lib = ckernels.load(args.kernels) if args.kernels is not None else ckernels.load()
            for name in args.scenarios:
                for p in PRECISIONS:
                    print(build_simulation(Path(name) if args.kernels is not None else name, p,
                                           lib, args.kernels or GENERATED))
        except (RuntimeError, ValueError, OSError) as error:  # a compiler's, a setting's
            print(f"embedded_bench.py: build: {error}", file=sys.stderr)
            return 2
        return 0
    lib = ckernels.load()
    print("bench: the embedded step in double and float", flush=True)
    steps = bench_embedded_steps()
    print("bench: the all-in-C simulation", flush=True)
    sims = bench_embedded_sims()
    out = ROOT / "build" / "embedded-bench.json"
    out.write_text(json.dumps({"targets": TARGETS, "embedded_steps": steps,
                               "embedded_sims": sims}, indent=1, sort_keys=True) + "\n")
    print("\n".join(["## Targets", "", *verdicts(steps, sims), "", *markdown(steps, sims)]))
    print(f"bench: wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
