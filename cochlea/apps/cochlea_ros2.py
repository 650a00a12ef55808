"""``cochlea-ros2``: a run on ROS 2 topics (optional extra ``ros``; docs/logs.md, "Live on
ROS 2"), published by this process, outside the run's 1 kHz loop:

    cochlea-ros2 follow RUN_DIR [--scenario S] [--rate HZ]   # a real-time run as it runs
    cochlea-ros2 replay RUN_DIR [--rate HZ]                  # a finished run, at its pace

``follow`` reads the run's ``log.bin`` as the run's log writer appends it (every 0.2 s),
never writing to the run's folder, and publishes the newest row at ``--rate``; it ends when
the run's ``summary.json`` appears (exit 0) or when no row came for ``--idle`` seconds without
one (the run died: exit 3). ``cochlea-run --ros2`` starts it beside a real-time run.

Exit codes: 0 done; 2 bad input (not a run folder, a damaged log, ``--rate`` not finite and
> 0, an unknown scenario), one line on stderr; 3 the run's log did not appear or stopped
growing without a summary; 4 ROS 2 (rclpy, sensor_msgs, std_msgs) is not installed; 130
interrupted.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..console import OneLineParser
from ..errors import EXIT_USER_ERROR, CochleaError, printable
from ..export.run_log import open_run
from ..ros2.node import Publisher, load_ros
from ..ros2.source import (
    Described,
    RawTail,
    check_rate,
    describe_scenario,
    raw_units,
    robot_description,
)

PROG = "cochlea-ros2"
EXIT_NO_LOG = 3
EXIT_NO_ROS = 4
DEFAULT_RATE_HZ = 50.0
#: How far (s) behind the newest row of log.bin the follower plays the run: more than the
#: log writer's interval (0.2 s), so it never waits for the next batch.
LAG_S = 0.5


class NoRos(CochleaError):
    pass


class NoLog(CochleaError):
    pass


def _number(text: str, option: str) -> float:
    """A finite number > 0 from the command line, or one line (CochleaError)."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value <= 0:
        raise CochleaError(f"{option} {text}: expected a finite number > 0")
    return value


def _check(args) -> None:
    args.rate = check_rate(_number(args.rate, "--rate"))
    for option in ("wait", "idle"):
        if hasattr(args, option):
            setattr(args, option, _number(getattr(args, option), f"--{option}"))


def _ros():
    try:
        return load_ros()
    except CochleaError as exc:
        raise NoRos(str(exc)) from None


def _folder(path: Path) -> Path:
    if not path.is_dir():
        what = "missing" if not os.path.lexists(path) else "not a folder"
        raise CochleaError(f"RUN_DIR {path} is {what}: name a run's output folder")
    return path


def _tick(next_time: float, period: float) -> float:
    """Sleep until ``next_time`` (monotonic s); the next tick, never in the past (a bridge
    that fell behind skips rows, it does not catch up)."""
    delay = next_time - time.monotonic()
    if delay > 0:
        time.sleep(delay)
    return max(next_time + period, time.monotonic())


def follow(args) -> int:
    folder = _folder(args.run_dir)
    try:
        os.nice(10)  # the run's loop comes first on a shared machine
    except OSError:
        pass
    deadline = time.monotonic() + args.wait
    while not (folder / "log.columns.json").exists():
        if (folder / "summary.json").exists():
            raise CochleaError(f"{folder} is a finished run without log.bin (an as-fast run?): "
                               f"use {PROG} replay")
        if time.monotonic() > deadline:
            raise NoLog(f"{folder}: no log.columns.json after {args.wait:g} s: not a real-time "
                        "run that is starting")
        time.sleep(0.05)
    tail = RawTail(folder)
    if (folder / "summary.json").exists() and tail.rows_written() == 0:
        raise CochleaError(f"{folder} is a finished run without log.bin (or with no row in it): "
                           f"nothing to follow; use {PROG} replay")
    if args.scenario is not None:
        adapter, system = describe_scenario(args.scenario)
    elif (folder / "summary.json").exists():
        run = open_run(folder)
        adapter, system = run.adapter, run.system
    else:
        raise CochleaError(f"{folder} is a run still going: name its scenario with --scenario "
                           "(cochlea-run --ros2 does)")
    described = Described(adapter, system, raw_units(adapter, system, tail.names, tail.bin))
    ros = _ros()
    publisher = _publisher(ros, described)
    # The log writer appends a batch of rows every 0.2 s: the rows are played at the run's own
    # pace, LAG_S behind the newest, so they come out at --rate rather than in bursts.
    period, last, idle_since = 1.0 / args.rate, -1, time.monotonic()
    known, times, offset = 0, np.empty(0), None  # times: of rows last + 1 .. known - 1
    next_time = time.monotonic()
    try:
        while True:
            finished = (folder / "summary.json").exists()  # before the count: rows all in
            n = tail.rows_written()
            if n > known:
                times = np.concatenate([times, tail.times(known, n)])
                known, idle_since = n, time.monotonic()
                if offset is None:  # from the newest row on: a live view, not a catch-up
                    offset = time.monotonic() - times[-1] + LAG_S
            if offset is not None and len(times):
                # The newest row due by now (the rows before it are skipped).
                due = int(np.searchsorted(times, time.monotonic() - offset, side="right"))
                if due:
                    last += due
                    times = times[due:]
                    publisher.publish(tail.row(last))
            if finished and last == known - 1:
                break
            if not finished and time.monotonic() - idle_since > args.idle:
                raise NoLog(f"{folder}: no new row for {args.idle:g} s and no summary.json: "
                            f"the run ended without its report; published {publisher.published} "
                            "rows")
            next_time = _tick(next_time, period)
    finally:
        publisher.close()
    print(printable(f"{PROG}: {folder}: published {publisher.published} rows of {known} at up to "
                    f"{args.rate:g} Hz" + ("" if publisher.tf_pub is not None else
                                           "; /tf not published (no tf2_msgs)")))
    return 0


def _publisher(ros, described):
    publisher = Publisher(ros, described, robot_description(described))
    if publisher.tf_pub is None:
        print(f"{PROG}: warning: tf2_msgs is not installed (no wheel on the package index: "
              "python -m cochlea.ros2.tf2_msgs_build builds it): /joint_states and "
              "/robot_description only, no /tf", file=sys.stderr, flush=True)
    return publisher


def replay(args) -> int:
    run = open_run(_folder(args.run_dir))
    described = Described(run.adapter, run.system, run.units)
    ros = _ros()
    publisher = _publisher(ros, described)
    period = 1.0 / args.rate
    start, first, due = time.monotonic(), None, -math.inf
    try:
        for rows in run.chunks():
            for k in range(len(rows)):
                t = float(rows[k, 0])
                if first is None:
                    first = t
                if t < due:
                    continue
                delay = start + (t - first) - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                publisher.publish(rows[k:k + 1])
                due = t + period
    finally:
        publisher.close()
    print(printable(f"{PROG}: {run.folder}: replayed {publisher.published} rows at up to "
                    f"{args.rate:g} Hz"))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    f = sub.add_parser("follow", help="publish a real-time run while it runs")
    r = sub.add_parser("replay", help="publish a finished run at its own pace")
    for p in (f, r):
        p.add_argument("run_dir", type=Path, metavar="RUN_DIR")
        p.add_argument("--rate", default=str(DEFAULT_RATE_HZ), metavar="HZ",
                       help=f"publishing rate, Hz (default {DEFAULT_RATE_HZ:g})")
    f.add_argument("--scenario", metavar="NAME_OR_FILE",
                   help="the run's scenario (its robot description), while summary.json is "
                        "not yet written")
    f.add_argument("--wait", default="30", metavar="S",
                   help="seconds to wait for the run's log.columns.json (default 30)")
    f.add_argument("--idle", default="30", metavar="S",
                   help="seconds without a new row, before the summary, that end the follower "
                        "(default 30)")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse's own usage line and exit code 2
        return int(exc.code or 0)
    try:
        _check(args)
        return (follow if args.command == "follow" else replay)(args)
    except NoRos as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_NO_ROS
    except NoLog as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_NO_LOG
    except CochleaError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
