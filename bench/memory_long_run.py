"""Peak resident memory of a long run against its length: the real-time loop on the simulated
robot with the clock taken out (``realtime=False``: the same periods back to back), its log
streamed to ``log.bin``, then the report (``log.csv``, ``summary.json``, figures) read back from
it -- what ``cochlea-run`` does after a real-time run.

Each case runs in a subprocess of its own and reports its peak resident set (``VmHWM`` of
``/proc/self/status``) after setting up, after the loop and after the report. The acceptance of
issue 13: a one-hour run's peak within 20 % of a one-minute run's.

    .venv/bin/python bench/memory_long_run.py                     # 60 s and 3600 s, full report
    .venv/bin/python bench/memory_long_run.py --durations 20 200 --no-report
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def peak_rss_mb() -> float:
    """The process's peak resident set so far (MB), from the kernel's own high-water mark."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def case(scenario: str, duration: float, report: bool, out: Path,
         figures_only: bool = False) -> dict:
    """One run in this process: the loop, then the summary, and (``report``) log.csv and the
    figures, or (``figures_only``) the figures."""
    from cochlea.apps import report as reporting
    from cochlea.runtime import RealTimeLoop, SimBackend, build_supervisor
    from cochlea.sim import load_scenario, unit_setups

    sc = load_scenario(scenario)
    setups = unit_setups(sc)
    steps = int(round(duration * sc.rate_hz))
    backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=steps)
    supervisor = build_supervisor(setups, sc.system.keep_out_radius,
                                  substeps=sc.plant_substeps, watchdog_misses=500)
    loop = RealTimeLoop(setups, backend, supervisor, sc.period, steps, realtime=False,
                        substeps=sc.plant_substeps)
    out.mkdir(parents=True, exist_ok=True)
    figures = {"setup_MB": peak_rss_mb()}
    start = time.perf_counter()
    stop = loop.run(out / "log.bin")
    figures.update(loop_s=time.perf_counter() - start, after_loop_MB=peak_rss_mb())
    timing = loop.timing_summary()
    result = loop.result(sc)
    result.stop = {"rule": stop.rule, "time_s": stop.time, "detail": stop.detail,
                   "exit_code": stop.code}
    if report:
        start = time.perf_counter()
        data = reporting.write_all(result, out, None, timing)
        figures.update(report_s=time.perf_counter() - start, csv_MB=(out / "log.csv").stat(
            ).st_size / 2 ** 20, figures=len(data["figures"]))
    elif figures_only:  # the report's reading without the CSV's minutes of formatting
        reporting.summary(result, None, timing)
        figures.update(figures=len(reporting.figures(result, out)))
    else:
        reporting.summary(result, None, timing)
    figures.update(after_report_MB=peak_rss_mb(), periods=loop.rows, rule=stop.rule,
                   log_bin_MB=(out / "log.bin").stat().st_size / 2 ** 20)
    return {"scenario": scenario, "duration_s": duration, "report": report, **figures}


def measure(scenario: str, duration: float, report: bool) -> dict:
    """:func:`case` in a fresh interpreter, so each peak is that run's own."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, __file__, "--case", scenario, str(duration),
               "1" if report else "0", tmp]
        done = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--durations", type=float, nargs="+", default=[60.0, 3600.0], metavar="S")
    p.add_argument("--scenario", default="serial_task")
    p.add_argument("--no-report", action="store_true", help="the loop and the summary only")
    p.add_argument("--case", nargs=4, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.case:
        scenario, duration, report, out = args.case
        print(json.dumps(case(scenario, float(duration), report == "1", Path(out),
                              figures_only=report == "figures")))
        return 0
    rows = [measure(args.scenario, d, not args.no_report) for d in args.durations]
    for r in rows:
        print(json.dumps(r))
    first, last = rows[0], rows[-1]
    growth = last["after_report_MB"] / first["after_report_MB"] - 1
    print(f"peak RSS: {first['duration_s']:g} s run {first['after_report_MB']:.1f} MB, "
          f"{last['duration_s']:g} s run {last['after_report_MB']:.1f} MB "
          f"({100 * growth:+.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
