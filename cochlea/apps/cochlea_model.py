"""``cochlea-model``: a robot's model summarised (parameters, M, G and the tool pose at a
configuration). User mistakes print one line and exit with EXIT_USER_ERROR; a reader that
stops reading (``cochlea-model | head -1``) ends it quietly, with the shell's code for SIGPIPE."""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from ..console import EXIT_BROKEN_PIPE, stdout_was_closed, tolerate_closed_stdout
from ..errors import EXIT_USER_ERROR, CochleaError
from ..robots import ROBOTS, model
from ..robots.parallel import SCENARIO_START
from ..robots.serial import load_serial


def _print_serial_summary(args: argparse.Namespace) -> None:
    if args.at is not None:
        raise CochleaError("--at is for the parallel mechanism; give the serial arm's joint "
                           "angles with --at-deg")
    system = load_serial(args.description or args.robot)
    arm_names = [args.arm] if args.arm else [a.name for a in system.arms]
    for arm_name in arm_names:
        arm = model(args.robot, arm=arm_name, parameterisation=args.parameterisation,
                    method=args.method or "newton-euler", description=args.description)
        print(arm.describe())
        if args.at_deg is not None:
            if len(args.at_deg) != arm.nq:
                raise CochleaError(f"--at-deg needs {arm.nq} joint angles (deg), got "
                                   f"{len(args.at_deg)}")
            q = np.radians(args.at_deg)
        else:
            q = np.zeros(arm.nq)
        x, y, phi = np.array(arm.fk_world(q)).ravel()
        np.set_printoptions(precision=6, suppress=False)
        print(f"  at q = {np.degrees(q).round(3).tolist()} deg:")
        print(f"    tool in the cochlea frame: x = {x:.6f} m, y = {y:.6f} m, "
              f"phi = {np.degrees(phi):.3f} deg")
        print("    M(q) [kg m^2] =")
        for row in np.array(arm.M(q)):
            print("      " + "  ".join(f"{v: .6e}" for v in row))
        print("    G(q) [N m] = " + "  ".join(f"{v: .3e}" for v in np.array(arm.G(q)).ravel()))
        print()


def _print_parallel_summary(args: argparse.Namespace) -> None:
    if args.arm is not None:
        raise CochleaError("--arm is for the serial system; the parallel mechanism is one robot")
    if args.at_deg is not None:
        raise CochleaError("--at-deg is for the serial arms; give the parallel mechanism's "
                           "th1 th2 d1 th1' th2' (deg, deg, m, deg, deg) with --at")
    if args.method == "newton-euler":
        raise CochleaError("the parallel mechanism is a closed chain: its model comes from the "
                           "Lagrange method only (--method lagrange, the default for it)")
    robot = model("parallel", parameterisation=args.parameterisation, method="lagrange",
                  description=args.description)
    system = robot.geometry.system
    print(robot.describe())
    print(f"  geometry: l_p = {system.link_length:g} m, d2 = {system.base_offset:g} m, "
          f"d3 = {system.rod_length:g} m, {system.min_pivot_distance:g} m <= |C - S| <= d3; "
          f"gravity (u, v) = {system.gravity.tolist()} m/s^2")
    for joint in system.joints:
        fit = joint.motor.fit
        line = (f"  motor {joint.name}: {joint.motor.model} ID {joint.motor.id}, "
                f"{fit.y} = {fit.a:g} * {fit.x} {'-' if fit.b < 0 else '+'} {abs(fit.b):g}")
        if joint.transmission is not None:
            t = joint.transmission
            line += (f"; {t.kind.replace('_', ' ')} {t.size:g} m: torque = force * "
                     f"{t.ratio:.6g} m")
        print(line)
    if args.at is not None:
        if len(args.at) != robot.nq:
            raise CochleaError(f"--at needs {robot.nq} values th1 th2 d1 th1' th2' (deg, deg, "
                               f"m, deg, deg), got {len(args.at)}")
        q = np.array(args.at, float)
        q[[0, 1, 3, 4]] = np.radians(q[[0, 1, 3, 4]])
        where = "at"
    else:
        q = SCENARIO_START
        where = "at the joint-space scenario's start (thesis 3.67, right side mirrored),"
    x = np.array(robot.fk(q)).ravel()
    shown = [round(float(np.degrees(q[0])), 3), round(float(np.degrees(q[1])), 3),
             float(q[2]), round(float(np.degrees(q[3])), 3), round(float(np.degrees(q[4])), 3)]
    print(f"  {where} q = {shown} (deg, deg, m, deg, deg):")
    print(f"    left  end effector C  = ({x[0]:.6f}, {x[1]:.6f}) m, phi  = "
          f"{np.degrees(x[2]):.3f} deg")
    print(f"    right end effector C' = ({x[3]:.6f}, {x[4]:.6f}) m, phi' = "
          f"{np.degrees(x[5]):.3f} deg")
    problems = robot.geometry.violations(q)
    print("    outside the workspace: " + "; ".join(problems) if problems else
          "    inside the workspace")
    print("    M(q) [kg m^2, kg m, kg] =")
    for row in np.array(robot.M(q)):
        print("      " + "  ".join(f"{v: .6e}" for v in row))
    print("    G(q) [N m, N m, N, N m, N m] = "
          + "  ".join(f"{v: .4e}" for v in np.array(robot.G(q)).ravel()))


EXIT_INTERRUPTED = 130


#: What ``cochlea-model`` prints for each robot (every robot of :data:`cochlea.robots.ROBOTS`).
SUMMARIES = {"serial": _print_serial_summary, "parallel": _print_parallel_summary}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
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
                        "one (cochlea/data/robots/)")
    parser.add_argument("--at-deg", nargs="+", type=float, metavar="DEG",
                        help="serial: joint angles in degrees at which to evaluate M, G and "
                             "the tool pose (default: all zero)")
    parser.add_argument("--at", nargs=5, type=float, metavar="X",
                        help="parallel: th1 th2 d1 th1' th2' in deg, deg, m, deg, deg (default: "
                             "the joint-space scenario's start)")
    args = parser.parse_args(argv)
    tolerate_closed_stdout()
    try:
        SUMMARIES[args.robot](args)
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
