"""A user's robot on C kernels (issue 25, item 4; docs/codegen.md, "Your own robot's C
kernels"), measured in one run, as ratios (this machine is shared: absolute figures drift by
10-30 % between runs, ratios taken in one run much less):

1. generation + compilation of a 6-DoF arm's kernels: UR5, imported from the example-robot-data
   URDF with ``cochlea-urdf import`` (its starter scenario: joint space, controller e), then
   ``cochlea-codegen --scenario starter.toml --out DIR`` (wall time of each stage; target 60 s
   on 2 cores);
2. the as-fast run of user robots (UR5, a 4-DoF arm imported from tests/data/arm4.urdf, its
   slider made revolute, and the planar 2-DoF example models/examples/planar2_xm540.toml) on
   their C kernels against CasADi, and their real-time factor per joint (real-time factor x
   joints) against the shipped serial study's on its C kernels
   (serial_joint: two 3-joint arms), each the median of several full-length runs (target:
   >= 80 % of the shipped arms' per joint); also with every unit on one thread (``simulate(...,
   threads=False)``): the shipped study's two arms otherwise run on a thread each, two cores
   for its 6 joints against one for a single arm's.

    .venv/bin/python bench/user_robot.py [--duration S] [--out bench/user_robot.json]

Writes the JSON and prints a Markdown table (docs/codegen.md quotes it).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import statistics
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT)]

from cochlea.apps import cochlea_codegen, cochlea_urdf  # noqa: E402
from cochlea.sim import load_scenario, simulate, unit_setups  # noqa: E402


def wall(fn, reps: int) -> float:
    times = []
    for _ in range(reps):
        gc.collect()
        gc.disable()
        try:
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        finally:
            gc.enable()
    return statistics.median(times)


def ur5_urdf() -> Path:
    dist = metadata.distribution("example-robot-data")
    return Path(str(dist.locate_file(
        "cmeel.prefix/share/example-robot-data/robots/ur_description/urdf/ur5_robot.urdf")))


def imported(urdf: Path, folder: Path) -> Path:
    folder.mkdir(parents=True)
    assert cochlea_urdf.main(["import", str(urdf), "--out", str(folder / "robot.toml"),
                              "--scenario-out", str(folder / "starter.toml")]) == 0
    return folder / "starter.toml"


def generated(scenario: Path, out: Path) -> dict:
    """Generation and compilation, timed apart (the command's two stages)."""
    t0 = time.perf_counter()
    config, kernels, loops = cochlea_codegen.scenario_kernels(scenario)
    cochlea_codegen.write_kernels(config, kernels, loops, out)
    t1 = time.perf_counter()
    cochlea_codegen.compile_library(out)
    t2 = time.perf_counter()
    return {"generate_s": t1 - t0, "compile_s": t2 - t1, "total_s": t2 - t0,
            "c_bytes": sum(p.stat().st_size for p in out.glob("*.c")), "cores": os.cpu_count()}


def run_speed(sc, duration: float, library=None) -> dict:
    """The as-fast run on C (the units on a thread each, as ``simulate`` runs them, and one
    after the other on one thread: the shipped study's two arms otherwise share two cores)
    and on CasADi."""
    setups = unit_setups(sc)
    joints = sum(u.controller_model.nq for u in setups)
    c = wall(lambda: simulate(sc, duration, setups, kernels="c", library=library), 5)
    one = wall(lambda: simulate(sc, duration, setups, kernels="c", library=library,
                                threads=False), 5)
    casadi = wall(lambda: simulate(sc, duration, setups, kernels="casadi"), 1)
    return {"joints": joints, "duration_s": duration, "c_s": c, "c_one_thread_s": one,
            "casadi_s": casadi, "rtf_c": duration / c, "rtf_casadi": duration / casadi,
            "rtf_per_joint_c": joints * duration / c,
            "rtf_per_joint_c_one_thread": joints * duration / one,
            "rtf_per_joint_casadi": joints * duration / casadi, "c_over_casadi": casadi / c}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--duration", type=float, default=20.0, help="seconds simulated per run")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "user_robot.json")
    args = p.parse_args()
    results: dict = {"load_average": os.getloadavg()}
    with tempfile.TemporaryDirectory(prefix="cochlea-bench-user-") as tmp:
        tmp = Path(tmp)
        arm4 = tmp / "arm4r.urdf"
        arm4.write_text((ROOT / "tests" / "data" / "arm4.urdf").read_text().replace(
            'name="extend" type="prismatic"', 'name="extend" type="revolute"'))
        # planar2: the shipped example of a user's planar arm (two XM540s), written by hand
        robots = {"ur5": imported(ur5_urdf(), tmp / "ur5"), "arm4": imported(arm4, tmp / "arm4"),
                  "planar2": ROOT / "models" / "examples" / "planar2_xm540_joint.toml"}
        for name, scenario in robots.items():
            results[name] = {"codegen": generated(scenario, tmp / name / "kernels")}
            print(f"{name}: generated and compiled in {results[name]['codegen']['total_s']:.1f} s",
                  flush=True)
        shipped = run_speed(load_scenario("serial_joint"), args.duration)
        results["serial_joint"] = shipped
        for name, scenario in robots.items():
            speed = run_speed(load_scenario(scenario), args.duration, tmp / name / "kernels")
            speed["per_joint_vs_shipped"] = (speed["rtf_per_joint_c"]
                                             / shipped["rtf_per_joint_c"])
            speed["per_joint_vs_shipped_one_thread"] = (
                speed["rtf_per_joint_c_one_thread"] / shipped["rtf_per_joint_c_one_thread"])
            results[name]["run"] = speed
    args.out.write_text(json.dumps(results, indent=1) + "\n")
    print("\n| robot | joints | generate + compile (s) | RTF on C | RTF on CasADi | C / CasADi "
          "| RTF x joints on C, vs the shipped serial arms | the same, one thread |")
    print("|---|---|---|---|---|---|---|---|")
    s = results["serial_joint"]
    print(f"| serial_joint (shipped) | {s['joints']} | -- | {s['rtf_c']:.0f} | "
          f"{s['rtf_casadi']:.1f} | {s['c_over_casadi']:.0f}x | {s['rtf_per_joint_c']:.0f} "
          f"(100 %) | {s['rtf_per_joint_c_one_thread']:.0f} (100 %) |")
    for name in ("planar2", "arm4", "ur5"):
        r, g = results[name]["run"], results[name]["codegen"]
        print(f"| {name} (user) | {r['joints']} | {g['generate_s']:.1f} + {g['compile_s']:.1f} "
              f"| {r['rtf_c']:.0f} | {r['rtf_casadi']:.1f} | {r['c_over_casadi']:.0f}x | "
              f"{r['rtf_per_joint_c']:.0f} ({100 * r['per_joint_vs_shipped']:.0f} %) | "
              f"{r['rtf_per_joint_c_one_thread']:.0f} "
              f"({100 * r['per_joint_vs_shipped_one_thread']:.0f} %) |")
    print(f"\nload average {results['load_average'][0]:.2f}; written {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
