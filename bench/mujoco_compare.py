"""The generated plant step against MuJoCo's RK4 step of the same arm (issue 30, Speed).

MuJoCo is a bench-only dependency (pyproject's ``bench`` extra; ``make bench`` installs it):
nothing in cochlea imports it, and this module imports it only inside :func:`bench`.

1. **The same arm.** :func:`mjcf` writes an MJCF of one arm of a serial description *as cochlea
   loaded it* (no number copied by hand): the base pose, per link the joint frame
   (``origin_xyz_m``, ``origin_rpy_deg``), the joint's type and axis, the inertial (mass,
   centre of mass, the full inertia about it, off-diagonal terms included), the armature when
   the plant carries it, viscous damping only where the plant's friction input has it, the
   system's gravity; no geometry, contacts disabled, ``integrator="RK4"`` and the scenario's
   plant period as the timestep. The torque enters as ``qfrc_applied``, held over the step as
   the plant holds it.
2. **Checked before it is timed.** At :data:`STATES` random states and torques (within the
   joints' position, velocity and effort limits), MuJoCo's ``qacc`` after ``mj_forward`` must
   equal cochlea's forward dynamics (``forward_dynamics_p`` at the plant's parameters), and one
   ``mj_step`` from the same state must equal the generated C plant step, each to
   :data:`TOLERANCE` (relative: the largest difference over the largest value; for the step,
   over the largest change of the state in the step, which is stricter than over the state).
   If either fails, the section says so and reports no ratio.
3. **Timed in C, both.** ``mj_step`` in a C loop (:data:`HARNESS`, compiled against the
   headers and ``libmujoco.so`` the wheel ships), from the same state every call, as
   ``bench/time_kernel.c`` times the plant kernel (same input every call); for comparison
   ``mujoco.rollout`` (MuJoCo's own C rollout: a trajectory of many steps, per step) and
   ``mujoco.mj_step`` called from Python.

Only the serial arm: MuJoCo models a closed chain (the parallel mechanism) as a tree plus
equality constraints, which its constraint solver enforces softly and iteratively (solref,
solimp), so its accelerations are not the closed chain's exact forward dynamics and a 1e-9
check could not pass; see :data:`PARALLEL_NOTE`.
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from cochlea.robots.serial import load_serial
from cochlea.robots.serial.description import Arm, SerialSystem, joint_rotation
from cochlea.sim import load_scenario, unit_setups

ROOT = Path(__file__).resolve().parent.parent
WORK = ROOT / "build" / "bench"
#: The study whose plant is compared: arm 1 on the ideal plant at its 1 ms period.
SCENARIO = "serial_joint"
STATES = 50
TOLERANCE = 1e-9
SEED = 30
TITLE = "## The plant step against MuJoCo's RK4 step (serial arm 1)"
PARALLEL_NOTE = (
    "Not compared on the parallel mechanism: MuJoCo has no closed kinematic chain, it models "
    "one as a tree plus equality constraints (`connect`) that its constraint solver enforces "
    "softly (solref, solimp) and iteratively, so its accelerations are not the closed chain's "
    "exact forward dynamics (the constraint drifts and is pulled back) and neither a 1e-9 check "
    "nor a like-for-like time is possible.")

#: mj_step timed in C: ``time_mujoco MODEL.xml STATE REPS CALLS`` prints the median ns per
#: step over REPS runs of CALLS steps, each from STATE (binary doubles: qpos, qvel,
#: qfrc_applied), as bench/time_kernel.c calls a kernel on the same input every time.
HARNESS = r"""
#define _POSIX_C_SOURCE 199309L
#include <mujoco/mujoco.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static double now_ns(void) {
  struct timespec t;
  clock_gettime(CLOCK_MONOTONIC, &t);
  return 1e9 * (double)t.tv_sec + (double)t.tv_nsec;
}

static int compare(const void* a, const void* b) {
  double x = *(const double*)a, y = *(const double*)b;
  return (x > y) - (x < y);
}

int main(int argc, char** argv) {
  if (argc != 5) { fprintf(stderr, "usage: time_mujoco MODEL STATE REPS CALLS\n"); return 2; }
  char error[1000] = "";
  mjModel* m = mj_loadXML(argv[1], NULL, error, sizeof error);
  if (!m) { fprintf(stderr, "time_mujoco: %s\n", error); return 2; }
  mjData* d = mj_makeData(m);
  int nq = m->nq, nv = m->nv, i;
  double* state = malloc((size_t)(nq + 2 * nv) * sizeof(double));
  FILE* file = fopen(argv[2], "rb");
  if (!file || fread(state, sizeof(double), (size_t)(nq + 2 * nv), file)
      != (size_t)(nq + 2 * nv)) {
    fprintf(stderr, "time_mujoco: cannot read the state from %s\n", argv[2]);
    return 2;
  }
  fclose(file);
  for (i = 0; i < nv; ++i) d->qfrc_applied[i] = state[nq + nv + i];
  long reps = atol(argv[3]), calls = atol(argv[4]), r, c;
  double* per_step = malloc((size_t)reps * sizeof(double));
  for (r = -1; r < reps; ++r) {  /* r = -1: warm up */
    double start = now_ns();
    for (c = 0; c < calls; ++c) {
      memcpy(d->qpos, state, (size_t)nq * sizeof(double));
      memcpy(d->qvel, state + nq, (size_t)nv * sizeof(double));
      mj_step(m, d);
    }
    if (r >= 0) per_step[r] = (now_ns() - start) / (double)calls;
  }
  qsort(per_step, (size_t)reps, sizeof(double), compare);
  printf("%.3f %s\n", per_step[reps / 2], mj_versionString());
  mj_deleteData(d);
  mj_deleteModel(m);
  return 0;
}
"""


# --------------------------------------------------------------------------------------------
# The MJCF, from the loaded description
# --------------------------------------------------------------------------------------------


def quaternion(R: np.ndarray) -> np.ndarray:
    """``[w, x, y, z]`` of a rotation matrix (Shepperd's method: the largest pivot)."""
    R = np.asarray(R, float)
    t = np.trace(R)
    if t > max(R[0, 0], R[1, 1], R[2, 2]):
        s = 2.0 * np.sqrt(1.0 + t)
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0] * 4
        q[0] = (R[k, j] - R[j, k]) / s
        q[1 + i] = s / 4
        q[1 + j] = (R[j, i] + R[i, j]) / s
        q[1 + k] = (R[k, i] + R[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q) * (1.0 if q[0] >= 0 else -1.0)


def _numbers(values) -> str:
    """Space-separated, every digit kept (repr round-trips a double)."""
    return " ".join(repr(float(v)) for v in np.ravel(values))


def mjcf(system: SerialSystem, arm: Arm, timestep: float, armature: bool = False,
         damping: np.ndarray | None = None) -> str:
    """The MJCF of ``arm``: its links as nested bodies under a fixed base body at the arm's base
    pose in the world (the cochlea frame), ``system.gravity``, RK4 at ``timestep`` (s).

    ``armature``: each joint's declared armature (``armature_kgm2`` / ``armature_kg``) as the
    joint's ``armature`` (the plant's ``Ia`` on the mass matrix's diagonal); ``damping``: the
    plant's viscous coefficients per joint (N m s/rad or N s/m), written only where nonzero."""
    if not timestep > 0:
        raise ValueError(f"timestep must be a positive number of seconds, got {timestep!r}")
    damping = np.zeros(len(arm.links)) if damping is None else np.asarray(damping, float)
    lines = [f"<mujoco model={quoteattr(f'{system.name}_{arm.name}')}>",
             '  <compiler angle="radian" inertiafromgeom="false" autolimits="false"/>',
             f'  <option timestep="{timestep!r}" integrator="RK4" '
             f'gravity="{_numbers(system.gravity)}">',
             '    <flag contact="disable"/>',
             "  </option>",
             "  <worldbody>",
             f"    <body name={quoteattr(f'{arm.name}_base')} pos=\"{_numbers(arm.base_xyz)}\" "
             f'quat="{_numbers(quaternion(arm.base_rotation))}">']
    indent = "    "
    for i, link in enumerate(arm.links):
        joint = link.joint
        indent += "  "
        name = joint.name or f"joint{i + 1}"
        lines.append(f"{indent}<body name={quoteattr(link.name)} "
                     f'pos="{_numbers(joint.origin_xyz)}" '
                     f'quat="{_numbers(quaternion(joint_rotation(joint)))}">')
        attributes = [f"name={quoteattr(name)}",
                      f'type="{"hinge" if joint.type == "revolute" else "slide"}"',
                      'pos="0 0 0"', f'axis="{_numbers(joint.axis)}"', 'limited="false"']
        if armature and joint.actuator.armature is not None:
            attributes.append(f'armature="{joint.actuator.armature!r}"')
        if damping[i] != 0.0:
            attributes.append(f'damping="{float(damping[i])!r}"')
        lines.append(f"{indent}  <joint {' '.join(attributes)}/>")
        I = np.asarray(link.inertia_com, float)  # about the centre of mass, link-frame axes
        six = [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]]
        lines.append(f'{indent}  <inertial pos="{_numbers(link.com)}" mass="{link.mass!r}" '
                     f'fullinertia="{_numbers(six)}"/>')
    for _ in arm.links:
        lines.append(f"{indent}</body>")
        indent = indent[:-2]
    lines += ["    </body>", "  </worldbody>", "</mujoco>", ""]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# The check and the times
# --------------------------------------------------------------------------------------------


def relative(a, b, scale=None) -> float:
    """``max|a - b|`` over ``max|scale|`` (default ``b``): the worst difference relative to the
    largest value it is measured against."""
    a, b = np.ravel(np.asarray(a, float)), np.ravel(np.asarray(b, float))
    scale = b if scale is None else np.ravel(np.asarray(scale, float))
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(scale))), 1e-300))


def random_states(u, count: int, seed: int = SEED) -> list[tuple[np.ndarray, ...]]:
    """``(q, qd, tau)`` uniform within every joint's position, velocity and effort limits."""
    rng = np.random.default_rng(seed)
    joints = u.plant_model.joints
    low = np.array([j.position_limits[0] for j in joints])
    high = np.array([j.position_limits[1] for j in joints])
    vmax = np.array([j.velocity_limit for j in joints])
    fmax = np.array([j.effort_limit for j in joints])
    return [(rng.uniform(low, high), rng.uniform(-vmax, vmax), rng.uniform(-fmax, fmax))
            for _ in range(count)]


def plant_step(kernel, inputs: list[np.ndarray]) -> np.ndarray:
    """One call of a library kernel (``cochlea.kernels.library``) on ``inputs``, in order."""
    for signature, value in zip(kernel.signature.inputs, inputs):
        kernel[signature.name][...] = value
    kernel()
    return np.array(next(iter(kernel.outputs.values())), float).ravel()


def check(mujoco, model, u, kernel, period: float) -> dict:
    """The worst relative differences of MuJoCo's ``qacc`` from the forward dynamics and of its
    RK4 step from the C plant step, over :data:`STATES` random states and torques."""
    data = mujoco.MjData(model)
    n = u.plant_model.nq
    fd = u.plant_model.forward_dynamics_p
    worst_qacc = worst_step = 0.0
    for q, qd, tau in random_states(u, STATES):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q, qd, tau
        mujoco.mj_forward(model, data)
        ours = np.array(fd(q, qd, tau - u.friction * qd, u.plant_params), float).ravel()
        worst_qacc = max(worst_qacc, relative(data.qacc, ours))
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q, qd, tau
        mujoco.mj_step(model, data)
        x = np.concatenate([q, qd])
        x_next = plant_step(kernel, [x, tau, u.plant_params, u.friction, np.array(period)])
        theirs = np.concatenate([data.qpos, data.qvel])
        worst_step = max(worst_step, relative(theirs - x, x_next - x))
        if x_next.shape != (2 * n,):
            raise RuntimeError(f"{kernel.name}: expected {2 * n} outputs, got {x_next.shape}")
    return {"qacc_max_rel": worst_qacc, "step_max_rel": worst_step}


def build_harness(mujoco) -> Path:
    """bench/../build/bench/time_mujoco, compiled against the wheel's headers and library."""
    package = Path(mujoco.__file__).parent
    include = package / "include"
    libraries = sorted(package.glob("libmujoco.so*"))
    if not (include / "mujoco" / "mujoco.h").is_file() or not libraries:
        raise RuntimeError(f"the mujoco wheel in {package} ships no C headers or library")
    WORK.mkdir(parents=True, exist_ok=True)
    source, program = WORK / "time_mujoco.c", WORK / "time_mujoco"
    source.write_text(HARNESS)
    subprocess.run(["cc", "-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", f"-I{include}",
                    "-o", str(program), str(source), str(libraries[0]),
                    f"-Wl,-rpath,{package}"], check=True, capture_output=True)
    return program


def time_mujoco_c(program: Path, xml: Path, state: np.ndarray, reps: int = 51,
                  calls: int = 2000) -> tuple[float, str]:
    """mj_step in C (s per step) from ``state`` every call, and MuJoCo's version string."""
    path = WORK / "mujoco.state"
    np.asarray(state, float).tofile(path)
    out = subprocess.run([str(program), str(xml), str(path), str(reps), str(calls)],
                         check=True, capture_output=True, text=True).stdout.split()
    return float(out[0]) * 1e-9, out[1]


def time_rollout(mujoco, model, x0: np.ndarray, steps: int = 2000, reps: int = 21) -> float:
    """``mujoco.rollout`` (C) of ``steps`` steps from ``x0`` with no torque: s per step."""
    from mujoco import rollout

    data = mujoco.MjData(model)
    n = model.nq
    data.qpos[:], data.qvel[:] = x0[:n], x0[n:]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    initial = np.empty(mujoco.mj_stateSize(model, spec))
    mujoco.mj_getState(model, data, initial, spec)
    rollout.rollout(model, data, initial, nstep=steps)  # warm up
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        rollout.rollout(model, data, initial, nstep=steps)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) / steps


def time_python(mujoco, model, x0: np.ndarray, calls: int = 2000, reps: int = 21) -> float:
    """``mujoco.mj_step`` called from Python, from ``x0`` every call: s per step."""
    data = mujoco.MjData(model)
    n = model.nq
    q0, qd0 = x0[:n].copy(), x0[n:].copy()
    times = []
    for _ in range(reps + 1):
        t0 = time.perf_counter()
        for _ in range(calls):
            data.qpos[:] = q0
            data.qvel[:] = qd0
            mujoco.mj_step(model, data)
        times.append((time.perf_counter() - t0) / calls)
    return statistics.median(times[1:])


def load_average() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def bench(lib, time_kernel: Callable[[str, list[np.ndarray]], float]) -> dict:
    """The section: the check, then (if it passes) both steps timed in C and their ratio.

    ``lib``: the loaded libcochlea.so (``cochlea.kernels.library.load()``); ``time_kernel(name,
    inputs)``: a kernel's time per call in C (bench/run.py's ``time_in_c``)."""
    try:
        import mujoco
    except ImportError as error:
        raise RuntimeError("mujoco is not installed: pip install -e '.[bench]' (make bench "
                           "installs the bench extra)") from error
    from cochlea.sim import compiled as csim

    sc = load_scenario(SCENARIO)
    u = unit_setups(sc)[0]
    system = load_serial(u.plant_model.source)
    arm = system.arm(u.name)
    kernels = csim.unit_kernels(lib, u, sc.plant_substeps)
    xml = mjcf(system, arm, sc.period, armature=u.plant_model.actuators != "none",
               damping=u.friction)
    WORK.mkdir(parents=True, exist_ok=True)
    xml_path = WORK / f"{SCENARIO}_{arm.name}.xml"
    xml_path.write_text(xml)
    model = mujoco.MjModel.from_xml_path(str(xml_path))
    row = {"scenario": SCENARIO, "unit": u.name, "period_s": sc.period,
           "plant_substeps": sc.plant_substeps, "plant_kernel": kernels.plant,
           "plant_operations": u.plant_function(sc.plant_substeps).n_instructions(),
           "mujoco": mujoco.__version__, "states": STATES, "tolerance": TOLERANCE,
           "xml": str(xml_path.relative_to(ROOT)), "load_before": load_average(),
           **check(mujoco, model, u, lib.kernel(kernels.plant), sc.period)}
    row["same_arm"] = max(row["qacc_max_rel"], row["step_max_rel"]) <= TOLERANCE
    print(f"  MuJoCo {mujoco.__version__}: qacc within {row['qacc_max_rel']:.1e}, RK4 step "
          f"within {row['step_max_rel']:.1e} of cochlea's ({STATES} states)", flush=True)
    if not row["same_arm"]:
        return row
    n = u.plant_model.nq
    x0, tau0 = np.asarray(u.plant_x0, float), np.zeros(n)
    row["plant_c_s"] = time_kernel(kernels.plant, [x0, tau0, u.plant_params, u.friction,
                                                   np.array(sc.period)])
    row["mujoco_c_s"], row["mujoco_c_version"] = time_mujoco_c(
        build_harness(mujoco), xml_path, np.concatenate([x0, tau0]))
    row["mujoco_rollout_s"] = time_rollout(mujoco, model, x0)
    row["mujoco_python_s"] = time_python(mujoco, model, x0)
    row["ratio"] = row["mujoco_c_s"] / row["plant_c_s"]
    row["load_after"] = load_average()
    print(f"  plant step {row['plant_c_s'] * 1e6:.3f} us, MuJoCo mj_step "
          f"{row['mujoco_c_s'] * 1e6:.3f} us in C ({row['ratio']:.1f}x), rollout "
          f"{row['mujoco_rollout_s'] * 1e6:.3f} us, from Python "
          f"{row['mujoco_python_s'] * 1e6:.2f} us", flush=True)
    return row


def markdown(row: dict | None, reason: list[str] = ()) -> list[str]:
    """The section of results.md; ``row`` None: it did not run, ``reason`` says why."""
    out = ["", TITLE, ""]
    if not row:
        return out + list(reason) + [PARALLEL_NOTE]
    out.append(
        f"MuJoCo {row['mujoco']}, the MJCF written from the description as cochlea loads it "
        f"(bench/mujoco_compare.py, `{row['xml']}`): {row['unit']} of {row['scenario']}, RK4 "
        f"at the plant's period, {row['period_s'] * 1e3:g} ms, contacts off, the torque held "
        f"as `qfrc_applied`. Checked first at {row['states']} random states and torques "
        f"within the joints' limits: MuJoCo's `qacc` (mj_forward) against cochlea's forward "
        f"dynamics, worst {row['qacc_max_rel']:.1e} relative; one `mj_step` against the "
        f"generated plant step `{row['plant_kernel']}`, worst {row['step_max_rel']:.1e} "
        f"relative to the step's change of state (tolerance {row['tolerance']:g}).")
    out.append("")
    if not row["same_arm"]:
        return out + [f"**Not the same arm** (a difference above {row['tolerance']:g}): no "
                      "time or ratio is reported.", "", PARALLEL_NOTE]
    out += ["Per step, from the same state every call (the scenario's initial state, no "
            "torque). *plant step, C*: the generated kernel timed in C (bench/time_kernel.c, "
            f"{row['plant_substeps']} RK4 sub-step, {row['plant_operations']} operations); "
            "*mj_step, C*: MuJoCo's step in a C loop against the wheel's libmujoco; "
            "*rollout*: `mujoco.rollout` (MuJoCo's C rollout, a free trajectory); *from "
            "Python*: `mujoco.mj_step` in a Python loop.", "",
            "| plant step, C (us) | mj_step, C (us) | rollout (us) | mj_step from Python (us) "
            "| mj_step / plant step |", "|---|---|---|---|---|",
            f"| {row['plant_c_s'] * 1e6:.3f} | {row['mujoco_c_s'] * 1e6:.3f} | "
            f"{row['mujoco_rollout_s'] * 1e6:.3f} | {row['mujoco_python_s'] * 1e6:.2f} | "
            f"{row['ratio']:.1f}x |", "",
            f"Load average (1 min) {row['load_before']:.2f} before and "
            f"{row['load_after']:.2f} after the section.", "", PARALLEL_NOTE]
    return out


def main() -> int:
    """``python bench/mujoco_compare.py``: the section alone, printed as markdown."""
    sys.path.insert(0, str(ROOT / "bench"))
    import run as bench_run

    from cochlea.kernels import library as ckernels

    harness, lib = bench_run.compile_helpers()[1], ckernels.load()
    row = bench(lib, lambda name, inputs: bench_run.time_kernel(harness, lib, name, inputs))
    print("\n".join(markdown(row)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
