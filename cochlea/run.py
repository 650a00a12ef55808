"""``cochlea-run``: run a controller on the simulated robot and leave a log, a summary and plots.

Exit codes: 0 the run finished (``summary.json`` says whether it converged), 2 the user's input
is wrong (options, scenario, description, an unreachable target: nothing ran), 3 the simulation
diverged (the log up to that period is written).
"""

from __future__ import annotations

import argparse
import sys
import time
from datetime import datetime
from pathlib import Path

from .errors import EXIT_USER_ERROR, CochleaError

EXIT_DIVERGED = 3


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="cochlea-run",
        description="Run one of the four robust adaptive controllers on the simulated robot "
                    "(as fast as possible) and write log.csv, summary.json and PNG figures.",
        epilog="Example: cochlea-run --robot serial --space task --out runs/first. Without "
               "--scenario the thesis's study for that robot and space is used "
               "(models/scenarios/ROBOT_SPACE.toml).",
    )
    p.add_argument("--robot", required=True, choices=["serial", "parallel"],
                   help="serial: the two 3R arms; parallel: the 5-DoF mechanism")
    p.add_argument("--space", required=True, choices=["joint", "task"],
                   help="joint: controllers e/f; task: controllers g/d")
    p.add_argument("--scenario", help="scenario TOML (default: the thesis's study)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="simulated seconds (default: the scenario's)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output folder (default: runs/ROBOT_SPACE_YYYYmmdd-HHMMSS)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except CochleaError as exc:
        print(f"cochlea-run: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR


def _run(args: argparse.Namespace) -> int:
    from . import report
    from .simulation import load_scenario, simulate, unit_setups

    scenario = load_scenario(args.scenario or f"{args.robot}_{args.space}")
    if (scenario.robot, scenario.space) != (args.robot, args.space):
        raise CochleaError(f"scenario {scenario.path} is for --robot {scenario.robot} --space "
                           f"{scenario.space}, not --robot {args.robot} --space {args.space}: "
                           "change the options or the scenario")
    if args.duration is not None and not args.duration > 0:
        raise CochleaError(f"--duration must be positive, got {args.duration}")
    setups = unit_setups(scenario)  # validates reachability before anything runs
    out = args.out or Path("runs") / (f"{args.robot}_{args.space}_"
                                      f"{datetime.now().strftime('%Y%m%d-%H%M%S')}")
    print(f"cochlea-run: {scenario.name} (controller {scenario.controller}, "
          f"{scenario.variant} variant) -> {out}")
    start = time.perf_counter()
    result = simulate(scenario, args.duration, setups)
    wall = time.perf_counter() - start
    data = report.write_all(result, out, wall)
    print(f"  simulated {data['duration_s']:.2f} s in {wall:.2f} s "
          f"({data['duration_s'] / wall:.1f}x real time)")
    for name, unit in data["units"].items():
        for coord, c in unit["tracked"].items():
            print(f"  {name}.{coord}: initial |e| {c['initial_abs_error']:.3e} {c['unit']}, "
                  f"final RMS {c['final_rms_error']:.3e} {c['unit']}"
                  f"{'' if c['converged'] else '  NOT CONVERGED'}")
    print(f"  converged: {'yes' if data['converged'] else 'no'}; log: {out / 'log.csv'}; "
          f"summary: {out / 'summary.json'}; figures: {len(data['figures'])} PNG in {out}")
    if result.diverged:
        for name, t in result.diverged.items():
            print(f"cochlea-run: {name} diverged at t = {t:.3f} s (log kept up to there)",
                  file=sys.stderr)
        return EXIT_DIVERGED
    return 0
