"""``cochlea-excite``: design an excitation trajectory for identification and write it as a
joint-space scenario ``cochlea-run`` tracks (docs/excitation.md). User mistakes, and requests
no trajectory can satisfy, print one line and exit with EXIT_USER_ERROR; an --out that cannot
take the file, and a write that fails, have their own codes (docs/excitation.md, "Limits,
files and exit codes"); nothing is written then."""

from __future__ import annotations

import argparse
import math
import os
import shlex
import signal
import stat
import sys
from pathlib import Path

from ..errors import EXIT_USER_ERROR, CochleaError
from ..ident import files
from ..ident.cli import OneLineParser, Terminated, exit_code, sigterm_unwinds
from ..ident.estimate import DEFAULT_MAX_CONDITION
from ..ident.excite import ExcitationOptions, check_options, design, scenario_text
from ..robots import ROBOTS, robot
from ..sim.scenario import load as load_scenario
from ..sim.setup import unit_setups
from ..text import number_argument, whole_argument

#: Exit codes (docs/excitation.md, "Exit codes"); EXIT_USER_ERROR (2): a wrong option or
#: number, limits nothing fits.
#: --out refused before anything runs (a folder, FIFO, device, symbolic link, a path under a
#: file, a read-only folder, an input, an existing file without --force).
EXIT_OUTPUT_REFUSED = 5
#: Writing the scenario failed (full disk, I/O error): no partial file, the previous kept.
EXIT_WRITE_FAILED = 6
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE


def _parser() -> argparse.ArgumentParser:
    defaults = ExcitationOptions()
    p = OneLineParser(
        prog="cochlea-excite",
        description="Design an excitation trajectory for identifying a robot's dynamic "
                    "parameters: a finite Fourier series per joint, optimised for the "
                    "condition number of the stacked base regressor within the joints' "
                    "position, velocity and torque limits and the robot's workspace, written "
                    "as a joint-space scenario for cochlea-run.",
        epilog="Example:\n"
               "  cochlea-excite --robot serial --arm arm1 --out excite_arm1.toml\n"
               "  cochlea-run --robot serial --space joint --scenario excite_arm1.toml "
               "--realtime off --out runs/excite_arm1\n"
               "  cochlea-excite --robot serial --description robot.toml --out excite.toml\n"
               "See docs/excitation.md.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--robot", required=True, choices=list(ROBOTS),
                   help="serial: one 3R arm (the other holds still); parallel: the mechanism")
    p.add_argument("--arm", help="serial: the arm to excite (default: the first)")
    p.add_argument("--description", metavar="ROBOT.toml",
                   help="the robot description to excite (default: the shipped one): its "
                        "joint limits, optional working_pose_deg and [[keep_out]] volumes "
                        "(docs/excitation.md)")
    p.add_argument("--scenario", metavar="S.toml",
                   help="the joint-space scenario of the same description whose control "
                        "settings and gains track the excitation (default: the robot's "
                        "excitation study for the shipped description, the cochlea-urdf "
                        "starter's gains for another)")
    p.add_argument("--out", required=True, type=Path, metavar="FILE.toml",
                   help="the scenario to write (refused if it exists, unless --force)")
    p.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    p.add_argument("--period", type=number_argument, default=defaults.period, metavar="S",
                   help=f"period of the fundamental, s (default {defaults.period:g})")
    p.add_argument("--harmonics", type=whole_argument, default=defaults.harmonics, metavar="H",
                   help=f"harmonics per joint, at least 2 (default {defaults.harmonics})")
    p.add_argument("--amplitude-deg", type=number_argument,
                   default=math.degrees(defaults.amplitude_rad), metavar="DEG",
                   help="revolute joints stay within this of their working pose (default "
                        f"{math.degrees(defaults.amplitude_rad):g})")
    p.add_argument("--amplitude-mm", type=number_argument, default=defaults.amplitude_m * 1000,
                   metavar="MM", help="prismatic joints (the slider) likewise (default "
                                      f"{defaults.amplitude_m * 1000:g})")
    p.add_argument("--periods", type=whole_argument, default=defaults.periods, metavar="N",
                   help="the run's length in whole periods; it ends at rest where it began "
                        f"(default {defaults.periods})")
    p.add_argument("--seed", type=whole_argument, default=defaults.seed,
                   help=f"seed of the optimiser's random starts (default {defaults.seed})")
    p.add_argument("--starts", type=whole_argument, default=defaults.starts, metavar="N",
                   help=f"random starts of the optimiser (default {defaults.starts})")
    p.add_argument("--iterations", type=whole_argument, default=defaults.iterations, metavar="N",
                   help=f"SLSQP iterations per start (default {defaults.iterations})")
    p.add_argument("--limit-fraction", type=number_argument, default=defaults.limit_fraction,
                   metavar="F", help="velocity and nominal torque stay within this fraction "
                                     f"of their limits (default {defaults.limit_fraction:g})")
    p.add_argument("--clearance-mm", type=number_argument, default=defaults.clearance * 1000,
                   metavar="MM", help="serial: smallest distance between the excited arm and "
                                      f"the other one (default {defaults.clearance * 1000:g})")
    return p


def check_out(path: Path, force: bool, inputs: tuple[Path, ...] = ()) -> None:
    """Refuse an --out that cannot become the scenario file, before the optimisation: a
    folder, a FIFO, a device, a symbolic link, a path under a file, a folder this process
    cannot write (a read-only file system), one of the inputs (the description, the tracking
    scenario), or an existing file without --force."""
    where = f"--out {path}"
    if os.path.lexists(path):
        mode = os.lstat(path).st_mode
        if stat.S_ISDIR(mode):
            raise files.OutputRefused(f"{where} is a folder: name the scenario file, e.g. "
                                      f"{path / 'excite.toml'}")
        if not stat.S_ISLNK(mode) and stat.S_ISREG(mode) and not force:
            raise files.OutputRefused(f"{where} exists: name a new file, or give --force to "
                                      "overwrite it")
    files.check_output(path, "--out", inputs=inputs)


def _options(args: argparse.Namespace) -> ExcitationOptions:
    return ExcitationOptions(
        period=args.period, harmonics=args.harmonics,
        amplitude_rad=math.radians(args.amplitude_deg), amplitude_m=args.amplitude_mm / 1000,
        periods=args.periods, seed=args.seed, starts=args.starts, iterations=args.iterations,
        limit_fraction=args.limit_fraction, clearance=args.clearance_mm / 1000)


def _description_ref(args: argparse.Namespace) -> str | None:
    """The written scenario's ``description`` key: None for the shipped one; a file's path
    relative to the scenario's folder (scenarios resolve it there), else absolute."""
    if args.description is None:
        return None
    path = Path(args.description)
    if path.suffix != ".toml" and not path.exists():
        return args.description  # a shipped name
    folder = Path(os.path.abspath(args.out)).parent
    try:
        return os.path.relpath(os.path.abspath(path), folder)
    except ValueError:  # another drive
        return os.path.abspath(path)


def check_condition(result) -> None:
    """Refuse a design that ``cochlea-identify`` would refuse at its default
    ``--max-condition`` (:data:`cochlea.ident.estimate.DEFAULT_MAX_CONDITION`, on the same
    column-scaled condition number): running it would record a log that identifies nothing."""
    limit = DEFAULT_MAX_CONDITION
    if not result.scaled_condition <= limit:
        raise CochleaError(
            f"the designed excitation of {result.unit} is not good enough to identify from: its "
            f"scaled condition number is {result.scaled_condition:.3g}, above {limit:g} (the "
            "largest cochlea-identify accepts by default, --max-condition); nothing written: "
            "raise --amplitude-deg / --amplitude-mm, --harmonics, --starts or --iterations")


def _command(argv: list[str] | None) -> str:
    words = sys.argv[1:] if argv is None else argv
    return "cochlea-excite " + " ".join(shlex.quote(w) for w in words)


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        adapter = robot(args.robot)
        # --arm refused where it names no unit
        adapter.unit(adapter.load(args.description), args.arm)
        options = _options(args)
        check_options(options)
        inputs = tuple(Path(p) for p in (args.description, args.scenario) if p)
        check_out(args.out, args.force, inputs)
        result = design(args.robot, args.arm, options, args.description, args.scenario)
        check_condition(result)
        text = scenario_text(result, _command(argv), _description_ref(args))
        # Written under a temporary name beside --out, renamed when complete and checked: a
        # full disk or an I/O error leaves no partial file and the previous one as it was.
        with sigterm_unwinds(), files.Staged() as stage:
            stage.write_text(args.out, text)
            # What cochlea-run will check before anything moves, checked before it is kept.
            unit_setups(load_scenario(stage.path_of(args.out)))
            stage.commit()
        print(f"cochlea-excite: {args.robot} {result.unit}: period {options.period:g} s, "
              f"{options.harmonics} harmonics, {options.periods} periods -> {args.out}")
        print(f"  condition number of the stacked base regressor: designed "
              f"{result.condition:.4g} (columns scaled: {result.scaled_condition:.4g}); "
              f"hand-picked sine of the same amplitude {result.sine_condition:.4g} (scaled: "
              f"{result.sine_scaled_condition:.4g})")
        print("  peak |velocity| / limit: "
              + ", ".join(f"{v:.2f}" for v in result.peak_velocity)
              + "; peak |nominal torque| / limit: "
              + ", ".join(f"{v:.2f}" for v in result.peak_effort))
        approach = [f"{v * 1000:.1f} mm to {what}" for v, what in (
            (result.keep_out_distance, "the cochlea centre"),
            (result.clearance_distance, "the other arm"),
            (result.keep_out_volume_distance, "the keep-out volumes")) if v is not None]
        if approach:
            print("  closest approach: " + ", ".join(approach))
        print(f"  run it: cochlea-run --robot {args.robot} --space joint --scenario {args.out} "
              "--realtime off")
        sys.stdout.flush()
    except CochleaError as exc:
        print(f"cochlea-excite: {exc}", file=sys.stderr)
        if isinstance(exc, files.OutputRefused):
            return EXIT_OUTPUT_REFUSED
        if isinstance(exc, files.WriteFailed):
            return EXIT_WRITE_FAILED
        return EXIT_USER_ERROR
    except BrokenPipeError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return EXIT_BROKEN_PIPE
    except OSError as exc:  # not while writing (that is WriteFailed): reading an input
        print(f"cochlea-excite: cannot read {exc.filename}: {exc.strerror or exc}; nothing "
              "written", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, Terminated)
        print(f"cochlea-excite: {'terminated' if terminated else 'interrupted'}; nothing "
              "written", file=sys.stderr)
        return exit_code(exc) if terminated else EXIT_INTERRUPTED
    return 0


if __name__ == "__main__":
    sys.exit(main())
