"""Closed-form inverse kinematics of a planar 3R arm, symbolic (for trajectories) and numeric.

The tool pose ``[x, y, phi]`` fixes the wrist point ``w = p - l3 (cos phi, sin phi)``; the first
two links reach ``w`` with the elbow on one of two sides, ``elbow = +1`` (``th2 >= 0``) or
``elbow = -1`` (``th2 <= 0``). The branch is always an explicit choice: numerically it is taken
nearest to a reference configuration, then kept fixed along a trajectory.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ...errors import KinematicsError, ModelError
from .description import Arm


class UnreachableTarget(KinematicsError):
    """A task-space target lies outside the arm's workspace."""


def planar_3r_lengths(arm: Arm) -> tuple[float, float, float]:
    """Link lengths of a planar 3R arm; refuses chains the closed form does not describe."""
    ok = len(arm.links) == 3
    for i, link in enumerate(arm.links if ok else ()):
        j = link.joint
        parent_length = arm.links[i - 1].length if i else 0.0
        ok &= (j.type == "revolute" and np.allclose(j.axis, [0, 0, 1])
               and np.allclose(j.origin_rpy, 0) and np.allclose(j.origin_xyz,
                                                               [parent_length, 0, 0]))
    if not ok:
        raise ModelError(f"arm {arm.name!r}: closed-form inverse kinematics needs a planar 3R "
                         "arm (revolute z axes, each joint at the previous link's tip)")
    return tuple(link.length for link in arm.links)


def world_to_base(arm: Arm, pose_world):
    """A tool pose ``[x, y, phi]`` (m, m, rad) from the cochlea frame into the arm's base frame."""
    c, s = np.cos(arm.base_yaw), np.sin(arm.base_yaw)
    dx = pose_world[0] - arm.base_xyz[0]
    dy = pose_world[1] - arm.base_xyz[1]
    return [c * dx + s * dy, -s * dx + c * dy, pose_world[2] - arm.base_yaw]


def elbow_cosine(arm: Arm, pose_base):
    """``cos th2`` of the pose; the pose is reachable iff it lies in [-1, 1]."""
    l1, l2, l3 = planar_3r_lengths(arm)
    x, y, phi = pose_base[0], pose_base[1], pose_base[2]
    wx, wy = x - l3 * ca.cos(phi), y - l3 * ca.sin(phi)
    return (wx**2 + wy**2 - l1**2 - l2**2) / (2 * l1 * l2)


def ik_symbolic(arm: Arm, pose_base, elbow: int, offsets=(0.0, 0.0, 0.0)) -> ca.SX:
    """Joint angles (rad) reaching ``pose_base`` on the given elbow branch, as an expression.

    ``offsets`` adds whole turns (2 pi k) chosen once so the solution is continuous with a
    reference configuration. Valid only where :func:`elbow_cosine` is inside [-1, 1]; callers
    check reachability over the whole trajectory before using it.
    """
    l1, l2, l3 = planar_3r_lengths(arm)
    x, y, phi = pose_base[0], pose_base[1], pose_base[2]
    wx, wy = x - l3 * ca.cos(phi), y - l3 * ca.sin(phi)
    c2 = (wx**2 + wy**2 - l1**2 - l2**2) / (2 * l1 * l2)
    th2 = elbow * ca.acos(c2)
    th1 = ca.atan2(wy, wx) - ca.atan2(l2 * ca.sin(th2), l1 + l2 * ca.cos(th2))
    th3 = phi - th1 - th2
    return ca.vertcat(th1 + offsets[0], th2 + offsets[1], th3 + offsets[2])


def ik(arm: Arm, pose_world, reference_q) -> tuple[np.ndarray, int, np.ndarray]:
    """Joint angles (rad) for a tool pose in the cochlea frame, nearest to ``reference_q``.

    Returns ``(q, elbow, offsets)``: the branch and whole-turn offsets used, so a trajectory can
    keep them. Raises :class:`UnreachableTarget` outside the workspace.
    """
    pose_base = world_to_base(arm, pose_world)
    c2 = float(elbow_cosine(arm, pose_base))
    if not -1.0 <= c2 <= 1.0:
        l1, l2, l3 = planar_3r_lengths(arm)
        raise UnreachableTarget(
            f"arm {arm.name!r}: the tool pose x = {pose_world[0]:.4f} m, y = {pose_world[1]:.4f} m,"
            f" phi = {np.degrees(pose_world[2]):.2f} deg (cochlea frame) is out of reach: its "
            f"wrist point must lie between {abs(l1 - l2):.4f} m and {l1 + l2:.4f} m from the base")
    reference_q = np.asarray(reference_q, float)
    best = None
    for elbow in (1, -1):
        q = np.array(ik_symbolic(arm, ca.DM(pose_base), elbow)).ravel()
        offsets = 2 * np.pi * np.round((reference_q - q) / (2 * np.pi))
        q = q + offsets
        distance = np.linalg.norm(q - reference_q)
        if best is None or distance < best[0]:
            best = (distance, q, elbow, offsets)
    return best[1], best[2], best[3]
