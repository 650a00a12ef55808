"""Symbolic kinematics and dynamics of one serial chain (revolute and prismatic joints).

All dynamics here are written in the *standard inertial parameters* of each link, ten per link,
in the link frame: ``[m, mx, my, mz, Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` where ``(mx, my, mz)`` is
the first moment of mass ``m * c`` and the inertia is about the link-frame origin (not the
centre of mass). The dynamics are linear in these, which is what makes the Slotine-Li
regressor exact.

Two independent derivations are provided: the recursive Newton-Euler algorithm
(:func:`rnea`, the one the model uses) and the Lagrangian energies (:func:`energies`, the
cross-check).
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from ..lagrange import time_derivative
from ..model import INERTIAL_NAMES
from ..spatial import axis_angle, vee
from .description import Arm, Joint, Link, joint_rotation, rpy_matrix

N_INERTIAL = len(INERTIAL_NAMES)


def inertial_parameters(link: Link) -> np.ndarray:
    """The link's ten standard inertial parameters (parallel-axis shift to the frame origin)."""
    m, c = link.mass, link.com
    inertia_origin = link.inertia_com + m * (float(c @ c) * np.eye(3) - np.outer(c, c))
    I = inertia_origin
    return np.array([m, *(m * c), I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])


def _unpack(phi) -> tuple:
    m = phi[0]
    h = phi[1:4]
    I = ca.vertcat(
        ca.horzcat(phi[4], phi[7], phi[8]),
        ca.horzcat(phi[7], phi[5], phi[9]),
        ca.horzcat(phi[8], phi[9], phi[6]),
    )
    return m, h, I


def joint_transform(joint: Joint, q) -> tuple[ca.SX, ca.SX]:
    """Pose ``(R, p)`` of the link frame in the parent frame at joint coordinate ``q``."""
    R0 = ca.DM(joint_rotation(joint))
    p0 = ca.DM(joint.origin_xyz)
    if joint.type == "revolute":
        return R0 @ axis_angle(joint.axis, q), p0 + ca.SX.zeros(3)
    return R0 + ca.SX.zeros(3, 3), p0 + R0 @ ca.DM(joint.axis) * q


def link_poses(arm: Arm, q: ca.SX) -> list[tuple[ca.SX, ca.SX]]:
    """Pose ``(R, p)`` of every link frame in the arm's base frame."""
    R, p = ca.SX.eye(3), ca.SX.zeros(3)
    poses = []
    for i, link in enumerate(arm.links):
        Rj, pj = joint_transform(link.joint, q[i])
        p = p + R @ pj
        R = R @ Rj
        poses.append((R, p))
    return poses


def tool_offset(arm: Arm) -> np.ndarray:
    """The tool point in the last link's frame (m): ``tool_xyz_m``, else ``[length, 0, 0]``."""
    if arm.tool_xyz is not None:
        return np.asarray(arm.tool_xyz, float)
    return np.array([arm.links[-1].length, 0.0, 0.0])


def tool_point(arm: Arm, q: ca.SX) -> tuple[ca.SX, ca.SX]:
    """Position (base frame) of the tool point (:func:`tool_offset`) and the tool frame's R:
    the last link's, turned by ``tool_rpy_deg`` where the arm gives it."""
    R, p = link_poses(arm, q)[-1]
    if arm.tool_xyz is None:
        p = p + R @ ca.DM([arm.links[-1].length, 0.0, 0.0])
    else:
        p = p + R @ ca.DM(arm.tool_xyz)
    if arm.tool_rpy is not None:
        R = R @ ca.DM(rpy_matrix(arm.tool_rpy))
    return p, R


def is_planar(arm: Arm) -> bool:
    """True when every joint frame keeps z parallel to the base z and revolute axes are +-z.

    Then the tool's planar orientation is the unwrapped sum of the joint angles instead of an
    atan2 that jumps at +-180 deg.
    """
    if arm.tool_rpy is not None and (abs(arm.tool_rpy[0]) > 1e-12
                                     or abs(arm.tool_rpy[1]) > 1e-12):
        return False
    for link in arm.links:
        j = link.joint
        if abs(j.origin_rpy[0]) > 1e-12 or abs(j.origin_rpy[1]) > 1e-12:
            return False
        if j.type == "revolute" and abs(abs(j.axis[2]) - 1.0) > 1e-12:
            return False
    return True


def planar_orientation(arm: Arm, q: ca.SX) -> ca.SX:
    """Tool orientation about base z (rad): unwrapped for planar chains, else from atan2."""
    if is_planar(arm):
        phi = ca.SX(sum(float(l.joint.origin_rpy[2]) for l in arm.links)
                    + (float(arm.tool_rpy[2]) if arm.tool_rpy is not None else 0.0))
        for i, link in enumerate(arm.links):
            if link.joint.type == "revolute":
                phi = phi + float(np.sign(link.joint.axis[2])) * q[i]
        return phi
    _, R = tool_point(arm, q)
    return ca.atan2(R[1, 0], R[0, 0])


def armature_indices(arm: Arm) -> list[int]:
    """The joints whose drive declares an armature, in order: their parameters follow the
    links' ten each in ``phi``."""
    return [i for i, link in enumerate(arm.links) if link.joint.actuator.armature is not None]


def n_parameters(arm: Arm) -> int:
    return N_INERTIAL * len(arm.links) + len(armature_indices(arm))


def rnea(arm: Arm, q, qd, qdd, phi, gravity_base) -> ca.SX:
    """Inverse dynamics ``tau(q, qd, qdd)`` by the recursive Newton-Euler algorithm.

    ``phi`` stacks the ten inertial parameters of each link, then the armature of each joint
    that has one (``Ia * qdd`` on that joint); ``gravity_base`` is the gravity vector in the
    arm's base frame (m/s^2). Quantities are expressed in each link's own frame; gravity enters
    as an upward acceleration of the base (thesis 2.8).
    """
    n = len(arm.links)
    w = ca.SX.zeros(3)
    wd = ca.SX.zeros(3)
    a = -ca.DM(gravity_base) + ca.SX.zeros(3)  # linear acceleration of the frame origin
    kin = []  # per link: R (parent->link), p (link origin in parent), w, wd, a
    for i, link in enumerate(arm.links):
        R, p = joint_transform(link.joint, q[i])
        z = ca.DM(link.joint.axis)
        a_carried = R.T @ (a + ca.cross(wd, p) + ca.cross(w, ca.cross(w, p)))
        if link.joint.type == "revolute":
            w_parent = R.T @ w
            w = w_parent + z * qd[i]
            wd = R.T @ wd + ca.cross(w_parent, z * qd[i]) + z * qdd[i]
            a = a_carried
        else:
            w = R.T @ w
            wd = R.T @ wd
            a = a_carried + 2 * ca.cross(w, z * qd[i]) + z * qdd[i]
        kin.append((R, p, w, wd, a))

    tau = ca.SX.zeros(n)
    F_child = ca.SX.zeros(3)
    N_child = ca.SX.zeros(3)
    R_child = ca.SX.eye(3)
    p_child = ca.SX.zeros(3)
    for i in reversed(range(n)):
        R, p, w, wd, a = kin[i]
        m, h, I = _unpack(phi[N_INERTIAL * i: N_INERTIAL * (i + 1)])
        f = m * a + ca.cross(wd, h) + ca.cross(w, ca.cross(w, h))
        nm = I @ wd + ca.cross(w, I @ w) + ca.cross(h, a)
        F_from_child = R_child @ F_child
        F = f + F_from_child
        N = nm + R_child @ N_child + ca.cross(p_child, F_from_child)
        z = ca.DM(arm.links[i].joint.axis)
        tau[i] = ca.dot(z, N) if arm.links[i].joint.type == "revolute" else ca.dot(z, F)
        F_child, N_child, R_child, p_child = F, N, R, p
    for k, i in enumerate(armature_indices(arm)):
        tau[i] = tau[i] + phi[N_INERTIAL * n + k] * qdd[i]
    return tau


def energies(arm: Arm, q, qd, phi, gravity_base) -> tuple[ca.SX, ca.SX]:
    """Kinetic and potential energy of the arm (J), from the link poses alone.

    Per link, with origin velocity ``v`` and angular velocity ``w`` in the link frame,
    ``K = 1/2 m v.v + v.(w x h) + 1/2 w' I w`` and ``U = -g.(m p + R h)``.
    """
    K = ca.SX(0)
    U = ca.SX(0)
    g = ca.DM(gravity_base)
    for i, (R, p) in enumerate(link_poses(arm, q)):
        m, h, I = _unpack(phi[N_INERTIAL * i: N_INERTIAL * (i + 1)])
        v = R.T @ time_derivative(p, q, qd)
        w = R.T @ vee(time_derivative(R, q, qd) @ R.T)
        K = K + 0.5 * m * ca.dot(v, v) + ca.dot(v, ca.cross(w, h)) + 0.5 * ca.dot(w, I @ w)
        U = U - ca.dot(g, m * p + R @ h)
    n = len(arm.links)
    for k, i in enumerate(armature_indices(arm)):  # the rotors, each on its own coordinate
        K = K + 0.5 * phi[N_INERTIAL * n + k] * qd[i] ** 2
    return K, U
