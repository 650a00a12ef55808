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
        unit = system.arm(arm_name)
        prismatic = [link.joint.type == "prismatic" for link in unit.links]
        for link in unit.links:
            t = link.joint.transmission
            if t is not None:  # the motor's m/rad: what the drive and the bridge use
                print(f"  transmission {link.name}: {t.kind.replace('_', ' ')} "
                      f"{t.size:g} {'m/rad' if t.kind == 'ratio' else 'm'}: {t.ratio:.6g} m "
                      f"per motor rad, motor torque = force * {t.ratio:.6g} m")
        if args.at_deg is not None:
            if len(args.at_deg) != arm.nq:
                raise CochleaError(f"--at-deg needs {arm.nq} joint values (deg; m for a "
                                   f"prismatic joint), got {len(args.at_deg)}")
            # deg for a revolute joint, m for a prismatic one (as the description's poses)
            q = np.array([v if p else np.radians(v) for v, p in zip(args.at_deg, prismatic)])
        else:
            q = np.zeros(arm.nq)
        x, y, phi = np.array(arm.fk_world(q)).ravel()
        np.set_printoptions(precision=6, suppress=False)
        shown = [f"{v:.6g} m" if p else f"{np.degrees(v):.6g} deg" for v, p in zip(q, prismatic)]
        print(f"  at q = [{', '.join(shown)}]:")
        print(f"    tool in the cochlea frame: x = {x:.6f} m, y = {y:.6f} m, "
              f"phi = {np.degrees(phi):.3f} deg")
        if not (is_planar(unit) and unit.base_is_level):  # a spatial arm: its whole tool pose
            pose = np.array(task_space(unit, "pose").fk(q)).ravel()
            print(f"    tool pose: x, y, z = {pose[0]:.6f}, {pose[1]:.6f}, {pose[2]:.6f} m, "
                  "roll, pitch, yaw = " + ", ".join(f"{np.degrees(v):.3f}" for v in pose[3:])
                  + " deg")
        if any(prismatic):  # M_ij in kg m^2, kg m or kg; G in N m or N, by joint type
            print("    M(q) [kg m^2; kg m between a revolute and a prismatic joint; kg between "
                  "two prismatic joints] =")
        else:
            print("    M(q) [kg m^2] =")
        for row in np.array(arm.M(q)):
            print("      " + "  ".join(f"{v: .6e}" for v in row))
        print("    G(q) [" + ("N m; N at a prismatic joint" if any(prismatic) else "N m")
              + "] = " + "  ".join(f"{v: .3e}" for v in np.array(arm.G(q)).ravel()))
        print()
