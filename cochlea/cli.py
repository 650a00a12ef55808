"""Command-line entry points. User mistakes print one line and exit with EXIT_USER_ERROR."""

from __future__ import annotations

import argparse
import sys

import numpy as np

from .errors import EXIT_USER_ERROR, CochleaError


def _print_model_summary(args: argparse.Namespace) -> None:
    from .description import load_serial
    from .model import model

    system = load_serial(args.description or args.robot)
    arm_names = [args.arm] if args.arm else [a.name for a in system.arms]
    for arm_name in arm_names:
        arm = model(args.robot, arm=arm_name, parameterisation=args.parameterisation,
                    method=args.method, description=args.description)
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


def model_main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="cochlea-model",
        description="Print the symbolic model of a robot: joints and limits, dynamic parameters "
                    "(full, base or mass-only), and M, G and the tool pose at a configuration.",
    )
    parser.add_argument("robot", nargs="?", default="serial", choices=["serial"],
                        help="which robot (the parallel mechanism arrives with issue 3)")
    parser.add_argument("--arm", help="one arm of the serial system (default: every arm)")
    parser.add_argument("--parameterisation", default="base", choices=["inertial", "base", "mass"],
                        help="parameter set to list (default: base)")
    parser.add_argument("--method", default="newton-euler", choices=["newton-euler", "lagrange"])
    parser.add_argument("--description", help="a robot description TOML instead of models/")
    parser.add_argument("--at-deg", nargs="+", type=float, metavar="DEG",
                        help="joint angles in degrees at which to evaluate M, G and the tool "
                             "pose (default: all zero)")
    args = parser.parse_args(argv)
    try:
        _print_model_summary(args)
    except CochleaError as exc:
        print(f"cochlea-model: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    return 0
