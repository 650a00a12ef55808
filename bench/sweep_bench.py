"""The sweep's figures of merit (docs/sweeps.md), a standalone script (not in ``make bench``:
it starts Dask clusters and takes minutes; ``make bench`` runs its serial part, :func:`serial`):

1. samples per second per core of each of the four thesis studies at full length (20 s serial,
   10 s parallel), serially in this process: scenario data, set-ups, C simulation, supervisor
   verdict and summary per sample, as a sweep's worker does it, in CPU time (process time: on a
   shared machine wall time measures the neighbours), with the set-ups from the worker's cache
   (:func:`cochlea.sim.setup.unit_setups`) and, for comparison, built again for every sample;
   then where a sample's CPU time goes;
2. parallel efficiency of a sweep on a LocalCluster of 2 processes against 1;
3. the same sweep through a separately started ``dask scheduler`` and two ``dask worker``
   processes (the lab-cluster path, end to end).

    .venv/bin/python bench/sweep_bench.py [--samples N] [--duration S] [--serial-only]

The machine's load average is printed with the numbers: on a shared machine the wall times
(and so the efficiencies) say as much about the neighbours as about the sweep.
"""

from __future__ import annotations

import argparse
import functools
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT)]
if __name__ == "__main__":
    # As a sweep's worker runs: its nanny starts it with one BLAS thread (distributed's
    # pre-spawn-environ), which must be set before numpy is imported. A sample wakes no BLAS
    # thread either way (docs/sweeps.md, third pass); only the pool's spin at numpy's import
    # (some 0.1 s of CPU, before anything is measured) is spared.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from cochlea.apps import cochlea_sweep, report  # noqa: E402
from cochlea.runtime import build_supervisor, verdict  # noqa: E402
from cochlea.runtime.supervisor import log_reductions  # noqa: E402
from cochlea.sim import compiled, load_scenario, simulate, unit_setups  # noqa: E402
from cochlea.sweep import execute, sampling  # noqa: E402
from cochlea.sweep import spec as sweep_spec  # noqa: E402

STUDIES = ("serial_joint", "serial_task", "parallel_joint", "parallel_task")
SPEC = """format = "cochlea-sweep/1"
scenario = "{scenario}"
samples = {samples}
seed = 1
{duration}
[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{choice = [0, 1, 2]}}
"""


def spec_file(folder: Path, scenario: str, samples: int, duration: float | None) -> Path:
    path = folder / f"{scenario}.toml"
    path.write_text(SPEC.format(scenario=scenario, samples=samples,
                                duration="" if duration is None else f"duration_s = {duration}"))
    return path


def _per_sample(spec, samples: int, cache: bool) -> tuple[float, float]:
    """CPU and wall s per sample of ``samples`` samples through ``run_batch``, the structure's
    first sample (a worker's one-off set-up) aside."""
    evaluate = functools.partial(cochlea_sweep.evaluate, cache=cache)
    execute.run_batch(spec, [0], evaluate)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    execute.run_batch(spec, list(range(samples)), evaluate)
    return (time.process_time() - cpu0) / samples, (time.perf_counter() - wall0) / samples


#: The parts of a sample :func:`breakdown` times, in the order a sample goes through them.
PARTS = ("scenario data", "scenario load", "set-ups", "C closed loop", "simulate (rest)",
         "supervisor verdict", "summary + row")


def group_size(spec) -> int:
    """How many of ``spec``'s samples ``cochlea_sweep.evaluate_many`` takes through each phase
    together (its GROUP_PERIODS, GROUP_SAMPLES)."""
    sc = load_scenario(cochlea_sweep.SAMPLE_FILE, data=sampling.scenario_data(spec, 0))
    held = cochlea_sweep.unit_periods(sc, len(unit_setups(sc)))
    return max(1, min(cochlea_sweep.GROUP_SAMPLES,
                      math.ceil(cochlea_sweep.GROUP_PERIODS / max(held, 1))))


def breakdown(spec, samples: int) -> dict[str, float]:
    """Where a cached sample's CPU time goes (s per sample): ``evaluate``'s steps one by one,
    the C closed loop (``run_c``, every unit) apart from the rest of ``simulate``, the samples
    in groups as ``evaluate_many`` takes a worker's batch (each phase for the whole group)."""
    parts = dict.fromkeys(PARTS, 0.0)
    run_c = compiled.run_c
    loop = [0.0]
    size = group_size(spec)

    def timed_run_c(*args, **kw):  # each unit's own CPU time (on threads or not)
        t0 = time.thread_time()
        try:
            return run_c(*args, **kw)
        finally:
            loop[0] += time.thread_time() - t0

    compiled.run_c = timed_run_c  # simulate_compiled looks it up at each call
    clock = time.process_time()

    def lap(name):
        nonlocal clock
        now = time.process_time()
        parts[name] += now - clock
        clock = now

    try:
        for first in range(0, samples, size):
            group = []
            for i in range(first, min(first + size, samples)):
                data = sampling.scenario_data(spec, i)  # what run_batch hands evaluate
                lap("scenario data")
                sc = load_scenario(cochlea_sweep.SAMPLE_FILE, data=data)  # as evaluate reads it
                lap("scenario load")
                group.append((sc, unit_setups(sc)))
                lap("set-ups")
            results_ = []
            for sc, setups in group:
                loop[0] = 0.0
                results_.append(simulate(sc, None, setups, threads=False))  # as evaluate runs it
                lap("simulate (rest)")
                parts["simulate (rest)"] -= loop[0]
                parts["C closed loop"] += loop[0]
            for (sc, setups), result in zip(group, results_):
                supervisor = build_supervisor(setups, sc.system.keep_out_radius,
                                              kernels="c", substeps=sc.plant_substeps,
                                              cache=True)
                reductions = [log_reductions(u) for u in result.units]  # read by both
                result.supervisor = verdict(result, supervisor, reductions)
                lap("supervisor verdict")
                limits = {u.name: {j.name: float(lim) for j, lim in
                                   zip(u.controller_model.joints, u.effort_limit)}
                          for u in setups}
                cochlea_sweep.measures(report.summary(result, 0.0, reductions=reductions,
                                                      row=True), limits)
                lap("summary + row")
    finally:
        compiled.run_c = run_c
    return {k: v / samples for k, v in parts.items()}


def serial(folder: Path, samples: int, uncached: int = 3) -> list[dict]:
    """Samples per core of each study (rows, also printed as a Markdown table), then where
    the time goes."""
    print("## Samples per second per core (serial, full-length studies, CPU time)\n")
    print("| study | s | samples | CPU s per sample | samples/s/core | set-ups built per sample: "
          "CPU s | wall s per sample | load average |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    cochlea_sweep.warm()
    rows = []
    for study in STUDIES:
        spec = sweep_spec.load(spec_file(folder, study, samples, None))
        load0 = os.getloadavg()[0]
        cpu, wall = _per_sample(spec, samples, cache=True)
        old, _ = _per_sample(spec, uncached, cache=False)
        load1 = os.getloadavg()[0]
        row = {"study": study, "duration_s": load_scenario(study).duration, "samples": samples,
               "cpu_s": cpu, "per_s_core": 1 / cpu, "uncached_cpu_s": old, "wall_s": wall,
               "load": (load0, load1), "parts": breakdown(spec, samples)}
        rows.append(row)
        print(f"| {study} | {row['duration_s']:g} | {samples} | {cpu:.4f} | {1 / cpu:.1f} | "
              f"{old:.3f} | {wall:.4f} | {load0:.1f}-{load1:.1f} |", flush=True)
    print("\n## Where a sample's CPU time goes (ms per sample)\n")
    names = list(rows[0]["parts"])
    print("| study | " + " | ".join(names) + " | total | outside / loop |")
    print("| --- |" + " --- |" * (len(names) + 2))
    for r in rows:
        parts = r["parts"]
        total, loop = sum(parts.values()), parts["C closed loop"]
        r["outside_share"] = (total - loop) / loop  # issue 30 item 3: under 10 %
        print(f"| {r['study']} | " + " | ".join(f"{parts[k] * 1e3:.2f}" for k in names)
              + f" | {total * 1e3:.2f} | {r['outside_share']:.0%} |")
    print()
    return rows


def _sweep(spec: Path, out: Path, **kw) -> dict:
    shutil.rmtree(out, ignore_errors=True)
    s = sweep_spec.load(spec)
    return execute.run(s, out, cochlea_sweep.evaluate, progress=False, warm=cochlea_sweep.warm,
                       **kw)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parallel(folder: Path, samples: int, duration: float) -> None:
    spec = spec_file(folder, "serial_task", samples, duration)
    print(f"## Parallel efficiency (serial_task, {samples} samples of {duration:g} s)\n")
    print("| run | workers | wall s (sweep) | batches | batch | efficiency |")
    print("| --- | --- | --- | --- | --- | --- |")
    one = _sweep(spec, folder / "one", workers=1)
    print(f"| LocalCluster | 1 | {one['wall_s']:.1f} | {one['batches']} | {one['batch']} | - |",
          flush=True)
    two = _sweep(spec, folder / "two", workers=2)
    print(f"| LocalCluster | 2 | {two['wall_s']:.1f} | {two['batches']} | {two['batch']} | "
          f"{one['wall_s'] / (2 * two['wall_s']):.0%} |", flush=True)
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    bin_dir = Path(sys.executable).parent
    procs = [subprocess.Popen([str(bin_dir / "dask"), "scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              start_new_session=True)]
    try:
        procs += [subprocess.Popen([str(bin_dir / "dask"), "worker", address, "--nthreads", "1",
                                    "--no-dashboard"], stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL, start_new_session=True)
                  for _ in range(2)]
        # Both workers first: the sweep may start on one, which is not what is measured.
        from distributed import Client

        with Client(address, timeout=60) as c:
            c.wait_for_workers(2, timeout=60)
        ext = _sweep(spec, folder / "ext", scheduler=address)
        print(f"| dask scheduler + 2 dask worker | {ext['workers']} | {ext['wall_s']:.1f} | "
              f"{ext['batches']} | {ext['batch']} | {one['wall_s'] / (2 * ext['wall_s']):.0%} |")
    finally:
        for p in reversed(procs):
            os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            p.wait()
    print("\nwall s (sweep) includes starting the LocalCluster's processes (not the separately "
          "started ones); efficiency = T(1 worker) / (2 T(2 workers)).")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--samples", type=int, default=5, help="per study, serial part (default 5)")
    p.add_argument("--sweep-samples", type=int, default=40, help="parallel part (default 40)")
    p.add_argument("--duration", type=float, default=5.0, help="parallel part: s (default 5)")
    p.add_argument("--serial-only", action="store_true", help="samples per core only (no Dask)")
    args = p.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start\n")
    with tempfile.TemporaryDirectory(prefix="sweep-bench-") as tmp:
        folder = Path(tmp)
        serial(folder, args.samples)
        if not args.serial_only:
            parallel(folder, args.sweep_samples, args.duration)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
