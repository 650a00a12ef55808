"""The sweep's figures of merit (docs/sweeps.md), a standalone script (not in ``make bench``:
it starts Dask clusters and takes minutes):

1. samples per second per core of each of the four thesis studies at full length (20 s),
   serially in this process: scenario file, set-ups, C simulation, supervisor verdict and
   summary per sample, as a sweep's worker does it (CPU time and wall time);
2. parallel efficiency of a sweep on a LocalCluster of 2 processes against 1;
3. the same sweep through a separately started ``dask scheduler`` and two ``dask worker``
   processes (the lab-cluster path, end to end).

    .venv/bin/python bench/sweep_bench.py [--samples N] [--duration S]

The machine's load average is printed with the numbers: on a shared machine the wall times
(and so the efficiencies) say as much about the neighbours as about the sweep.
"""

from __future__ import annotations

import argparse
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

from cochlea.apps import cochlea_sweep  # noqa: E402
from cochlea.sweep import execute  # noqa: E402
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


def serial(folder: Path, samples: int) -> None:
    print("## Samples per second per core (serial, full-length studies)\n")
    print("| study | samples | CPU s per sample | samples/s/core (CPU) | wall s per sample |")
    print("| --- | --- | --- | --- | --- |")
    cochlea_sweep.warm()
    for study in STUDIES:
        spec = sweep_spec.load(spec_file(folder, study, samples, None))
        execute.run_batch(spec, [0], cochlea_sweep.evaluate)  # first-call costs aside
        cpu0, wall0 = time.process_time(), time.perf_counter()
        execute.run_batch(spec, list(range(samples)), cochlea_sweep.evaluate)
        cpu = (time.process_time() - cpu0) / samples
        wall = (time.perf_counter() - wall0) / samples
        print(f"| {study} | {samples} | {cpu:.3f} | {1 / cpu:.2f} | {wall:.3f} |", flush=True)
    print()


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
    args = p.parse_args()
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} at start\n")
    with tempfile.TemporaryDirectory(prefix="sweep-bench-") as tmp:
        folder = Path(tmp)
        serial(folder, args.samples)
        parallel(folder, args.sweep_samples, args.duration)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
