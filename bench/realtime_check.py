"""The runtime's acceptance measurement (not a test: it times the machine).

Runs the serial task-space study for its full 20 s twice -- in real time through
``cochlea-run`` (sim backend, supervisor, C kernels) and as fast as possible -- and checks that
deadline misses stay below 0.5 % of the periods and that the two runs' tracking results agree
(the real-time loop executes the same periods, so they should agree to rounding). Writes
``bench/realtime.md`` and ``bench/realtime.json``; exits 1 when a target is missed.

    make realtime-check
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MISS_TARGET = 0.005


def run(out: Path, *extra: str) -> dict:
    cmd = [sys.executable, "-m", "cochlea.apps.cochlea_run",
           "--robot", "serial", "--space", "task", "--out", str(out), "--status", "off", *extra]
    result = subprocess.run(cmd, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"{' '.join(cmd[3:])} failed ({result.returncode}):\n{result.stderr}")
    return json.loads((out / "summary.json").read_text())


def main() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        realtime = run(Path(tmp) / "realtime")
        fast = run(Path(tmp) / "fast", "--realtime", "off")
        rt_log = np.loadtxt(Path(tmp) / "realtime" / "log.csv", delimiter=",", skiprows=1)
        fast_log = np.loadtxt(Path(tmp) / "fast" / "log.csv", delimiter=",", skiprows=1)
    timing = realtime["timing"]
    columns = fast_log.shape[1]  # the real-time log adds timing columns at the end
    difference = float(np.max(np.abs(rt_log[:, :columns] - fast_log)))
    rows = []
    for unit, data in realtime["units"].items():
        for coord, c in data["tracked"].items():
            f = fast["units"][unit]["tracked"][coord]
            rows.append((f"{unit}.{coord}", c["unit"], c["final_rms_error"], f["final_rms_error"]))
    ok_misses = timing["deadline_miss_fraction"] < MISS_TARGET
    ok_tracking = difference < 1e-9 and realtime["converged"]
    load = os.getloadavg()
    data = {
        "machine": {"cpus": os.cpu_count(), "load_average_before_1_5_15": list(load),
                    "python": platform.python_version()},
        "timing": timing,
        "deadline_miss_target": MISS_TARGET,
        "deadline_misses_ok": ok_misses,
        "max_abs_log_difference_realtime_vs_fast": difference,
        "tracking_ok": ok_tracking,
        "final_rms": {name: {"unit": unit, "realtime": a, "fast": b}
                      for name, unit, a, b in rows},
    }
    (HERE / "realtime.json").write_text(json.dumps(data, indent=2) + "\n")
    lines = [
        "# Real-time check: serial task-space study, 20 s at 1 kHz (`make realtime-check`)",
        "",
        f"Machine: {os.cpu_count()} CPUs, load average {load[0]:.2f} / {load[1]:.2f} / "
        f"{load[2]:.2f} when the run started; loop scheduling: {timing['scheduling']}.",
        "",
        "| measure | value | target |",
        "|---|---|---|",
        f"| deadline misses | {timing['deadline_misses']} of {realtime['periods']} "
        f"({100 * timing['deadline_miss_fraction']:.3f} %) | below 0.5 % "
        f"({'met' if ok_misses else 'MISSED'}) |",
        f"| period p50 / p99 / max | {timing['period_p50'] * 1e3:.3f} / "
        f"{timing['period_p99'] * 1e3:.3f} / {timing['period_max'] * 1e3:.3f} ms | 1 ms |",
        f"| period mean / std | {timing['period_mean'] * 1e3:.4f} / "
        f"{timing['period_std'] * 1e3:.4f} ms | |",
        f"| compute p50 / p99 | {timing['compute_p50'] * 1e6:.0f} / "
        f"{timing['compute_p99'] * 1e6:.0f} us | |",
        f"| backend (plant) per period, mean / p99 | {timing['backend_mean'] * 1e6:.0f} / "
        f"{timing['backend_p99'] * 1e6:.0f} us | |",
        f"| largest difference, real-time log vs as-fast log | {difference:.1e} | equal "
        f"({'met' if ok_tracking else 'MISSED'}) |",
        "",
        "| coordinate | final RMS, real time | final RMS, as fast |",
        "|---|---|---|",
    ]
    lines += [f"| {n} | {a:.3e} {u} | {b:.3e} {u} |" for n, u, a, b in rows]
    (HERE / "realtime.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0 if ok_misses and ok_tracking else 1


if __name__ == "__main__":
    sys.exit(main())
