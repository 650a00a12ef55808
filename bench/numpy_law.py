"""Controller e's fused step in plain NumPy, for the benchmark: the honest hand-written baseline.

Closed-form dynamics of a planar serial arm (revolute joints about z, joint i+1 at the tip of
link i, as in ``models/serial.toml``) in the thesis's mass parameterisation: link i contributes
``p_i * M_i(q)`` with ``M_i = Jv_i' Jv_i + (Izz_i / m_i) a_i a_i'`` (Jv_i the Jacobian of its
centre of mass, a_i selects joints 1..i; all inertial parameters scale with the mass), the
Christoffel Coriolis matrix from ``dM_i/dq`` in closed form (``d Jv_i[:, j] / dq_l =
-(c_i - o_max(j, l))``), gravity from the in-plane component of g. The regressor's column i is
``M_i qdd_r + C_i qd_r + G_i``; the law, the projected update and the Euler step with the clip
follow ``cochlea.controllers`` line by line. ``tests/test_ckernels.py`` holds it to the C kernel.
"""

from __future__ import annotations

import numpy as np


class NumpyStepE:
    """``step(q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound, h, *robust)`` of controller e
    (corrected variant) on one planar arm of a serial description."""

    def __init__(self, arm, gravity_base):
        for link in arm.links:
            j = link.joint
            if j.type != "revolute" or not np.allclose(j.axis, [0, 0, 1]):
                raise NotImplementedError("the NumPy baseline handles planar z-axis arms only")
            if not np.allclose(j.origin_rpy, 0):
                raise NotImplementedError("the NumPy baseline handles unrotated joints only")
        self.n = len(arm.links)
        # joint i's origin in link i-1's frame (the first at the base)
        self.offsets = np.array([link.joint.origin_xyz[:2] for link in arm.links])
        self.com = np.array([link.com[:2] for link in arm.links])
        self.izz_per_kg = np.array([link.inertia_com[2, 2] / link.mass for link in arm.links])
        self.g_plane = np.asarray(gravity_base, float)[:2]

    def _kinematics(self, q):
        n = self.n
        theta = np.cumsum(q)
        origins = np.zeros((n, 2))
        coms = np.zeros((n, 2))
        position = np.zeros(2)
        for i in range(n):
            if i > 0:
                c, s = np.cos(theta[i - 1]), np.sin(theta[i - 1])
                x, y = self.offsets[i]
                position = position + np.array([c * x - s * y, s * x + c * y])
            elif np.any(self.offsets[0]):
                position = self.offsets[0].copy()
            origins[i] = position
            c, s = np.cos(theta[i]), np.sin(theta[i])
            x, y = self.com[i]
            coms[i] = position + np.array([c * x - s * y, s * x + c * y])
        return origins, coms

    def _per_link(self, q, qd):
        """Per unit mass of each link: M_i, C_i(q, qd) and G_i."""
        n = self.n
        origins, coms = self._kinematics(q)
        Ms, Cs, Gs = [], [], []
        for i in range(n):
            d = coms[i] - origins[: i + 1]  # (i+1, 2): c_i - o_j
            Jv = np.zeros((2, n))
            Jv[0, : i + 1], Jv[1, : i + 1] = -d[:, 1], d[:, 0]  # z x (c_i - o_j)
            a = np.zeros(n)
            a[: i + 1] = 1.0
            M = Jv.T @ Jv + self.izz_per_kg[i] * np.outer(a, a)
            dM = np.zeros((n, n, n))  # dM[l] = dM/dq_l
            for l in range(i + 1):
                dJ = np.zeros((2, n))
                for j in range(i + 1):
                    dJ[:, j] = -(coms[i] - origins[max(j, l)])
                dM[l] = dJ.T @ Jv + Jv.T @ dJ
            # C[k, j] = sum_l 1/2 (dM[l][k, j] + dM[j][k, l] - dM[k][l, j]) qd_l
            # dM[l, a, b] = dM_ab/dq_l; gamma[k, j, l] = dM[l,k,j] + dM[j,k,l] - dM[k,l,j]
            gamma = 0.5 * (dM.transpose(1, 2, 0) + dM.transpose(1, 0, 2)
                           - dM.transpose(0, 2, 1))
            C = np.einsum("kjl,l->kj", gamma, qd)
            G = -Jv.T @ self.g_plane
            Ms.append(M)
            Cs.append(C)
            Gs.append(G)
        return Ms, Cs, Gs

    def __call__(self, q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound, h,
                 deadzone=0.0, p_min=-np.inf, p_max=np.inf, static_excess=None,
                 stribeck_velocity=None):
        # The rigid links carry no friction: the static-friction shape has nothing to act on.
        n = self.n
        alpha, G_e, K_e = gains[:n], gains[n:2 * n], gains[2 * n:3 * n]
        e = xd - q
        e_dot = xd_dot - qd
        r = e_dot + alpha * e
        qd_r = xd_dot + alpha * e
        qdd_r = xd_ddot + alpha * e_dot
        Ms, Cs, Gs = self._per_link(q, qd)
        Y = np.column_stack([M @ qdd_r + C @ qd_r + G for M, C, G in zip(Ms, Cs, Gs)])
        tau = Y @ p_hat + K_e * e + G_e * r
        s = r - np.clip(r, -deadzone, deadzone)  # the adaptation's dead zone
        raw = Gamma * (Y.T @ s)
        outward = p_hat @ raw
        metric = max(p_hat @ (Gamma * p_hat), 1e-300)
        if p_hat @ p_hat >= (1 - 1e-9) * bound ** 2 and outward > 0:
            raw = raw - Gamma * p_hat * (outward / metric)
        raw = np.where(((p_hat >= p_max) & (raw > 0)) | ((p_hat <= p_min) & (raw < 0)), 0.0, raw)
        p_next = p_hat + h * raw
        p_next = p_next * min(1.0, bound / max(np.linalg.norm(p_next), 1e-300))
        p_next = np.minimum(np.maximum(p_next, p_min), p_max)
        return tau, p_next, np.concatenate([e, r])
