"""``make bench``: the fast path measured, written to bench/results.md and bench/results.json.

Everything is measured in one run on this machine; each number is the median of many
repetitions (garbage collector off while timing). Per-call times of a Python path include the
Python loop that repeats the call (tens of ns, the same for every path, the floor included).

1. Per call of each controller's fused step (e, g on serial arm 1; f, d on the parallel
   mechanism), at the thesis scenario's initial state: through ctypes (kernels.library), the
   same step as a CasADi Function called from Python, CasADi's Function.buffer() on the compiled
   library (casadi.external), a C function with the same signature that does nothing, called
   through ctypes the same way (the floor), the kernel alone timed in C (bench/time_kernel.c);
   for controller e a NumPy implementation of the same law (bench/numpy_law.py) and, for the
   serial arm, Pinocchio's rnea called from Python. Every path's outputs are checked equal.
2. Closed-loop simulation of every scenario in models/scenarios/, full length, as a
   real-time factor: the CasADi reference, the Python loop over ctypes kernels, the all-in-C
   driver (end to end, and the driver calls alone).
3. Generation and compile time of all kernels (clean, into a scratch folder), generated size.
4. The embedded controller (bench/embedded_bench.py): the step in double and in float, and the
   all-in-C simulation (embedded/sim) end to end.
5. The embedded program build/cochlea-embedded against cochlea-emulator
   (bench/embedded_program.py): its loop's compute against cochlea-run's, the bus time of one
   period at 1-4 Mbaud with the emulator's wire timing, the deadline misses of 20 s.
6. A sweep's samples per core (bench/sweep_bench.py's serial part, CPU time): each study's
   full-length sample as a cochlea-sweep worker runs it, and where its time goes.
7. The generated plant step against MuJoCo's RK4 step of the same arm
   (bench/mujoco_compare.py; mujoco is the bench extra): the arm checked the same first
   (accelerations and one step to 1e-9), then both steps timed in C and their ratio.

A section that cannot run (a tool missing, a program that refuses, a run that fails) does not
end the benchmark: its section in results.md says why ("not measured in this run: ..."),
results.json holds the reason under ``not_run``, and the other sections still run.

``python bench/run.py`` runs every section and writes bench/results.md and results.json;
``--only SECTION [SECTION ...] --out DIR`` runs the sections named (of :data:`SECTIONS`) and
writes DIR/results.md and DIR/results.json (a partial run never replaces bench/'s files).
Exit codes: 0 the results were written (every section measured or saying why not); 2 a bad
option (one line on stderr).
"""

from __future__ import annotations

import argparse
import functools
import gc
import itertools
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

import casadi as ca  # noqa: E402
import embedded_bench  # noqa: E402
import embedded_program  # noqa: E402
import mujoco_compare  # noqa: E402
import numpy as np  # noqa: E402
import pinocchio as pin  # noqa: E402
import sweep_bench  # noqa: E402
from numpy_law import NumpyStepE  # noqa: E402

import cochlea  # noqa: E402
from cochlea.kernels import library as ckernels
from cochlea.resources import SCENARIOS_DIR  # noqa: E402
from cochlea.robots.plant import GEAR_SUBSTEPS
from cochlea.robots.serial import load_serial  # noqa: E402
from cochlea.sim import compiled as csim  # noqa: E402
from cochlea.sim import load_scenario, simulate, unit_setups  # noqa: E402
from tests.test_pinocchio_oracle import pinocchio_arm  # noqa: E402

OUT = ROOT / "bench"
WORK = ROOT / "build" / "bench"
CONTROLLERS = (("e", "serial_joint"), ("g", "serial_task"), ("f", "parallel_joint"),
               ("d", "parallel_task"))
#: Issue 30's sweep targets (samples/s/core): the 20 s serial studies, the 10 s parallel ones.
TARGETS = {"step_vs_floor": 2.0, "casadi_vs_step": 10.0, "serial_rtf": 1000.0,
           "codegen_compile_s": 60.0, "realistic_rtf_ratio": 0.8,
           "sweep_serial_samples_per_s_core": 60.0, "sweep_parallel_samples_per_s_core": 40.0,
           "sweep_outside_share": 0.10,  # item 3: a sample's cost outside its loop
           **embedded_bench.TARGETS}


# --------------------------------------------------------------------------------------------
# Timing
# --------------------------------------------------------------------------------------------


def per_call(fn, reps: int = 101, batch_s: float = 2e-3) -> float:
    """Median time of one call (s) over ``reps`` batches of back-to-back calls."""
    start = time.perf_counter()
    fn()
    estimate = max(time.perf_counter() - start, 5e-8)
    calls = max(5, int(batch_s / estimate))
    for _ in range(min(calls, 1000)):  # warm up
        fn()
    times = []
    gc.disable()
    try:
        for _ in range(reps):
            t0 = time.perf_counter_ns()
            for _ in itertools.repeat(None, calls):
                fn()
            times.append((time.perf_counter_ns() - t0) / calls)
    finally:
        gc.enable()
    return statistics.median(times) * 1e-9


def wall(fn, reps: int) -> tuple[float, object]:
    """Median wall time (s) of ``reps`` runs of fn, and its last result."""
    times, result = [], None
    for _ in range(reps):
        gc.collect()
        gc.disable()
        try:
            t0 = time.perf_counter()
            result = fn()
            times.append(time.perf_counter() - t0)
        finally:
            gc.enable()
    return statistics.median(times), result


def compile_helpers() -> tuple[Path, Path]:
    WORK.mkdir(parents=True, exist_ok=True)
    floor, harness = WORK / "libfloor.so", WORK / "time_kernel"
    flags = ["-O2", "-Wall", "-Wextra", "-Werror"]
    subprocess.run(["cc", *flags, "-fPIC", "-shared", "-o", str(floor),
                    str(OUT / "floor.c")], check=True)
    subprocess.run(["cc", *flags, "-o", str(harness), str(OUT / "time_kernel.c"), "-ldl"],
                   check=True)
    return floor, harness


def time_in_c(harness: Path, lib: ckernels.Library, name: str, inputs: list[np.ndarray],
              reps: int = 101, calls: int = 2000) -> float:
    """The kernel alone, timed in C (s per call)."""
    path = WORK / f"{name}.inputs"
    np.concatenate([np.ravel(np.asarray(a, float), order="F") for a in inputs]).tofile(path)
    # The C symbol: an alias (a kernel computing what another does) runs that kernel's C.
    out = subprocess.run([str(harness), str(lib.path), lib.symbol(name), str(path), str(reps),
                          str(calls)],
                         check=True, capture_output=True, text=True)
    return float(out.stdout) * 1e-9


# --------------------------------------------------------------------------------------------
# 1. Per-call cost of the fused step
# --------------------------------------------------------------------------------------------


def step_inputs(u) -> list[np.ndarray]:
    """The step's inputs at the scenario's start, with the nominal estimate."""
    n = u.controller_model.nq
    xd, xd_dot, xd_ddot = (np.array(v, float).ravel() for v in u.desired(0.0))
    return [u.x0[:n].copy(), u.x0[n:].copy(), xd, xd_dot, xd_ddot,
            u.controller_model.p_nominal.astype(float), u.gains.astype(float),
            u.gamma.astype(float), np.array(u.bound, float), np.array(1e-3),
            *(np.asarray(v, float) for v in u.robust_inputs)]


def close(a, b) -> float:
    a, b = np.ravel(np.asarray(a, float)), np.ravel(np.asarray(b, float))
    return float(np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b))))


def bench_steps(lib: ckernels.Library, floor_path: Path, harness: Path) -> list[dict]:
    import ctypes  # noqa: PLC0415

    floor_fn = ctypes.CDLL(str(floor_path)).cochlea_floor
    floor_fn.argtypes, floor_fn.restype = ckernels.KERNEL_ARGTYPES, ctypes.c_int
    system = load_serial("serial")
    rows = []
    for kind, scenario in CONTROLLERS:
        u = unit_setups(load_scenario(scenario))[0]
        f = u.controller.step
        name = f.name()
        args = step_inputs(u)
        reference = [np.array(o) for o in f(*args)]
        row = {"controller": kind, "kernel": name, "scenario": scenario,
               "operations": f.n_instructions()}

        kernel = lib.kernel(name)
        for a, value in zip(kernel.signature.inputs, args):
            kernel[a.name][...] = value
        kernel()
        row["check_ctypes"] = max(close(o, r) for o, r in zip(kernel.outputs.values(),
                                                              reference))
        row["ctypes_s"] = per_call(kernel)
        row["ctypes_bare_s"] = per_call(kernel.call)

        row["casadi_python_s"] = per_call(lambda: f(*args), reps=51)

        external = ca.external(lib.symbol(name), str(lib.path))
        buffer, trigger = external.buffer()
        ins = [np.ascontiguousarray(a, float).reshape(-1).copy() for a in args]
        outs = [np.zeros(external.nnz_out(i)) for i in range(external.n_out())]
        for i, a in enumerate(ins):
            buffer.set_arg(i, memoryview(a))
        for i, o in enumerate(outs):
            buffer.set_res(i, memoryview(o))
        trigger()
        row["check_casadi_buffer"] = max(close(o, r) for o, r in zip(outs, reference))
        row["casadi_buffer_s"] = per_call(trigger)

        floor = ckernels.Kernel(floor_fn, lib.signature(name), {})
        row["floor_s"] = per_call(floor)
        row["c_alone_s"] = time_in_c(harness, lib, name, args)

        if kind == "e":
            arm = system.arms[0]
            law = NumpyStepE(arm, arm.base_rotation.T @ system.gravity)
            row["check_numpy"] = max(close(o, r) for o, r in zip(law(*args), reference))
            row["numpy_s"] = per_call(lambda: law(*args), reps=51)
        if kind in ("e", "g"):
            model = pinocchio_arm(system, system.arms[0])
            data = model.createData()
            q, v, a = args[0], args[1], np.zeros(3)
            tau = pin.rnea(model, data, q, v, a)
            row["check_pinocchio_rnea"] = close(
                tau, np.array(cochlea.model("serial").inverse_dynamics(q, v, a)))
            row["pinocchio_rnea_s"] = per_call(lambda: pin.rnea(model, data, q, v, a))
        row["step_vs_floor"] = row["ctypes_s"] / row["floor_s"]
        row["casadi_vs_step"] = row["casadi_python_s"] / row["ctypes_s"]
        rows.append(row)
        print(f"  {name}: ctypes {row['ctypes_s'] * 1e6:.3f} us, floor "
              f"{row['floor_s'] * 1e6:.3f} us, C alone {row['c_alone_s'] * 1e6:.3f} us, "
              f"CasADi from Python {row['casadi_python_s'] * 1e6:.1f} us", flush=True)
    return rows


# --------------------------------------------------------------------------------------------
# 2. Closed-loop real-time factors
# --------------------------------------------------------------------------------------------


def max_log_difference(a, b) -> float:
    worst = 0.0
    for u, r in zip(a.units, b.units):
        # "pose": the measured state's, computed where the run did not log it.
        for key in ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose",
                    "true_q", "true_qd", "true_x"):
            x, y = getattr(u, key), getattr(r, key)
            worst = max(worst, float(np.max(np.abs(x - y))) if x.size else 0.0)
    return worst


#: Besides every shipped scenario, each thesis study on the realistic plant (same controller).
REALISTIC_PLANT = " (realistic plant)"


def closed_loop_cases():
    """``(label, scenario)``: every shipped scenario, and each thesis study on the realistic
    plant, so the realistic plant's cost is measured with the controller held the same."""
    for path in sorted(SCENARIOS_DIR.glob("*.toml")):
        yield path.stem, load_scenario(path.stem)
    for _, study in CONTROLLERS:
        yield study + REALISTIC_PLANT, load_scenario(study, plant_preset="realistic")


def bench_closed_loops(lib: ckernels.Library, harness: Path) -> list[dict]:
    rows = []
    for label, sc in closed_loop_cases():
        setups = unit_setups(sc)
        duration = sc.duration
        row = {"scenario": label, "duration_s": duration, "units": len(setups),
               "periods": int(round(duration * sc.rate_hz)), "plant": sc.plant.preset,
               "controller_actuators": sc.controller_actuators}
        t_ref, reference = wall(lambda: simulate(sc, setups=setups, kernels="casadi"), 3)
        t_py, python_loop = wall(
            lambda: csim.simulate_compiled(sc, setups=setups, loop="python"), 5)
        t_c, c_loop = wall(lambda: csim.simulate_compiled(sc, setups=setups, loop="c"), 11)
        # The C driver calls alone, units one after the other, inputs prepared once (every
        # plant option of the scenario passed, as simulate() does).
        steps = row["periods"]
        time_grid = np.arange(steps) * sc.period
        prepared = []
        for u in setups:
            kernels = csim.unit_kernels(lib, u, sc.plant_substeps)
            prepared.append((kernels, u, csim.desired_samples(u, time_grid)))

        def driver_only():
            for kernels, u, desired in prepared:
                csim.run_c(lib, kernels, u, sc.period, sc.plant.delay_periods, desired, None)

        t_driver, _ = wall(driver_only, 21)
        # Per period and unit: the plant and step kernels alone, in C.
        k0, u0 = prepared[0][:2]
        # The plant's own state and trailing input: with the gearbox ``[q, qd, theta,
        # theta_dot]`` and the drive's rows, else ``[q, qd]`` and the Coulomb levels if any.
        plant_args = [u0.plant_x0, np.zeros(u0.controller_model.nq), u0.plant_params,
                      u0.friction, np.array(sc.period)]
        if u0.drive is not None:
            plant_args.append(u0.drive)
        elif u0.coulomb is not None:
            plant_args.append(u0.coulomb)
        row.update({
            "casadi_s": t_ref, "python_ctypes_s": t_py, "c_s": t_c, "c_driver_s": t_driver,
            "rtf_casadi": duration / t_ref, "rtf_python_ctypes": duration / t_py,
            "rtf_c": duration / t_c, "rtf_c_driver": duration / t_driver,
            "max_diff_python_ctypes": max_log_difference(python_loop, reference),
            "max_diff_c": max_log_difference(c_loop, reference),
            "plant_kernel_c_s": time_in_c(harness, lib, k0.plant, plant_args, 51, 500),
            "step_kernel_c_s": time_in_c(harness, lib, k0.step, step_inputs(u0), 51, 2000),
            "plant_operations": u0.plant_function(sc.plant_substeps).n_instructions(),
            "gearbox": bool(u0.gearbox),
            "forward_dynamics_operations":
                u0.plant_model.forward_dynamics_p.n_instructions(),
            "plant_substeps": sc.plant_substeps,
        })
        rows.append(row)
        print(f"  {label}: CasADi {row['rtf_casadi']:.0f}x, Python+ctypes "
              f"{row['rtf_python_ctypes']:.0f}x, all-in-C {row['rtf_c']:.0f}x (driver alone "
              f"{row['rtf_c_driver']:.0f}x) real time", flush=True)
    return rows


def plant_integration(row: dict) -> str:
    """How the row's plant integrates one period, in words."""
    k = row["plant_substeps"]
    if row.get("gearbox"):
        return (f"{k * GEAR_SUBSTEPS} linearly implicit sub-steps of the geared plant, each an "
                "n x n linear solve")
    return f"{k} RK4 sub-steps = {4 * k} forward-dynamics evaluations"


RTF_PATHS = (("rtf_python_ctypes", "Python + ctypes"), ("rtf_c", "all-in-C"),
             ("rtf_c_driver", "C driver"))


def realistic_ratios(loops: list[dict]) -> list[dict]:
    """Per study: each real-time factor on the realistic plant (the thesis study's controller,
    then the realistic study's) over the same on the ideal plant."""
    by_name = {r["scenario"]: r for r in loops}
    rows = []
    for kind, study in CONTROLLERS:
        ideal = by_name[study]
        for case in (study + REALISTIC_PLANT, f"{study}_realistic"):
            rows.append({"controller": kind, "ideal": study, "case": case, **{
                key: by_name[case][key] / ideal[key] for key, _ in RTF_PATHS}})
    return rows


# --------------------------------------------------------------------------------------------
# 3. Generation, compilation, size
# --------------------------------------------------------------------------------------------


def bench_build() -> dict:
    with tempfile.TemporaryDirectory(prefix="cochlea-bench-") as tmp:
        gen, build = Path(tmp) / "gen", Path(tmp) / "build"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--out", str(gen)],
                       cwd=ROOT, check=True, capture_output=True)
        t_gen = time.perf_counter() - t0
        t0 = time.perf_counter()
        subprocess.run(["make", "-s", "lib", f"GEN={gen}", f"BUILD={build}"], cwd=ROOT,
                       check=True, capture_output=True)
        t_compile = time.perf_counter() - t0
        committed = ROOT / "generated_c"  # the library's sources and embedded/, every file
        identical = all((gen / p.relative_to(committed)).read_bytes() == p.read_bytes()
                        for p in committed.rglob("*") if p.is_file())
        so_size = (build / "libcochlea.so").stat().st_size
    files = sorted(p for p in (ROOT / "generated_c").iterdir() if p.is_file())
    c_files = [p for p in files if p.suffix in (".c", ".h")]
    return {"generate_s": t_gen, "compile_s": t_compile, "total_s": t_gen + t_compile,
            "jobs": os.cpu_count(), "regenerated_identical": identical,
            "files": len(files), "c_and_h_files": len(c_files),
            "c_and_h_bytes": sum(p.stat().st_size for p in c_files),
            "c_and_h_lines": sum(p.read_text().count("\n") for p in c_files),
            "library_bytes": so_size}


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def load_average() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def machine() -> dict:
    cpu = next((line.split(":", 1)[1].strip() for line in
                Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    cc = subprocess.run(["cc", "--version"], capture_output=True, text=True).stdout
    return {"cpu": cpu, "cores": os.cpu_count(), "system": platform.platform(),
            "python": platform.python_version(), "casadi": ca.__version__,
            "numpy": np.__version__, "pinocchio": pin.__version__,
            "cc": cc.splitlines()[0] if cc else "?", "flags": "-O2 -std=c99 -fPIC",
            "date": time.strftime("%Y-%m-%d")}


def us(seconds: float) -> str:
    return f"{seconds * 1e6:.3f}" if seconds < 1e-5 else f"{seconds * 1e6:.1f}"


def verdicts(steps: list[dict] | None, loops: list[dict] | None, build: dict | None
             ) -> list[str]:
    """The target lines of the sections that ran (None: a section that did not)."""
    steps, loops = steps or [], loops or []
    lines = []
    for r in steps:
        ratio, target = r["step_vs_floor"], TARGETS["step_vs_floor"]
        if ratio <= target:
            lines.append(f"- **met**: `{r['kernel']}` through ctypes is {ratio:.2f}x the floor "
                         f"(target <= {target:g}x).")
        else:
            rest = r["ctypes_s"] - r["floor_s"] - r["c_alone_s"]
            lines.append(
                f"- **missed** by {ratio / target:.3f}x: `{r['kernel']}` through ctypes is "
                f"{ratio:.3f}x the floor (target <= {target:g}x). Why: the law's own "
                f"arithmetic, {us(r['c_alone_s'])} us alone in C ({r['operations']} "
                f"operations) against a floor of {us(r['floor_s'])} us, so even a free call "
                f"would be {1 + r['c_alone_s'] / r['floor_s']:.2f}x the floor; the remaining "
                f"{us(rest)} us is the same code run between Python calls, with caches it "
                "shares with the interpreter, where the C figure runs it in a tight loop. The "
                "binding adds no work per call (`bare` is the ctypes call alone).")
    for r in steps:
        ratio, target = r["casadi_vs_step"], TARGETS["casadi_vs_step"]
        verdict = "met" if ratio >= target else f"missed by {target / ratio:.2f}x"
        lines.append(f"- **{verdict}**: `{r['kernel']}` through ctypes is {ratio:.0f}x faster "
                     f"than the CasADi Function from Python (target >= {target:g}x).")
    target = TARGETS["serial_rtf"]
    for r in loops:
        if not r["scenario"].startswith("serial"):
            continue
        rtf = r["rtf_c"]
        if rtf >= target:
            lines.append(f"- **met**: {r['scenario']} all-in-C at {rtf:.0f}x real time "
                         f"(target >= {target:g}x).")
            continue
        per_unit = r["plant_kernel_c_s"] + r["step_kernel_c_s"]
        lines.append(
            f"- **missed** by {target / rtf:.2f}x: {r['scenario']} all-in-C at {rtf:.0f}x real "
            f"time end to end ({r['rtf_c_driver']:.0f}x for the C driver calls alone, the "
            f"{r['units']} arms one after the other; target >= {target:g}x). Why: each arm "
            f"and period costs the plant step, {us(r['plant_kernel_c_s'])} us in C "
            f"({plant_integration(r)}, {r['plant_operations']} operations), plus the "
            "controller step, "
            f"{us(r['step_kernel_c_s'])} us: {us(per_unit)} us per arm and period, so "
            f"{r['units']} arms cap one core at about {1e-3 / (r['units'] * per_unit):.0f}x. "
            "The driver adds nothing measurable; simulate() runs the arms on parallel threads, "
            "and the end-to-end figure also pays the run's set-up (the desired samples of the "
            "whole run, evaluated by CasADi, and binding the kernels). The plant's forward "
            f"dynamics already takes its bias from recursive Newton-Euler "
            f"({r['forward_dynamics_operations']} operations).")
    # The realistic plant's cost, controller held the same: the paths that run the studies
    # (simulate()'s all-in-C, the C driver). The Python + ctypes loop is a comparison, and the
    # realistic studies run a larger controller: both are reported in the table below.
    target = TARGETS["realistic_rtf_ratio"]
    for r in realistic_ratios(loops) if loops else []:
        if not r["case"].endswith(REALISTIC_PLANT):
            continue
        worst_key, worst_name = min(RTF_PATHS[1:], key=lambda p: r[p[0]])
        ratio = r[worst_key]
        verdict = "met" if ratio >= target else f"missed by {target / ratio:.2f}x"
        lines.append(f"- **{verdict}**: {r['case']} keeps {ratio:.0%} of {r['ideal']}'s "
                     f"real-time factor on its slower C path ({worst_name}; target >= "
                     f"{target:.0%}).")
    if build is not None:
        total, target = build["total_s"], TARGETS["codegen_compile_s"]
        verdict = "met" if total < target else f"missed by {total / target:.2f}x"
        lines.append(f"- **{verdict}**: generation {build['generate_s']:.1f} s + compilation "
                     f"{build['compile_s']:.1f} s = {total:.1f} s on {build['jobs']} cores "
                     f"(target < {target:g} s).")
    return lines


def not_measured(results: dict, *sections: str) -> list[str]:
    """The lines of a section that did not run: why (one paragraph), or [] if it ran."""
    reasons = [results.get("not_run", {}).get(s) for s in sections]
    reasons = [r for r in reasons if r]
    return [f"Not measured in this run: {'; '.join(reasons)}.", ""] if reasons else []


def markdown(results: dict) -> str:
    m = results["machine"]
    steps, loops, build = (results.get("steps"), results.get("closed_loops"),
                           results.get("build"))
    out = ["# Benchmark results", "",
           f"Written by `make bench` (bench/run.py) on {m['date']}: {m['cpu']}, {m['cores']} "
           f"cores, {m['system']}; Python {m['python']}, CasADi {m['casadi']}, NumPy "
           f"{m['numpy']}, Pinocchio {m['pinocchio']}, {m['cc']} ({m['flags']}). Medians of "
           "many repetitions, all in one run. Not a test: nothing asserts a time. Load average "
           f"(1 min) {results['load_before']:.2f} before and {results['load_after']:.2f} after "
           "the run (other work on the machine slows every path alike).", "",
           "## Targets", ""]
    out += verdicts(steps, loops, build)
    out += embedded_bench.verdicts(results.get("embedded_steps") or [],
                                   results.get("embedded_sims") or [])
    out += sweep_verdicts(results.get("sweep") or [], loops)
    out += outside_verdicts(results.get("sweep") or [])
    for section, reason in results.get("not_run", {}).items():
        out.append(f"- **not measured**: {SECTIONS[section]}: {reason}")
    out += ["", "## Per call of the fused step (us)", ""]
    out += not_measured(results, "steps")
    out += [] if steps is None else [
            "At the thesis scenario's initial state, corrected variant. *ctypes*: "
            "`kernel()` of `cochlea.kernels.library` (return code checked); *bare*: the prepared "
            "ctypes call alone; *floor*: an empty C function with the same signature called the "
            "same way; *C alone*: the kernel timed in C; *buffer*: CasADi's `Function.buffer()` "
            "on `casadi.external` of libcochlea.so; *CasADi*: the CasADi Function called from "
            "Python with numpy arguments; *NumPy*: bench/numpy_law.py (controller e only); "
            "*rnea*: Pinocchio's `pin.rnea` from Python on arm 1 (serial only, a reference "
            "for one rigid-body call).", "",
            "| kernel | ops | C alone | floor | ctypes | bare | buffer | CasADi | NumPy | rnea "
            "| ctypes / floor | CasADi / ctypes |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in steps or []:
        out.append(
            f"| `{r['kernel']}` | {r['operations']} | {us(r['c_alone_s'])} | {us(r['floor_s'])} "
            f"| {us(r['ctypes_s'])} | {us(r['ctypes_bare_s'])} | {us(r['casadi_buffer_s'])} | "
            f"{us(r['casadi_python_s'])} | "
            f"{us(r['numpy_s']) if 'numpy_s' in r else '-'} | "
            f"{us(r['pinocchio_rnea_s']) if 'pinocchio_rnea_s' in r else '-'} | "
            f"{r['step_vs_floor']:.2f} | {r['casadi_vs_step']:.0f} |")
    checks = [v for r in steps or [] for k, v in r.items() if k.startswith("check_")]
    if checks:
        out += ["", f"Every path's outputs agree with the CasADi Function to {max(checks):.1e} "
                    "(relative to max(1, |value|))."]
    out += ["", "## Closed-loop simulation (real-time factor: simulated s per wall s)", ""]
    out += not_measured(results, "closed_loops")
    out += [] if loops is None else [
            "Full scenario length. *CasADi*: `simulate(kernels=\"casadi\")`, the reference; "
            "*Python + ctypes*: a Python loop over the step, plant and pose kernels "
            "(`simulate_compiled(loop=\"python\")`); *all-in-C*: `simulate()` (the default: the "
            "generated driver, units on parallel threads, setup included); *C driver*: the "
            "driver calls alone, units one after the other. Max diff: the largest absolute "
            "difference of any logged value from the CasADi reference.", "",
            "| scenario | s | units | CasADi | Python + ctypes | all-in-C | C driver | "
            "max diff (ctypes / C) |", "|---|---|---|---|---|---|---|---|"]
    for r in loops or []:
        out.append(f"| {r['scenario']} | {r['duration_s']:g} | {r['units']} | "
                   f"{r['rtf_casadi']:.0f}x | {r['rtf_python_ctypes']:.0f}x | "
                   f"{r['rtf_c']:.0f}x | {r['rtf_c_driver']:.0f}x | "
                   f"{r['max_diff_python_ctypes']:.1e} / {r['max_diff_c']:.1e} |")
    if loops is not None:
        out += loops_markdown(loops)
    out += ["", "## Generation and compilation", ""]
    out += not_measured(results, "build")
    if build is not None:
        out += [
            f"- `cochlea-codegen` (clean, Python start-up included): {build['generate_s']:.1f} s",
            f"- `make lib` (clean, -j{build['jobs']}): {build['compile_s']:.1f} s",
            f"- total: {build['total_s']:.1f} s; regenerated files identical to generated_c/: "
            f"{'yes' if build['regenerated_identical'] else 'NO'}",
            f"- generated_c/: {build['files']} files, {build['c_and_h_files']} C sources and "
            f"headers, {build['c_and_h_bytes'] / 1024:.0f} KiB, {build['c_and_h_lines']} lines; "
            f"libcochlea.so {build['library_bytes'] / 1024:.0f} KiB", ""]
    out += embedded_bench.markdown(results.get("embedded_steps"), results.get("embedded_sims"),
                                   loops, results.get("not_run", {}))
    out += [""]
    if results.get("embedded_program") is not None:
        out += [embedded_program.markdown(results["embedded_program"])]
    else:
        out += [embedded_program.TITLE, "", *not_measured(results, "embedded_program")]
    out += sweep_markdown(results.get("sweep"), not_measured(results, "sweep"))
    out += mujoco_compare.markdown(results.get("mujoco"), not_measured(results, "mujoco"))
    return "\n".join(out)


def loops_markdown(loops: list[dict]) -> list[str]:
    """The realistic plant's ratios and the per-period kernel costs of the closed loops."""
    out = ["", "The realistic plant's cost: each real-time factor over the same on the ideal "
            "plant (the thesis study). *(realistic plant)*: the thesis study's controller on "
            "the realistic plant (armature, sticking friction, encoder and register grids, "
            "current quantisation, one period of delay); *_realistic*: the realistic study "
            "(the controller estimates its drives' armature and friction too, a larger step). "
            "The target (>= 80 %) is on the realistic plant with the controller held the same, "
            "for the C paths that run the studies; the Python + ctypes loop, a comparison, "
            "pays the measurement and current grids in NumPy each period (a few us against a "
            "C period of under one).", "",
            "| case | " + " | ".join(name for _, name in RTF_PATHS) + " |",
            "|---|" + "---|" * len(RTF_PATHS)]
    for r in realistic_ratios(loops):
        out.append(f"| {r['case']} | " + " | ".join(f"{r[key]:.2f}" for key, _ in RTF_PATHS)
                   + " |")
    out += ["", "Per unit and period, in C: " + "; ".join(
        f"{r['scenario']}: plant {us(r['plant_kernel_c_s'])} us ({r['plant_operations']} ops), "
        f"step {us(r['step_kernel_c_s'])} us" for r in loops) + "."]
    return out


def sweep_target(study: str) -> float:
    """A study's sweep target (samples/s/core): issue 30's for the serial or parallel ones."""
    robot = "serial" if study.startswith("serial") else "parallel"
    return TARGETS[f"sweep_{robot}_samples_per_s_core"]


def kernel_floor(loop: dict | None, duration_s: float) -> float | None:
    """The CPU time (s) a ``duration_s`` run of a closed-loop row's scenario cannot go below on
    this machine: every unit's plant step and controller step each period, as timed alone in C
    (bench/time_kernel.c), nothing else. None without the row."""
    if loop is None:
        return None
    periods = loop["periods"] * duration_s / loop["duration_s"]
    return (loop["plant_kernel_c_s"] + loop["step_kernel_c_s"]) * loop["units"] * periods


def sweep_verdicts(rows: list[dict], loops: list[dict] | None = None) -> list[str]:
    """The target line of each study's sweep row (bench/sweep_bench.py's serial()): met, or
    missed by how much and why (where the sample's CPU time goes). ``loops``: the closed-loop
    rows, whose kernels timed in C say whether the target is within this machine's reach at
    all (:func:`kernel_floor`: a sample's loop runs those very kernels)."""
    lines = []
    by_name = {r["scenario"]: r for r in loops or []}
    for r in rows:
        rate, target = r["per_s_core"], sweep_target(r["study"])
        head = (f"{r['study']} ({r['duration_s']:g} s) sweeps at {rate:.1f} samples/s/core "
                f"(target >= {target:g})")
        if rate >= target:
            lines.append(f"- **met**: {head}.")
            continue
        cpu, loop = r["cpu_s"], r["parts"].get("C closed loop", 0.0)
        # The loop and the rest from the one breakdown (measured after the rate, on the same
        # samples): the rate's CPU time minus the breakdown's loop would put whatever the
        # machine's speed did between the two measures into "outside".
        total = sum(r["parts"].values()) or cpu
        outside = total - loop
        parts = sorted(((v, k) for k, v in r["parts"].items() if k != "C closed loop"),
                       reverse=True)[:2]
        moved = (f" (the breakdown, measured after the rate, totals {total * 1e3:.1f} ms a "
                 "sample: this machine's speed moved between the two)"
                 if abs(total - cpu) > 0.2 * cpu else "")
        lines.append(
            f"- **missed** by {target / rate:.2f}x: {head}. Why: a sample costs "
            f"{cpu * 1e3:.1f} ms of CPU where the target allows {1e3 / target:.1f} ms{moved}: "
            f"the C closed loop {loop * 1e3:.1f} ms ({loop / total:.0%}; alone it would allow "
            f"{1 / loop if loop > 0 else float('inf'):.0f} samples/s/core), the rest "
            f"{outside * 1e3:.1f} ms outside it (" + ", ".join(
                f"{k} {v * 1e3:.2f} ms" for v, k in parts) + "; issue 30 wants it under "
            f"10 % of the loop's, {0.1 * loop * 1e3:.1f} ms).")
        floor = kernel_floor(by_name.get(r["study"]), r["duration_s"])
        if floor is not None and floor > 1 / target:
            k = by_name[r["study"]]
            lines[-1] += (
                f" Out of reach at this run's speed, whatever the rest costs: the plant step "
                f"({us(k['plant_kernel_c_s'])} us) and the controller step "
                f"({us(k['step_kernel_c_s'])} us) alone, timed in C, {k['units']} "
                f"unit{'s' if k['units'] != 1 else ''} and "
                f"{k['periods'] * r['duration_s'] / k['duration_s']:.0f} periods, are "
                f"{floor * 1e3:.1f} ms a sample, above the {1e3 / target:.1f} ms the target "
                f"allows (at most {1 / floor:.0f} samples/s/core with nothing else): only a "
                "cheaper plant or controller (the studies' own integrator and law) or a faster "
                "machine would meet it (this one's speed moves by up to 2x over minutes: "
                "docs/sweeps.md).")
    return lines


def _outside_share(r: dict) -> float | None:
    """A sweep row's cost outside the C closed loop over the loop's, from its breakdown."""
    loop = r["parts"].get("C closed loop", 0.0)
    return (sum(r["parts"].values()) - loop) / loop if loop > 0 else None


def outside_verdicts(rows: list[dict]) -> list[str]:
    """Issue 30 item 3's line of each sweep row: a sample's cost outside its C closed loop (the
    scenario's data, load and set-ups, the rest of simulate, the verdict, the summary and row)
    under :data:`TARGETS` ``sweep_outside_share`` of the loop's, met or missed, with its two
    largest parts."""
    lines = []
    limit = TARGETS["sweep_outside_share"]
    for r in rows:
        share = _outside_share(r)
        if share is None:
            continue
        head = (f"{r['study']} ({r['duration_s']:g} s): a sample's cost outside its C closed "
                f"loop is {share:.1%} of the loop's (target < {limit:.0%})")
        if share < limit:
            lines.append(f"- **met**: {head}.")
            continue
        parts = sorted(((v, k) for k, v in r["parts"].items() if k != "C closed loop"),
                       reverse=True)[:2]
        lines.append(f"- **missed** by {share / limit:.2f}x: {head}. Largest: " + ", ".join(
            f"{k} {v * 1e3:.2f} ms" for v, k in parts) + ".")
    return lines


def sweep_markdown(rows: list[dict] | None, reason: list[str] = ()) -> list[str]:
    """Section 6: samples per core (the verdicts, against the targets of the 20 s serial
    studies and the 10 s parallel ones, are under Targets), and where a sample's CPU time goes.
    ``rows`` None: the section did not run, ``reason`` says why."""
    if rows is None:
        return ["", "## A sweep's samples per core (CPU time)", "", *reason]
    out = ["", "## A sweep's samples per core (CPU time)", "",
           "Each study's full-length sample as a `cochlea-sweep` worker runs it "
           "(bench/sweep_bench.py: scenario file, set-ups from the worker's cache, C "
           "simulation, supervisor verdict, summary), in process CPU time; *uncached*: the "
           "set-ups built again for the sample. Targets (verdicts under Targets above): at "
           f"least {TARGETS['sweep_serial_samples_per_s_core']:g} samples/s/core for the 20 s "
           f"serial studies, {TARGETS['sweep_parallel_samples_per_s_core']:g} for the 10 s "
           "parallel ones."]
    # In a sample's order (results.json sorts the keys), any part an older row lacks last.
    names = sorted(rows[0]["parts"], key=lambda k: (sweep_bench.PARTS + (k,)).index(k))
    out += ["", "| study | s | samples/s/core | CPU ms per sample | uncached ms | "
            + " | ".join(names) + " | outside / loop |",
            "|---|---|---|---|---|" + "---|" * len(names) + "---|"]
    for r in rows:
        share = _outside_share(r)
        out.append(f"| {r['study']} | {r['duration_s']:g} | {r['per_s_core']:.1f} | "
                   f"{r['cpu_s'] * 1e3:.1f} | {r['uncached_cpu_s'] * 1e3:.0f} | "
                   + " | ".join(f"{r['parts'][k] * 1e3:.2f}" for k in names)
                   + f" | {'-' if share is None else f'{share:.1%}'} |")
    return out


#: The sections of results.md, in the order they run: name -> what they measure.
SECTIONS = {
    "build": "generation and compilation",
    "steps": "per call of the fused steps",
    "closed_loops": "closed-loop simulation",
    "embedded_steps": "the embedded step in double and float",
    "embedded_sims": "the all-in-C simulation (embedded/sim)",
    "embedded_program": "the embedded program against the emulator (about 2 min)",
    "sweep": "a sweep's samples per core",
    "mujoco": "the plant step against MuJoCo's RK4 step",
}


def reason(error: BaseException) -> str:
    """One line saying why a section could not run (a failed command's last stderr line)."""
    text = f"{type(error).__name__}: {error}"
    stderr = getattr(error, "stderr", None)
    if isinstance(stderr, bytes):
        stderr = stderr.decode(errors="replace")
    if stderr and stderr.strip():
        text += f" ({stderr.strip().splitlines()[-1]})"
    return " ".join(text.split())[:600]


def run_sections(names) -> dict:
    """Run the sections ``names`` (of :data:`SECTIONS`); one that fails is recorded under
    ``not_run`` with its reason and the next one runs."""
    lib = functools.cache(ckernels.load)
    helpers = functools.cache(compile_helpers)
    plan = {
        "build": bench_build,
        "steps": lambda: bench_steps(lib(), *helpers()),
        "closed_loops": lambda: bench_closed_loops(lib(), helpers()[1]),
        "embedded_steps": embedded_bench.bench_embedded_steps,
        "embedded_sims": embedded_bench.bench_embedded_sims,
        "embedded_program": embedded_program.bench,
        "sweep": sweep_section,
        "mujoco": lambda: mujoco_compare.bench(
            lib(), functools.partial(time_kernel, helpers()[1], lib())),
    }
    results = {"machine": machine(), "targets": TARGETS, "load_before": load_average(),
               "not_run": {}}
    for name in SECTIONS:
        if name not in names:
            results["not_run"][name] = "not chosen (--only)"
            continue
        print(f"bench: {SECTIONS[name]}", flush=True)
        try:
            results[name] = plan[name]()
        except Exception as error:  # noqa: BLE001 -- said in the section, the rest runs
            results["not_run"][name] = reason(error)
            print(f"bench: {SECTIONS[name]}: not measured: {results['not_run'][name]}",
                  file=sys.stderr, flush=True)
    results["load_after"] = load_average()
    return results


def time_kernel(harness: Path, lib: ckernels.Library, name: str,
                inputs: list[np.ndarray]) -> float:
    """A kernel's time per call in C: the median of 51 runs of 2000 calls."""
    return time_in_c(harness, lib, name, inputs, 51, 2000)


def sweep_section() -> list[dict]:
    with tempfile.TemporaryDirectory(prefix="cochlea-bench-") as tmp:
        return sweep_bench.serial(Path(tmp), samples=10)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="make bench: the fast path measured")
    parser.add_argument("--only", nargs="+", metavar="SECTION",
                        help=f"run only these sections (of {', '.join(SECTIONS)}); needs --out")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="write results.md and results.json here (default: bench/)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.only or ()) - set(SECTIONS))
    if unknown:
        print(f"bench/run.py: error: --only: unknown section {', '.join(unknown)} (one of "
              f"{', '.join(SECTIONS)})", file=sys.stderr)
        return 2
    if args.only and args.out is None:
        print("bench/run.py: error: --only needs --out DIR (a partial run does not replace "
              "bench/results.md)", file=sys.stderr)
        return 2
    out = args.out or OUT
    if not out.is_dir():
        print(f"bench/run.py: error: --out {out}: not a folder", file=sys.stderr)
        return 2
    results = run_sections(args.only or SECTIONS)
    # Each file whole or not at all: written beside, then renamed over the old one.
    for name, text in (("results.json", json.dumps(results, indent=1, sort_keys=True) + "\n"),
                       ("results.md", markdown(results))):
        partial = out / f".{name}.{os.getpid()}"
        partial.write_text(text)
        os.replace(partial, out / name)
    missing = {k: v for k, v in results["not_run"].items() if v != "not chosen (--only)"}
    print(f"bench: wrote {out / 'results.md'} and {out / 'results.json'}"
          + (f"; not measured: {', '.join(missing)} (the sections say why)" if missing else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
