"""``cochlea-model``'s summary of the parallel mechanism: its parameters, geometry, motors, both
end effectors, M and G at a configuration."""

from __future__ import annotations

import numpy as np

from ...errors import CochleaError
from .description import ParallelSystem
from .geometry import SCENARIO_START


def print_summary(adapter, system: ParallelSystem, args) -> None:
    """``cochlea-model``'s text for the parallel mechanism (``args``: its parsed options)."""
    if args.arm is not None:
        raise CochleaError("--arm is for the serial system; the parallel mechanism is one robot")
    if args.at_deg is not None:
        raise CochleaError("--at-deg is for the serial arms; give the parallel mechanism's "
                           "th1 th2 d1 th1' th2' (deg, deg, m, deg, deg) with --at")
    if args.method == "newton-euler":
        raise CochleaError("the parallel mechanism is a closed chain: its model comes from the "
                           "Lagrange method only (--method lagrange, the default for it)")
    robot = adapter.model(system, parameterisation=args.parameterisation, method="lagrange")
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
