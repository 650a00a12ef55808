"""Forward dynamics of one serial chain by the articulated-body algorithm (Featherstone's ABA).

``qdd = ABA(q, qd, tau)`` solves ``M(q) qdd = tau - h(q, qd)`` exactly (the same rigid-body
dynamics as :func:`~cochlea.robots.serial.chain.rnea`) in O(n) operations, without forming
``M`` or solving it: a symbolic ``ca.solve`` of a spatial 6x6 mass matrix expands to many
times the operations (issue 25: the plant's RK4 step evaluates it four times a period).

Conventions are :func:`~cochlea.robots.serial.chain.rnea`'s: every quantity in its link's
own frame, spatial motion vectors ``[w; v]`` (angular velocity, velocity of the link frame's
origin) and force vectors ``[n; f]`` (moment about the origin, force); the link's inertia in
its ten standard parameters ``[m, mx, my, mz, Ixx, Iyy, Izz, Ixy, Ixz, Iyz]`` (first moment
``h = m c``, inertia about the frame origin); the joint's motion subspace its axis ``z`` in
the link frame (revolute ``[z; 0]``, prismatic ``[0; z]``); gravity enters as an upward
acceleration of the base. A joint's armature ``Ia`` (``Ia * qdd`` on its own coordinate) adds
to that joint's articulated inertia ``D = S' IA S + Ia``.

The articulated inertias are built in 3x3 blocks, symmetric by construction (only the upper
triangle computed, the lower the same SX nodes), so the generated C carries each product once.
"""

from __future__ import annotations

import casadi as ca

from .chain import N_INERTIAL, armature_indices, joint_transform
from .description import Arm


def _inertial(phi) -> tuple:
    """A link's ten parameters as ``(m, h, I)``: mass, first moment, inertia about the origin."""
    return phi[0], phi[1:4], _sym3([phi[4], phi[7], phi[8], phi[5], phi[9], phi[6]])


def _sym3(entries) -> ca.SX:
    """The symmetric 3x3 matrix of its upper triangle ``[a00, a01, a02, a11, a12, a22]``."""
    a00, a01, a02, a11, a12, a22 = entries
    return ca.vertcat(ca.horzcat(a00, a01, a02), ca.horzcat(a01, a11, a12),
                      ca.horzcat(a02, a12, a22))


def _symmetrise(A) -> ca.SX:
    """``A`` with its lower triangle the same nodes as its upper (A symmetric in exact
    arithmetic): the C then computes each entry once."""
    return _sym3([A[0, 0], A[0, 1], A[0, 2], A[1, 1], A[1, 2], A[2, 2]])


def _inertia_product(A, B, C, w, v):
    """``[A B; B' C] @ [w; v]`` (a spatial inertia in blocks, A and C symmetric)."""
    return A @ w + B @ v, B.T @ w + C @ v


def aba(arm: Arm, q, qd, tau, phi, gravity_base) -> ca.SX:
    """Joint accelerations ``qdd`` (rad/s^2 or m/s^2) of the arm under joint torques ``tau``
    (N m or N), ``phi`` and ``gravity_base`` as in :func:`~cochlea.robots.serial.chain.rnea`
    (the gravity vector in the arm's base frame, m/s^2)."""
    n = len(arm.links)
    armature = {i: phi[N_INERTIAL * n + k] for k, i in enumerate(armature_indices(arm))}

    # Pass 1, outward: transforms, velocities, velocity-product accelerations, bias forces.
    w = ca.SX.zeros(3)
    v = ca.SX.zeros(3)
    links = []
    for i, link in enumerate(arm.links):
        R, p = joint_transform(link.joint, q[i])
        z = ca.DM(link.joint.axis)
        revolute = link.joint.type == "revolute"
        # Parent's velocity carried into this frame: w' = R' w, v' = R' (v + w x p).
        w_in = R.T @ w
        v_in = R.T @ (v + ca.cross(w, p))
        if revolute:
            w = w_in + z * qd[i]
            v = v_in
            # c = v x (S qd), S qd = [z qd; 0]: [w x z qd; v x z qd]
            c_w = ca.cross(w, z * qd[i])
            c_v = ca.cross(v, z * qd[i])
        else:
            w = w_in
            v = v_in + z * qd[i]
            c_w = ca.SX.zeros(3)
            c_v = ca.cross(w, z * qd[i])
        m, h, I = _inertial(phi[N_INERTIAL * i: N_INERTIAL * (i + 1)])
        H = ca.vertcat(ca.horzcat(0, -h[2], h[1]), ca.horzcat(h[2], 0, -h[0]),
                       ca.horzcat(-h[1], h[0], 0))
        # Spatial inertia about the origin: [I  hx; hx' m 1] ([hx] = skew(h)).
        A, B, C = I, H, m * ca.SX.eye(3)
        L_w, L_v = _inertia_product(A, B, C, w, v)  # momentum [angular; linear]
        # Bias force v x* (I v): [w x L_w + v x L_v; w x L_v].
        pA_w = ca.cross(w, L_w) + ca.cross(v, L_v)
        pA_v = ca.cross(w, L_v)
        links.append({"R": R, "p": p, "z": z, "revolute": revolute, "c": (c_w, c_v),
                      "IA": [A, B, C], "pA": [pA_w, pA_v]})

    # Pass 2, inward: articulated inertias and bias forces.
    for i in reversed(range(n)):
        L = links[i]
        A, B, C = L["IA"]
        pA_w, pA_v = L["pA"]
        z = L["z"]
        # U = IA S; D = S' U (+ armature); u = tau - S' pA.
        if L["revolute"]:
            U_w, U_v = A @ z, B.T @ z
            D = ca.dot(z, U_w)
            u = tau[i] - ca.dot(z, pA_w)
        else:
            U_w, U_v = B @ z, C @ z
            D = ca.dot(z, U_v)
            u = tau[i] - ca.dot(z, pA_v)
        if i in armature:
            D = D + armature[i]
        L["U"], L["D"], L["u"] = (U_w, U_v), D, u
        if i == 0:
            continue
        # Ia = IA - U U' / D, pa = pA + Ia c + U u / D, carried to the parent.
        Dinv = 1 / D
        Uw_s, Uv_s = U_w * Dinv, U_v * Dinv
        Aa = _symmetrise(A - Uw_s @ U_w.T)
        Ba = B - Uw_s @ U_v.T
        Ca = _symmetrise(C - Uv_s @ U_v.T)
        c_w, c_v = L["c"]
        f_w, f_v = _inertia_product(Aa, Ba, Ca, c_w, c_v)
        pa_w = pA_w + f_w + Uw_s * u
        pa_v = pA_v + f_v + Uv_s * u
        # To the parent frame: X' = [R  px R; 0  R] on forces ([px] = skew(p)), and
        # X' Ia X on inertias, with X = [R' 0; -R' px  R'].
        R, p = L["R"], L["p"]
        P = ca.vertcat(ca.horzcat(0, -p[2], p[1]), ca.horzcat(p[2], 0, -p[0]),
                       ca.horzcat(-p[1], p[0], 0))
        f_par = R @ pa_v
        n_par = R @ pa_w + ca.cross(p, f_par)
        # Rotate the blocks: A_r = R Aa R', B_r = R Ba R', C_r = R Ca R'.
        A_r = _symmetrise(R @ Aa @ R.T)
        B_r = R @ Ba @ R.T
        C_r = _symmetrise(R @ Ca @ R.T)
        # Shift by p: [I px; 0 I] [A B; B' C] [I 0; -px I]
        #   = [A - B px + px B' - px C px,  B + px C;  B' - C px,  C], and px B' = -(B px)'.
        PC = P @ C_r
        B_s = B_r + PC
        BP = B_r @ P
        A_s = _symmetrise(A_r - BP - BP.T - PC @ P)
        parent = links[i - 1]
        pA, pB, pC = parent["IA"]
        parent["IA"] = [_symmetrise(pA + A_s), pB + B_s, _symmetrise(pC + C_r)]
        parent["pA"] = [parent["pA"][0] + n_par, parent["pA"][1] + f_par]

    # Pass 3, outward: accelerations. The base accelerates upward at g: a0 = [0; -g].
    a_w = ca.SX.zeros(3)
    a_v = -ca.DM(gravity_base) + ca.SX.zeros(3)
    qdd = []
    for i in range(n):
        L = links[i]
        R, p = L["R"], L["p"]
        c_w, c_v = L["c"]
        aw = R.T @ a_w + c_w
        av = R.T @ (a_v + ca.cross(a_w, p)) + c_v
        U_w, U_v = L["U"]
        qdd_i = (L["u"] - ca.dot(U_w, aw) - ca.dot(U_v, av)) / L["D"]
        if L["revolute"]:
            a_w, a_v = aw + L["z"] * qdd_i, av
        else:
            a_w, a_v = aw, av + L["z"] * qdd_i
        qdd.append(qdd_i)
    return ca.vertcat(*qdd)


def n_operations(expr, *symbols) -> int:
    """The number of SX operations of ``expr`` as one Function of ``symbols``."""
    return ca.Function("ops", list(symbols), [expr]).n_instructions()


__all__ = ["aba", "n_operations"]
