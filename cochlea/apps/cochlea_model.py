"""``cochlea-model``: a robot's model summarised (parameters, M, G and the tool pose at a
configuration). User mistakes print one line and exit with EXIT_USER_ERROR; a reader that
stops reading (``cochlea-model | head -1``) ends it quietly, with the shell's code for SIGPIPE."""

from __future__ import annotations

import argparse
import math
import os
import sys

from ..console import EXIT_BROKEN_PIPE, OneLineParser, stdout_was_closed, tolerate_closed_stdout
from ..errors import EXIT_USER_ERROR, CochleaError
from ..robots import ROBOTS, robot
from ..text import decimal

#: A joint coordinate of --at-deg / --at beyond this (deg, or m) is a typo: ten turns of a
#: revolute joint are 3600 deg, and no prismatic joint moves 10 km.
MAX_COORDINATE = 1e4


def _numbers(values: list[str] | None, option: str) -> list[float] | None:
    """An option's values as finite numbers: NaN or inf printed a table of NaNs with exit 0,
    and float() would read 1_0 as 10 (cochlea.text.decimal reads plain decimals only)."""
    if values is None:
        return None
    out = []
    for text in values:
        value = decimal(text)
        if value is None or not math.isfinite(value) or abs(value) > MAX_COORDINATE:
            raise CochleaError(f"{option} {text!r}: expected a finite decimal number within "
                               f"+-{MAX_COORDINATE:g}")
        out.append(value)
    return out


def _print_summary(args: argparse.Namespace) -> None:
    args.at_deg = _numbers(args.at_deg, "--at-deg")
    args.at = _numbers(args.at, "--at")
    adapter = robot(args.robot)
    adapter.print_summary(adapter.load(args.description), args)


EXIT_INTERRUPTED = 130


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(
        prog="cochlea-model",
        description="Print the symbolic model of a robot: joints and limits, dynamic parameters "
                    "(full, base or mass-only), and M, G and the tool pose (for the parallel "
                    "mechanism both end effectors) at a configuration.",
    )
    parser.add_argument("robot", nargs="?", default="serial", choices=list(ROBOTS),
                        help="which robot: the serial arms (default) or the parallel mechanism")
    parser.add_argument("--arm", help="one arm of the serial system (default: every arm)")
    parser.add_argument("--parameterisation", default="base", choices=["inertial", "base", "mass"],
                        help="parameter set to list (default: base)")
    parser.add_argument("--method", choices=["newton-euler", "lagrange"],
                        help="serial: newton-euler (default) or lagrange; the parallel "
                             "mechanism's model is Lagrangian only")
    parser.add_argument("--description", help="a robot description TOML instead of the shipped "
                        "one (models/robots/)")
    parser.add_argument("--at-deg", nargs="+", metavar="DEG",
                        help="serial: joint angles in degrees (metres for a prismatic joint) "
                             "at which to evaluate M, G and the tool pose (default: all zero)")
    parser.add_argument("--at", nargs=5, metavar="X",
                        help="parallel: th1 th2 d1 th1' th2' in deg, deg, m, deg, deg (default: "
                             "the joint-space scenario's start)")
    args = parser.parse_args(argv)
    tolerate_closed_stdout()
    try:
        _print_summary(args)
        sys.stdout.flush()  # what is still buffered fails here, not in the interpreter's exit
    except CochleaError as exc:
        print(f"cochlea-model: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as exc:  # the output's disk is full, its device gone
        _quiet_stdout()
        where = f" {exc.filename}" if exc.filename else " the output"
        print(f"cochlea-model: cannot write{where}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # Ctrl-C while CasADi builds a model
        print("cochlea-model: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    # The reader had what it wanted (``| head -1``): the shell's code for a closed pipe.
    return EXIT_BROKEN_PIPE if stdout_was_closed() else 0


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: Python flushes it again at exit, which must not fail too."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


if __name__ == "__main__":
    sys.exit(main())
