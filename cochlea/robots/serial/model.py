"""The symbolic model of one arm of the serial system: Newton-Euler (default) or Lagrange."""

from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np

from ..description import Actuator
from ..lagrange import christoffel_coriolis, gravity_vector, mass_matrix
from ..model import (
    JointInfo,
    RobotModel,
    assemble_model,
    check_options,
    full_inertial,
    with_armatures,
)
from ..spatial import rot_z
from .aba import aba
from .chain import (
    energies,
    inertial_parameters,
    n_parameters,
    planar_orientation,
    rnea,
    tool_point,
)
from .description import Arm, SerialSystem, joint_name


def rigid_arm(arm: Arm) -> Arm:
    """The arm without its drives' terms: the thesis's rigid links."""
    return replace(arm, links=tuple(replace(link, joint=replace(link.joint, actuator=Actuator()))
                                    for link in arm.links))


def build_model(system: SerialSystem, arm: Arm | str | None = None,
                parameterisation: str = "inertial", method: str = "newton-euler",
                actuators: str = "none") -> RobotModel:
    """The model of one arm (default: the first) of a loaded serial system, in its base frame
    (``fk``, ``J``) and in the world frame (``fk_world``, ``J_world``); ``actuators``: what it
    carries of the drives (:data:`~cochlea.robots.model.ACTUATORS`)."""
    check_options(parameterisation, method, actuators)
    if not isinstance(arm, Arm):
        arm = system.arms[0] if arm is None else system.arm(arm)
    if actuators == "none":
        arm = rigid_arm(arm)
    n = len(arm.links)
    q = ca.SX.sym("q", n)
    qd = ca.SX.sym("qd", n)
    qdd = ca.SX.sym("qdd", n)
    phi = ca.SX.sym("phi", n_parameters(arm))
    g_base = arm.base_rotation.T @ system.gravity

    forward = regressand = None
    if method == "newton-euler":
        # The forward dynamics by the articulated-body algorithm (O(n), exact; a symbolic
        # solve of a spatial 6x6 mass matrix expands to several times the operations).
        def forward(q_, qd_, tau_):
            return aba(arm, q_, qd_, tau_, phi, g_base)
        # The regressor's M qdd_r + C(qd) qd_r + G with the Christoffel C, by two Newton-Euler
        # passes: C(qd) qd_r is a symmetric bilinear form B(qd, qd_r) with B(v, v) = h(v),
        # the velocity terms, so B(a, b) = h((a + b) / 2) - h((a - b) / 2) (polarisation).
        def regressand(q_, qd_, qd_r_, qdd_r_):
            return (rnea(arm, q_, (qd_ + qd_r_) / 2, qdd_r_, phi, g_base)
                    - rnea(arm, q_, (qd_ - qd_r_) / 2, ca.SX.zeros(n), phi, np.zeros(3)))
        tau = rnea(arm, q, qd, qdd, phi, g_base)
        M = ca.jacobian(rnea(arm, q, ca.SX.zeros(n), qdd, phi, np.zeros(3)), qdd)
        M = 0.5 * (M + M.T)  # symmetric by construction, not only up to rounding
        G = rnea(arm, q, ca.SX.zeros(n), ca.SX.zeros(n), phi, g_base)
        C = christoffel_coriolis(M, q, qd)
    else:
        K, U = energies(arm, q, qd, phi, g_base)
        M = mass_matrix(K, qd)
        G = gravity_vector(U, q)
        C = christoffel_coriolis(M, q, qd)
        tau = M @ qdd + C @ qd + G

    tip, R_tip = tool_point(arm, q)
    fk = ca.vertcat(tip[0], tip[1], planar_orientation(arm, q))
    if arm.base_is_level:
        Rb = rot_z(arm.base_yaw)
        tip_world = ca.DM(arm.base_xyz[:2]) + Rb[:2, :2] @ tip[:2]
        fk_world = ca.vertcat(tip_world, fk[2] + arm.base_yaw)
    else:  # a rolled or pitched base: the tool's heading from its world rotation
        Rb = ca.DM(arm.base_rotation)
        tip_world = ca.DM(arm.base_xyz) + Rb @ tip
        R_world = Rb @ R_tip
        fk_world = ca.vertcat(tip_world[0], tip_world[1], ca.atan2(R_world[1, 0], R_world[0, 0]))
    kinematics = {"fk": fk, "J": ca.jacobian(fk, q), "fk_world": fk_world,
                  "J_world": ca.jacobian(fk_world, q)}

    joints = tuple(
        JointInfo(joint_name(link), link.joint.type, link.joint.position_limits,
                  link.joint.velocity_limit, link.joint.effort_limit)
        for link in arm.links
    )
    full, blocks = with_armatures(
        *full_inertial([(link.name, inertial_parameters(link)) for link in arm.links]),
        [(j.name, j.type, link.joint.actuator.armature) for j, link in zip(joints, arm.links)])
    friction = ([(link.joint.actuator.viscous, link.joint.actuator.coulomb) for link in arm.links]
                if actuators == "all" else None)
    return assemble_model(f"{system.name}/{arm.name}", f"{system.name}_{arm.name}",
                          joints=joints, q=q, qd=qd, qdd=qdd, phi=phi, M=M, C=C, G=G, tau=tau,
                          kinematics=kinematics, full=full, bodies=blocks,
                          parameterisation=parameterisation, method=method, source=system.path,
                          friction=friction, actuators=actuators, forward=forward,
                          regressand=regressand)

