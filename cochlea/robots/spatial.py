"""Small rotation and vector helpers on CasADi SX expressions."""

from __future__ import annotations

import casadi as ca
import numpy as np


def skew(v) -> ca.SX:
    """The matrix ``[v]x`` with ``[v]x w == v x w``."""
    return ca.vertcat(
        ca.horzcat(0, -v[2], v[1]),
        ca.horzcat(v[2], 0, -v[0]),
        ca.horzcat(-v[1], v[0], 0),
    )


def vee(S) -> ca.SX:
    """Inverse of :func:`skew` for a (numerically) skew-symmetric matrix."""
    return ca.vertcat(S[2, 1], S[0, 2], S[1, 0])


def axis_angle(axis: np.ndarray, angle) -> ca.SX:
    """Rotation by ``angle`` (rad, symbolic) about the unit vector ``axis`` (Rodrigues)."""
    K = ca.DM(skew_numeric(axis))
    return ca.DM.eye(3) + ca.sin(angle) * K + (1 - ca.cos(angle)) * (K @ K)


def skew_numeric(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rot_z(angle) -> ca.SX:
    c, s = ca.cos(angle), ca.sin(angle)
    return ca.vertcat(ca.horzcat(c, -s, 0), ca.horzcat(s, c, 0), ca.horzcat(0, 0, 1))
