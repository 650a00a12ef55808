"""The all-in-C simulation (embedded/sim/simulate.c): built per scenario, run, its log read.

The program is the scenario's embedded controller (``generated_c/embedded/<scenario>.c``, which
evaluates its own desired trajectory every period) and the units' generated plant kernels
(``generated_c/<group>.c``): one process, no Python and no CasADi. Build the programs with
``python bench/embedded_bench.py build [SCENARIO ...]`` (or ``make embedded-sim``).

A program's scenario is compiled in: :func:`sim_scenario_header` writes its
``sim_scenario.h`` (``embedded/sim/sim.h`` says what it defines) from ``unit_setups`` -- the
plant's parameters, the initial state, the grids -- once, at build time.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from cochlea.kernels import library as ckernels
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, unit_setups
from cochlea.sim.result import SimulationResult, UnitLog

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
#: The targets of these rows (bench/run.py merges them into its TARGETS).
TARGETS = {"embedded_sim_serial_rtf": 2000.0}
#: What the step timing replays: the first second of each scenario (periods).
REPLAY_PERIODS = 1000
#: Fields of a unit's log, compared with the simulation's.
LOG_FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "x")


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


def _object(source: Path, flags: tuple[str, ...], include: tuple[Path, ...] = ()) -> Path:
    """``source`` compiled with ``flags``, cached in build/embedded-sim/obj/ by the compiler,
    the flags and the text of the source and of every header in its include folders."""
    cc = compiler()
    headers = sorted({h for d in (source.parent, *include) for h in Path(d).glob("*.h")})
    key = _digest(cc, flags, source.read_text(), [(h.name, h.read_text()) for h in headers])
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


def _kernel_source(lib: ckernels.Library, kernel: str) -> tuple[str, str]:
    """The C function a library kernel runs and the group (``generated_c/<group>.c``) that
    defines it."""
    symbol = lib.symbol(kernel)
    entry = lib.manifest["kernels"][symbol]
    if entry["work"]["iw"] or entry["work"]["w"]:
        raise RuntimeError(f"{symbol} needs work memory: simulate.c passes none")
    group = entry["group"]
    header = (GENERATED / f"{group}.h").read_text()
    if f"int {symbol}(const casadi_real** arg" not in header:
        raise RuntimeError(f"{symbol} is not declared in generated_c/{group}.h")
    return symbol, group


def sim_scenario_header(name: str, lib: ckernels.Library | None = None) -> tuple[str, list[str]]:
    """``sim_scenario.h`` of scenario ``name`` for embedded/sim/simulate.c, and the groups of
    generated_c/ its plant and pose kernels are in.

    The kernels are the ones ``cochlea.sim.simulate`` runs for the scenario (found and checked
    against the setups by :func:`cochlea.sim.compiled.unit_kernels`); the data are the setups'
    (initial state, plant parameters, friction, grids), written as literals that round-trip."""
    lib = lib or ckernels.load()
    sc = load_scenario(name)
    setups = unit_setups(sc)
    if sc.plant.noise_q_std or sc.plant.noise_qd_std:
        raise RuntimeError(f"{name}: simulate.c has no measurement noise")
    upper = name.upper()
    lines = [f"/* Scenario {name} for embedded/sim/simulate.c (see embedded/sim/sim.h).",
             " * Written by bench/embedded_bench.py from cochlea.sim.unit_setups: do not edit. "
             "SI units. */",
             "#ifndef SIM_SCENARIO_H", "#define SIM_SCENARIO_H", "",
             '#include "sim.h"', f'#include "{name}.h"']
    groups, body, table = [], [], []
    n_pose, sizes = 0, []
    for u in setups:
        kernels = csim.unit_kernels(lib, u, sc.plant_substeps)
        loop = lib.manifest["closed_loops"][kernels.closed_loop]
        plant, plant_group = _kernel_source(lib, kernels.plant)
        pose, pose_group = _kernel_source(lib, kernels.pose)
        for g in (plant_group, pose_group):
            if g not in groups:
                groups.append(g)
        n = u.controller_model.nq
        nd, np_, ne = u.controller.n_desired, u.controller.n_params, loop["n_errors"]
        n_pose += loop["n_pose"]
        unit = f"{upper}_{u.name.upper()}"
        sizes += [f"{unit}_NQ == {n}", f"{unit}_NP == {np_}", f"{unit}_ND == {nd}",
                  f"{unit}_NE == {ne}"]
        prefix = f"sim_{u.name}"
        body += [f"/* {u.name}: plant {kernels.plant} (runs {plant}), pose {kernels.pose} */",
                 _c_array(f"{prefix}_x0", u.x0),
                 _c_array(f"{prefix}_plant_p", u.plant_params),
                 _c_array(f"{prefix}_friction", u.friction)]
        fields = {"coulomb": u.coulomb, "quantum": u.quantum, "offset": u.grid_offset,
                  "effort_quantum": None if u.effort_grid is None else u.effort_grid.quantum,
                  "effort_bound": None if u.effort_grid is None else u.effort_grid.bound}
        names = {}
        for key, value in fields.items():
            if value is None:
                names[key] = "NULL"
            else:
                body.append(_c_array(f"{prefix}_{key}", value))
                names[key] = f"{prefix}_{key}"
        table.append(
            f'    {{"{u.name}", {n}, {np_}, {nd}, {ne}, {loop["n_pose"]}, {plant}, '
            f"{pose}, {prefix}_x0, {prefix}_plant_p, {prefix}_friction, {names['coulomb']}, "
            f"{names['quantum']}, {names['offset']}, {names['effort_quantum']}, "
            f"{names['effort_bound']}}},")
    lines += [f'#include "{g}.h"' for g in groups]
    lines += ["", f'#define SIM_NAME "{name}"', f"#define SIM_C(x) {name}##x"]
    for size in ("UNITS", "NQ", "NX", "ND", "NP", "NE"):
        lines.append(f"#define SIM_{size} {upper}_{size}")
    lines += [f"#define SIM_NPOSE {n_pose}",
              f"#define SIM_PERIOD {sc.period!r} /* s */",
              f"#define SIM_DURATION {float(sc.duration)!r} /* s */",
              f"#define SIM_DELAY {int(sc.plant.delay_periods)} /* periods */",
              "",
              "/* The controller's sizes are the setups' (a negative array size otherwise). */",
              f"typedef char sim_sizes_agree[({' && '.join(sizes)} && {upper}_UNITS == "
              f"{len(setups)}) ? 1 : -1];", ""]
    lines += body
    lines += ["", "static const sim_unit sim_units[SIM_UNITS] = {", *table, "};", "",
              "#endif", ""]
    return "\n".join(lines), groups


def build_simulation(name: str, precision: str = "double",
                     lib: ckernels.Library | None = None) -> Path:
    """The all-in-C simulation of scenario ``name``: ``build/embedded-sim/<name>/<precision>/
    simulate`` (rebuilt when its scenario header, a source or the flags change)."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision: one of {PRECISIONS}")
    header, groups = sim_scenario_header(name, lib)
    folder = BUILD / name / precision
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "sim_scenario.h"
    if not path.exists() or path.read_text() != header:
        partial = folder / f".sim_scenario.h.{os.getpid()}"
        partial.write_text(header)
        os.replace(partial, path)
    flags = CFLAGS + (FLOAT_FLAGS if precision == "float" else ())
    include = (SIM_SOURCE, EMBEDDED, GENERATED)
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 2) as pool:
        jobs = [pool.submit(_object, GENERATED / f"{g}.c", CFLAGS) for g in groups]
        jobs.append(pool.submit(_object, EMBEDDED / f"{name}.c", flags))
        jobs.append(pool.submit(_object, SIM_SOURCE / "simulate.c", (*flags, "-Wconversion"),
                                (folder, *include)))
        objects = [j.result() for j in jobs]
    binary = folder / "simulate"
    key = _digest([o.name for o in objects])
    stamp = folder / "simulate.key"
    if not binary.exists() or not stamp.exists() or stamp.read_text() != key:
        partial = folder / f".simulate.{os.getpid()}"
        _run_cc([compiler(), *map(str, objects), "-lm", "-o", str(partial)])
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
    for u, size in zip(setups, info["unit_sizes"], strict=True):
        assert size["name"] == u.name
        n = size["nq"]
        part = {}
        for key, width in (("x", 2 * n), ("p_hat", size["np"]), ("tau", n),
                           ("errors", size["ne"]), ("pose", size["npose"]), ("xd", size["nd"]),
                           ("xd_dot", size["nd"])):
            part[key] = blocks[key][:, at[key]:at[key] + width]
            at[key] += width
        x = part["x"]
        logs.append(UnitLog(u.name, sc.space, x[:, :n], x[:, n:], part["xd"], part["xd_dot"],
                            part["errors"], part["tau"], part["p_hat"], part["pose"], u))
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
# Command line
# --------------------------------------------------------------------------------------------


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    build = sub.add_parser("build", help="build the all-in-C simulations into build/embedded-sim/")
    build.add_argument("scenarios", nargs="*", default=list(SCENARIOS))
    args = parser.parse_args(argv)
    lib = ckernels.load()
    for name in args.scenarios:
        for p in PRECISIONS:
            print(build_simulation(name, p, lib))
    return 0


if __name__ == "__main__":
    sys.exit(main())
