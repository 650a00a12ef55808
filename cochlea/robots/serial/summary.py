"""``cochlea-model``'s summary of a serial system: each arm's parameters, M, G and the tool
pose at a configuration."""

from __future__ import annotations

import numpy as np

from ...errors import CochleaError
from .chain import is_planar
from .description import SerialSystem
from .task import task_space


def print_summary(adapter, system: SerialSystem, args) -> None:
    """``cochlea-model``'s text for the serial arms (``args``: its parsed options)."""
    if args.at is not None:
        raise CochleaError("--at is for the parallel mechanism; give the serial arm's joint "
                           "angles with --at-deg")
    arm_names = [args.arm] if args.arm else [a.name for a in system.arms]
    for arm_name in arm_names:
        arm = adapter.model(system, arm_name, parameterisation=args.parameterisation,
                            method=args.method or "newton-euler")
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
        unit = system.arm(arm_name)
        if not (is_planar(unit) and unit.base_is_level):  # a spatial arm: its whole tool pose
            pose = np.array(task_space(unit, "pose").fk(q)).ravel()
            print(f"    tool pose: x, y, z = {pose[0]:.6f}, {pose[1]:.6f}, {pose[2]:.6f} m, "
                  "roll, pitch, yaw = " + ", ".join(f"{np.degrees(v):.3f}" for v in pose[3:])
                  + " deg")
        print("    M(q) [kg m^2] =")
        for row in np.array(arm.M(q)):
            print("      " + "  ".join(f"{v: .6e}" for v in row))
        print("    G(q) [N m] = " + "  ".join(f"{v: .3e}" for v in np.array(arm.G(q)).ravel()))
        print()
