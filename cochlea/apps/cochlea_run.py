"""``cochlea-run``: run a robust adaptive controller and leave a log, a summary and plots.

By default the run is real time (1 kHz, absolute deadlines) on the simulated robot, watched by
the safety supervisor; ``--realtime off`` runs the same scenario as fast as possible.

Exit codes (also in the README):

====  ======================================================================================
 0    the run finished, or the user stopped it (Ctrl-C) after the safe sequence
 2    the user's input is wrong (options, scenario, description, unreachable target); nothing
      moved
 3    ``--realtime off``: the simulation diverged (the log up to that period is written)
 4    ``--desired-topic``: ROS 2 (rclpy, trajectory_msgs) is not installed; nothing moved
 5    the backend could not start (port, motors); nothing moved
 8    ``--desired-topic``: no trajectory on the topic within ``--desired-timeout``; nothing
      moved
 9    ``--desired-topic``: the trajectory failed a check (the line names the point or time and
      the rule); nothing moved
 10   safe stop: a joint left its position limits (10-14 also for ``--realtime off``: the rule
      a real run would have stopped on; the as-fast run went on, its log is complete)
 11   safe stop: a joint exceeded its velocity limit
 12   safe stop: a tool entered the keep-out circle of radius R_m
 13   safe stop: a non-finite state, command or estimate
 14   safe stop: a parameter estimate's norm exceeded its bound
 15   safe stop: watchdog: too many consecutive overruns, a stall, a loop too far behind its
      deadlines (docs/runtime.md, "Real-time options and the overrun policy"), or too many
      consecutive backend failures
 16   safe stop: terminated by SIGTERM, or by SIGHUP (a hang-up: the terminal or SSH session
      closed; summary.json's stop detail names it)
 17   safe stop: the log could not be written (full disk, I/O error, a writer too slow);
      log.bin holds the periods written before
 18   the run happened but part of its report (log.csv, figures, summary.json) is lost
 19   safe stop: ``mirror = "measured"``: a follower's desired pose, the dual-arm rule on its
      leader's measured pose, is out of its reach or not finite (also for ``--realtime off``,
      whose run ends there)
 129  hung up (SIGHUP) before the run started (or during ``--realtime off``); nothing moved
 130  interrupted (SIGINT) before the run started (or during ``--realtime off``); nothing moved
 143  terminated (SIGTERM) before the run started (or during ``--realtime off``); nothing
      moved
====  ======================================================================================
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import signal
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from ..console import OneLineParser, signals_held, tolerate_closed_stdout
from ..dynamixel.bridge import DynamixelBackend
from ..dynamixel.control_table import baud_code
from ..errors import EXIT_USER_ERROR, CochleaError
from ..kernels.library import ENVIRONMENT
from ..resources import SCENARIOS_DIR, shipped_file
from ..robots import ROBOTS
from ..robots.motor_fit import bridge_compensates_friction
from ..ros2 import desired as ros2_desired
from ..runtime import (
    EXIT_BACKEND,
    FIFO_PRIORITY,
    POLICIES,
    STOP_CODES,
    BackendError,
    RealTimeLoop,
    RealtimeOptions,
    SimBackend,
    build_supervisor,
    check_realtime_options,
    verdict,
    write_raw_columns,
)
from ..sim import KERNELS, choose_kernels, load_scenario, simulate, unit_setups
from ..sim.scenario import MAX_PERIODS, MAX_RATE_HZ, MIN_RATE_HZ, PLANT_PRESETS
from ..sim.setup import MAX_FAST_PERIODS, MIRROR_RULE, check_run_length
from ..text import number_argument, whole_argument
from . import outputs, report

EXIT_DIVERGED = 3
EXIT_INTERRUPTED = 130  # the shell's code for SIGINT
EXIT_TERMINATED = 143  # ... and for SIGTERM
EXIT_HUNG_UP = 129  # ... and for SIGHUP (a hang-up)
#: The run happened but part of its report (log.csv, figures, summary.json) is lost.
EXIT_REPORT_FAILED = 18
#: Half a second at 1 kHz: beyond that the loop is not controlling the motors at all.
MAX_WATCHDOG_MISSES = 500


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="cochlea-run",
        description="Run one of the four robust adaptive controllers of the thesis -- e "
                    "(serial, joint space), g (serial, task space), f (parallel, joint space), "
                    "d (parallel, task space) -- on the simulated robot, in real time under a "
                    "safety supervisor, and write log.csv, summary.json and PNG figures.",
        epilog="Examples:\n"
               "  cochlea-run --robot serial --space task          # the thesis study, real time\n"
               "  cochlea-run --robot parallel --space joint --realtime off --out runs/f\n"
               "Without --scenario the thesis's study for the robot and space is used "
               "(models/scenarios/ROBOT_SPACE.toml). Ctrl-C stops safely (zero effort, "
               "drives off) and keeps the log. Exit codes: see README.md.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robot", required=True, choices=list(ROBOTS),
                   help="serial: the two 3R arms; parallel: the 5-DoF mechanism")
    p.add_argument("--space", required=True, choices=["joint", "task"],
                   help="joint: controllers e/f; task: controllers g/d")
    p.add_argument("--scenario", metavar="FILE",
                   help="scenario TOML (default: the thesis's study for ROBOT and SPACE)")
    p.add_argument("--plant", choices=list(PLANT_PRESETS),
                   help="the simulated robot: ideal, the rigid links as the scenario says; "
                        "realistic, the geared Dynamixels (rotors behind gears with the "
                        "datasheets' backlash, static and Coulomb friction, the bridge's current "
                        "conversion and Current Limit, encoder and velocity-register counts, 1 "
                        "period of delay). Without "
                        "--scenario, realistic runs the study tuned for it "
                        "(ROBOT_SPACE_realistic.toml); with one, it sets that scenario's plant")
    p.add_argument("--duration", type=number_argument, metavar="S",
                   help="seconds to run (default: the scenario's)")
    p.add_argument("--out", type=Path, metavar="DIR",
                   help="output folder (default: a new runs/ROBOT_SPACE_YYYYmmdd-HHMMSS)")
    p.add_argument("--backend", default="sim", choices=["sim", "dynamixel"],
                   help="what the loop drives: sim, the plant model advanced in real time "
                        "(default); dynamixel, the motors on --port (real ones, or the virtual "
                        "chain of cochlea-emulator)")
    p.add_argument("--port", metavar="PATH",
                   help="--backend dynamixel: the serial port, e.g. /dev/ttyUSB0, or the "
                        "pseudo-terminal cochlea-emulator prints")
    p.add_argument("--baud", type=whole_argument, metavar="B",
                   help="--backend dynamixel: the motors' baud rate (default 4000000)")
    p.add_argument("--homing", default="auto", choices=["auto", "required"],
                   help="--backend dynamixel, a robot with prismatic joints: check their "
                        "homing record (cochlea-dxl home) on a real port and not on the "
                        "emulator's pseudo-terminal (auto, default), or always (required)")
    p.add_argument("--start-tolerance-deg", type=number_argument, default=5.0, metavar="DEG",
                   help="--backend dynamixel: how far a revolute joint may stand from the "
                        "scenario's initial pose at the start (default 5 deg); farther is "
                        "refused before the torque comes on (exit code 5)")
    p.add_argument("--start-tolerance-mm", type=number_argument, default=5.0, metavar="MM",
                   help="--backend dynamixel: the same for a prismatic joint (default 5 mm)")
    p.add_argument("--homing-record", metavar="FILE",
                   help="--backend dynamixel: the homing record cochlea-dxl home wrote "
                        "(default ~/.cochlea/homing/ROBOT.json for the shipped description, "
                        "ROBOT-STEM-HASH.json for a user's; it must be the description's)")
    p.add_argument("--read-instruction", default="auto",
                   choices=["auto", "sync", "fast", "bulk"],
                   help="--backend dynamixel: the per-period read: auto (default) chooses from "
                        "the motors' data (FAST_SYNC_READ where every model answers it, "
                        "BULK_READ for a chain whose models place the state differently, "
                        "SYNC_READ otherwise); sync, fast or bulk force one (docs/dynamixel.md)")
    p.add_argument("--realtime", default="on", choices=["on", "off"],
                   help="on: 1 kHz absolute-deadline loop under the supervisor (default); "
                        "off: the as-fast-as-possible simulation")
    p.add_argument("--kernels", default="auto", choices=list(KERNELS),
                   help="auto: the generated C kernels when the library has this scenario's "
                        "(default), else casadi, saying so on the console and in summary.json; "
                        "c: the C kernels, or exit 2 when the library lacks or mismatches one; "
                        "casadi: the reference")
    p.add_argument("--library", metavar="PATH",
                   help="the C kernels' library: a .so, or the folder cochlea-codegen "
                        "--scenario FILE --out DIR wrote (default: $COCHLEA_LIB, else the "
                        "shipped build/libcochlea.so)")
    p.add_argument("--rate", type=number_argument, metavar="HZ",
                   help="control rate (default: the scenario's, 1000 Hz)")
    p.add_argument("--watchdog-misses", type=whole_argument, default=20, metavar="N",
                   help="real time: consecutive overrunning periods before the watchdog's "
                        "safe stop; one period stuck for longer than N periods stops at once "
                        f"(default 20; at most {MAX_WATCHDOG_MISSES}). Raise it only on a loaded "
                        "machine where a missed period is harmless, e.g. the virtual chain")
    p.add_argument("--ros2", action="store_true",
                   help="real time: also start cochlea-ros2 follow on the run's folder, a "
                        "process of its own that publishes /joint_states, /tf and "
                        "/robot_description from log.bin at 50 Hz; the run never waits on it "
                        "(docs/logs.md, Live on ROS 2)")
    p.add_argument("--desired-topic", metavar="TOPIC",
                   help="--space joint, --backend sim: wait for one trajectory_msgs/"
                        "JointTrajectory on this ROS 2 topic, check it as a scenario's path and "
                        "follow it instead of the scenario's (docs/logs.md, A desired trajectory "
                        "from ROS 2)")
    p.add_argument("--desired-timeout", type=number_argument,
                   metavar="S", help="--desired-topic: seconds to wait for the message "
                   f"(default {ros2_desired.DEFAULT_TIMEOUT_S:g}; exit 8 without one)")
    p.add_argument("--status", default="auto", choices=["auto", "on", "off"],
                   help="live one-line status while running (auto: when stderr is a terminal)")
    rt = p.add_argument_group(
        "real-time settings of the loop's thread (--realtime on; a setting the system refuses "
        "is one warning, and the run goes on with what it got: summary.json's realtime entry "
        "records both)")
    rt.add_argument("--mlockall", choices=["on", "off"],
                    help="on: lock the process's memory while the loop runs, so no page fault "
                         "stalls a period (needs CAP_IPC_LOCK or a memlock limit; default off)")
    rt.add_argument("--cpu", type=whole_argument, metavar="N",
                    help="pin the loop's thread to CPU N, e.g. one isolated with isolcpus "
                         "(default: leave it on the CPUs the process was given)")
    rt.add_argument("--sched", choices=list(POLICIES),
                    help="the loop's scheduling policy: fifo (default), rr or other (the "
                         "normal time-shared one); fifo and rr need root, CAP_SYS_NICE or an "
                         "rtprio limit")
    rt.add_argument("--priority", type=whole_argument, metavar="N",
                    help=f"--sched fifo or rr: the real-time priority, 1..99 (default "
                         f"{FIFO_PRIORITY}: above normal processes, below the kernel's own "
                         "threads at 50)")
    return p


def _realtime_options(args: argparse.Namespace) -> RealtimeOptions:
    """``--mlockall --cpu --sched --priority`` as the loop takes them; checked before anything
    moves."""
    given = [f"--{name}" for name in ("mlockall", "cpu", "sched", "priority")
             if getattr(args, name) is not None]
    if args.realtime == "off" and given:
        raise CochleaError(f"{', '.join(given)} set the real-time loop's thread and go with "
                           "--realtime on")
    options = RealtimeOptions(mlockall=args.mlockall == "on", cpu=args.cpu,
                              policy=args.sched or "fifo", priority=args.priority)
    check_realtime_options(options)
    return options


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # A reader that went away (``| head -1``) must not end a run mid-motion or before its
    # report: the rest of stdout goes to /dev/null and the run keeps its exit code.
    tolerate_closed_stdout()
    run = _Run(args)
    run.shield.install()
    try:
        return _run(args, run)
    except BackendError as exc:
        print(f"cochlea-run: the backend could not start, nothing moved: {exc}", file=sys.stderr)
        return EXIT_BACKEND
    except ros2_desired.TopicError as exc:
        print(f"cochlea-run: {exc}", file=sys.stderr)
        return exc.code
    except CochleaError as exc:
        print(f"cochlea-run: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except outputs.ReportError as exc:
        print(f"cochlea-run: {exc}", file=sys.stderr)
        return EXIT_REPORT_FAILED
    except KeyboardInterrupt as exc:  # only ever raised before anything ran (see _Run)
        signum = getattr(exc, "signum", signal.SIGINT)
        what, code = {signal.SIGTERM: ("terminated", EXIT_TERMINATED),
                      signal.SIGHUP: ("hung up (SIGHUP)", EXIT_HUNG_UP)}.get(
                          signum, ("interrupted", EXIT_INTERRUPTED))
        if run.simulating:
            print(f"cochlea-run: {what} during the as-fast simulation; nothing written (a "
                  "simulation: nothing moved)", file=sys.stderr)
        else:
            print(f"cochlea-run: {what} before the run started; nothing moved",
                  file=sys.stderr)
        return code
    finally:
        run.close()
        if argv is None:
            # The program itself: it is about to exit with the run's own code, which a late
            # Ctrl-C must not turn into a KeyboardInterrupt's traceback, nor a SIGTERM or a
            # hang-up into death by the signal.
            run.shield.ignore()
        else:
            run.shield.restore()  # called from Python (the tests): give the handlers back


class _Run:
    """What one invocation holds: its output folder and its signal handling.

    Until the run has produced something (``kept``), a failure or an interrupt undoes the
    start (the folder and what was written in it are removed, so the identical retry works);
    from then on nothing is removed. The lock on the folder is held to the end."""

    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.folder: outputs.OutputFolder | None = None
        self.shield = outputs.SignalShield("cochlea-run")
        self.kept = False
        self.simulating = False
        self.desired_source: dict | None = None  # --desired-topic: summary.json's record

    def claim(self, default: str) -> Path:
        # Held off until the folder is recorded here: an interrupt meanwhile would leave the
        # folder (and its lock file) behind, blocking the identical retry.
        with signals_held():
            if self.args.out is not None:
                self.folder = outputs.claim(self.args.out)
            else:
                self.folder = outputs.claim_new(Path("runs"), default)
        return self.folder.path

    def use_library(self, path: str) -> None:
        """Point ``$COCHLEA_LIB`` at ``path`` for this run (every layer loads the default
        library); :meth:`close` puts it back."""
        if not hasattr(self, "_environment"):
            self._environment = os.environ.get(ENVIRONMENT)
        os.environ[ENVIRONMENT] = path

    def close(self) -> None:
        if hasattr(self, "_environment"):  # the caller's $COCHLEA_LIB, as it was
            if self._environment is None:
                os.environ.pop(ENVIRONMENT, None)
            else:
                os.environ[ENVIRONMENT] = self._environment
            del self._environment
        if self.folder is None:
            return
        if self.kept:
            self.folder.release()
        else:
            self.folder.discard()


def _validate(args: argparse.Namespace, scenario) -> None:
    if (scenario.robot, scenario.space) != (args.robot, args.space):
        raise CochleaError(f"scenario {scenario.path} is for --robot {scenario.robot} --space "
                           f"{scenario.space}, not --robot {args.robot} --space {args.space}: "
                           "change the options or the scenario")
    if args.rate is not None and not MIN_RATE_HZ <= args.rate <= MAX_RATE_HZ:
        raise CochleaError(f"--rate must be between {MIN_RATE_HZ:g} and {MAX_RATE_HZ:g} Hz, "
                           f"got {args.rate}")
    # The run as it will be: its duration and rate, at least one period, at most what one run
    # may hold (the as-fast simulation keeps every period in memory).
    check_run_length(scenario.duration if args.duration is None else args.duration,
                     scenario.rate_hz if args.rate is None else args.rate,
                     "duration_s of the scenario" if args.duration is None else "--duration",
                     MAX_FAST_PERIODS if args.realtime == "off" else MAX_PERIODS)
    if not 1 <= args.watchdog_misses <= MAX_WATCHDOG_MISSES:
        raise CochleaError(f"--watchdog-misses must be between 1 and {MAX_WATCHDOG_MISSES} "
                           f"periods, got {args.watchdog_misses}")
    if args.realtime == "off" and args.backend != "sim":
        raise CochleaError("--realtime off simulates as fast as possible and needs "
                           "--backend sim")
    if args.backend == "dynamixel" and not args.port:
        raise CochleaError("--backend dynamixel needs --port PATH: the motors' serial port, "
                           "or the path cochlea-emulator prints")
    if args.backend != "dynamixel" and (args.port is not None or args.baud is not None):
        raise CochleaError("--port and --baud go with --backend dynamixel")
    if args.baud is not None:
        baud_code(args.baud)  # a rate the motors do not have, refused before the folder exists
    for name in ("start_tolerance_deg", "start_tolerance_mm"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):  # NaN, inf, zero or negative
            raise CochleaError(f"--{name.replace('_', '-')} must be a positive number, got "
                               f"{value}")
    if args.ros2 and args.realtime == "off":
        raise CochleaError("--ros2 follows a real-time run's log.bin as it is written; after "
                           "an as-fast run, publish it with cochlea-ros2 replay RUN_DIR")
    if args.library is not None and args.kernels == "casadi":
        raise CochleaError("--library names C kernels and goes with --kernels auto or c")
    _realtime_options(args)
    # --out is outputs.check_folder's (a leftover lock of a killed run is not "not empty").


def _run(args: argparse.Namespace, run: _Run) -> int:
    if args.out is not None:  # the cheap checks first; the folder is created only at the end
        outputs.check_folder(args.out)
    study = f"{args.robot}_{args.space}" + ("_realistic" if args.plant == "realistic" else "")
    scenario = load_scenario(args.scenario or shipped_file(SCENARIOS_DIR, study),
                             plant_preset=args.plant)
    _validate(args, scenario)
    topic = None
    if args.desired_topic is not None:  # waits for the trajectory, checks it (exit 4, 8, 9)
        topic = ros2_desired.from_topic(args, scenario)
        scenario, run.desired_source = topic.scenario, topic.source
    elif args.desired_timeout is not None:
        raise CochleaError("--desired-timeout goes with --desired-topic TOPIC")
    if args.rate is not None:
        scenario = dataclasses.replace(scenario, rate_hz=args.rate)
    if args.duration is not None:  # the up-front checks sample the run's actual duration
        scenario = dataclasses.replace(scenario, duration=args.duration)
    # Validates the whole run's path before anything moves, and that the drives hold the robot
    # against gravity where it starts (on the motors: at their Current Limits).
    setups = unit_setups(scenario, on_motors=args.backend == "dynamixel") if topic is None \
        else topic.setups()
    # Which kernels, decided once and checked (names and source hashes) before anything runs:
    # --kernels c refuses here; auto falls back here, and says so below and in summary.json.
    choice = choose_kernels(setups, scenario.plant_substeps, args.kernels, args.library)
    if choice.used == "c":  # every part of the run (loop, plant, supervisor) loads this one
        run.use_library(choice.library)
    periods = int(round(scenario.duration * scenario.rate_hz))
    target = args.out if args.out is not None else Path("runs")
    outputs.check_free_space(
        target, outputs.log_bytes(setups, periods, args.realtime == "on"),
        "--out" if args.out is not None else "the output folder",
        f"{periods} periods of " + ("log.bin and log.csv" if args.realtime == "on" else
                                    "log.csv"))
    out = run.claim(f"{args.robot}_{args.space}_{datetime.now().strftime('%Y%m%d-%H%M%S')}")
    # An as-fast run is the simulation from its first line on (an interrupt says so).
    run.simulating = args.realtime == "off"
    mode = "real time" if args.realtime == "on" else "as fast as possible"
    print(f"cochlea-run: {scenario.name} (controller {scenario.controller}, {scenario.variant} "
          f"variant), {args.backend} backend, {mode} at {scenario.rate_hz:g} Hz -> {out}",
          flush=True)
    print(f"cochlea-run: kernels: {choice.line()}", flush=True)
    args.kernels = choice.used  # "c" (checked above) or "casadi": no fallback left to take
    if args.realtime == "off":
        start = time.perf_counter()
        result = simulate(scenario, args.duration, setups, kernels=args.kernels)
        result.kernels = choice.summary()
        result.desired_source = run.desired_source
        wall = time.perf_counter() - start
        run.shield.defer()  # from here the report is written whatever the user presses
        run.simulating, run.kept = False, True
        # The as-fast run does not stop, but it answers to the same rules as a real one.
        supervisor = build_supervisor(setups, scenario.system.keep_out_radius,
                                      kernels=args.kernels, substeps=scenario.plant_substeps)
        result.supervisor = verdict(result, supervisor)
        data = report.write_all(result, out, wall)
        _report(data, out, wall)
        if result.diverged:
            for name, t in result.diverged.items():
                print(f"cochlea-run: {name} diverged at t = {t:.3f} s (log kept up to there)",
                      file=sys.stderr)
        rule = result.supervisor
        if rule["rule"] != "none":
            # A follower without a desired pose cannot go on: the as-fast run ends there too.
            went = ("the as-fast run ended there too, log kept up to there"
                    if result.mirror_stop is not None and rule["rule"] == MIRROR_RULE
                    else "the as-fast run went on")
            print(f"cochlea-run: a real run would have been stopped by rule {rule['rule']} at "
                  f"t = {rule['time_s']:.3f} s: {rule['detail']} ({went})", file=sys.stderr)
        if result.diverged:
            return EXIT_DIVERGED
        return STOP_CODES[rule["rule"]] if rule["rule"] != "none" else 0
    return _run_realtime(args, scenario, setups, run, choice)


def _run_realtime(args, scenario, setups, run: _Run, choice) -> int:
    out = run.folder.path
    keep_out = scenario.system.keep_out_radius
    duration = scenario.duration if args.duration is None else args.duration
    steps = int(round(duration * scenario.rate_hz))
    substeps = scenario.plant_substeps
    if args.backend == "dynamixel":
        backend = _dynamixel_backend(args, scenario, setups)
    else:
        # Measured (delay, noise, grids) and driven (effort grid) as the as-fast run is.
        backend = SimBackend(setups, scenario.period, substeps, kernels=args.kernels,
                             plant=scenario.plant, steps=steps)
    supervisor = build_supervisor(setups, keep_out, kernels=args.kernels,
                                  substeps=substeps, watchdog_misses=args.watchdog_misses)
    loop = RealTimeLoop(setups, backend, supervisor, scenario.period, steps, realtime=True,
                        kernels=args.kernels, substeps=substeps,
                        options=_realtime_options(args), warn=_warn)
    write_raw_columns(run.folder.track(out / "log.columns.json"), loop)
    if args.ros2:  # a child of its own, never waited on: its death changes nothing here
        _start_ros2(out, scenario)
    status = args.status == "on" or (args.status == "auto" and sys.stderr.isatty())
    # From here a signal is the loop's safe stop (the loop installs the same handler for its
    # periods): one arriving while the motors start stops the loop before its first command.
    run.shield.forward(loop.on_signal)
    if args.backend == "dynamixel":
        # The motors' start-up (ping, configure, first read, torque on) before the loop: a
        # refusal ends here with nothing to undo (the loop's own enable() is then a no-op).
        backend.enable()
    start = time.perf_counter()
    try:
        stop = loop.run(out / "log.bin", status=status)
    finally:
        # The loop hands SIGINT, SIGTERM and SIGHUP back to the shield as it returns: from now
        # on they are acknowledged, not obeyed, until the report is written.
        run.shield.defer()
        run.kept = run.kept or (out / "log.bin").exists()
    wall = time.perf_counter() - start
    result = loop.result(scenario)
    result.kernels = choice.summary()
    result.desired_source = run.desired_source
    if loop.kernel_source != choice.used:  # checked above, so never expected: said if so
        result.kernels.update(used=loop.kernel_source, fallback_reason="the real-time loop "
                              "could not bind the C kernels checked before the run")
    result.stop = {"rule": stop.rule, "time_s": stop.time, "detail": stop.detail,
                   "exit_code": stop.code}
    timing = loop.timing_summary()
    if args.backend == "dynamixel":
        timing["bus"] = backend.summary()
    quantum = None
    if args.backend == "dynamixel":  # the motors' encoders set what "converged" can mean
        quantum = {u.name: backend.position_quantum()[sl]
                   for u, sl in zip(setups, loop.slices)}
    data = report.write_all(result, out, wall, timing, realtime=loop.realtime_report,
                            position_quantum=quantum)
    _report(data, out, wall)
    if args.backend == "dynamixel":
        bus = timing["bus"]
        print(f"  bus: {bus['bus_budget']['bytes_per_period']} bytes per period, budget "
              f"{bus['bus_budget']['bus_s'] * 1e6:.0f} us; read + write mean "
              f"{timing['backend_mean'] * 1e6:.0f} us, p99 {timing['backend_p99'] * 1e6:.0f} us; "
              f"{bus['good_reads']} of {bus['reads']} reads good"
              + (f", failures {bus['failures']}" if bus["failures"] else "")
              + f"; shut-down: {bus['shutdown']}")
    print(f"  timing: period p50 {timing['period_p50'] * 1e3:.3f} ms, p99 "
          f"{timing['period_p99'] * 1e3:.3f} ms, max {timing['period_max'] * 1e3:.3f} ms; "
          f"deadline misses {timing['deadline_misses']} "
          f"({100 * timing['deadline_miss_fraction']:.2f} %), overruns {timing['overruns']}, "
          f"lateness max {timing['lateness_max'] * 1e3:.3f} ms; compute p99 "
          f"{timing['compute_p99'] * 1e6:.0f} us; {timing['scheduling']}")
    if stop.rule == "completed":
        return 0
    line = (f"cochlea-run: stopped by rule {stop.rule} at t = {stop.time:.3f} s: {stop.detail}"
            if stop.rule != "user-stop" else
            f"cochlea-run: stopped by the user at t = {stop.time:.3f} s")
    # A failed log is the one stop whose log is not whole: the detail says how much was kept.
    kept = "log kept up to the failure" if stop.rule == "log-failure" else "log complete"
    print(f"{line}; zero effort commanded, drives disabled, {kept}", file=sys.stderr)
    return STOP_CODES[stop.rule]


#: The bridge started by --ros2, kept only so Python does not warn of a child still running.
_CHILDREN: list = []


def _start_ros2(out: Path, scenario) -> None:
    """``cochlea-ros2 follow`` on ``out`` in a session of its own (a Ctrl-C meant for the run
    is not its), its output on this stderr; a bridge that cannot start is a warning."""
    try:
        _CHILDREN.append(subprocess.Popen(
            [sys.executable, "-m", "cochlea.apps.cochlea_ros2", "follow", str(out),
             "--scenario", str(scenario.path)],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, start_new_session=True,
            close_fds=True))
    except OSError as exc:
        _warn(f"--ros2: cannot start cochlea-ros2 ({exc.strerror or exc}); the run goes on")


def _warn(text: str) -> None:
    print(f"cochlea-run: warning: {text}", file=sys.stderr, flush=True)


def _dynamixel_backend(args, scenario, setups):
    """The motors of the scenario's description on ``--port``; refused before anything moves
    when the bus cannot carry the loop's rate, with a warning when it only just can, and (at
    start-up) when the robot does not stand at the scenario's initial pose."""
    start = np.concatenate([u.x0[:u.controller_model.nq] for u in setups])
    # Only a missing --baud means the default: --baud 0 is refused like any other bad rate.
    # The Realtime Tick read with the state: a motor repeating a stale packet is a failed read.
    backend = DynamixelBackend(scenario.robot, args.port,
                               4_000_000 if args.baud is None else args.baud,
                               description=scenario.description, system=scenario.system,
                               realtime_tick=True,
                               homing=args.homing, homing_record=args.homing_record,
                               offset_current=bridge_compensates_friction(
                                   scenario.controller_actuators),
                               expected_start=start,
                               read_instruction=args.read_instruction,
                               start_tolerance=(math.radians(args.start_tolerance_deg),
                                                args.start_tolerance_mm * 1e-3))
    verdict = backend.check_rate(scenario.rate_hz)
    if verdict.level == "refuse":
        raise CochleaError(f"{verdict.message} (--rate sets a lower one)")
    if verdict.level == "warn":
        print(f"cochlea-run: warning: {verdict.message}", file=sys.stderr, flush=True)
    transfers = backend.summary()["bus_budget"]
    print(f"cochlea-run: bus: {transfers['read_instruction']} + "
          f"{transfers['write_instruction']} per period ({transfers['read_choice']})",
          flush=True)
    return backend


def _report(data: dict, out: Path, wall: float) -> None:
    print(f"  ran {data['duration_s']:.2f} s in {wall:.2f} s "
          f"({data['duration_s'] / max(wall, 1e-9):.1f}x real time)")
    true = data["judged_error"] == "true"
    for name, unit in data["units"].items():
        for coord, c in unit["tracked"].items():
            if c["initial_abs_error"] is None:
                continue
            # Judged on the true error where the run has it; the measured one beside it.
            seen = f" (measured {c['measured_final_rms_error']:.3e})" if true else ""
            verdict = "" if c["converged"] else "  NOT CONVERGED"
            if not c["converged"] and c["initial_abs_error"] <= c["convergence_floor"]:
                # No error to shrink: the rule's ratio cannot hold, only the floor can.
                verdict += (f" (started on its path: the final RMS is above the floor "
                            f"{c['convergence_floor']:.1e} {c['unit']})")
            print(f"  {name}.{coord}: initial |e| {c['initial_abs_error']:.3e} {c['unit']}, "
                  f"final RMS {c['final_rms_error']:.3e} {c['unit']}{seen}{verdict}")
    print(f"  converged: {'yes' if data['converged'] else 'no'} (judged on the "
          f"{data['judged_error']} error)")
    print(f"  log: {out / 'log.csv'}\n  summary: {out / 'summary.json'}")
    for figure in data["figures"]:
        print(f"  figure: {figure}")


if __name__ == "__main__":
    sys.exit(main())
