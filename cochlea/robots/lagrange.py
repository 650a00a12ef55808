"""Generic Euler-Lagrange terms for any mechanism given its energies.

Used directly by closed-chain models (the parallel mechanism) and as the independent cross-check
of the serial chain's Newton-Euler recursion.
"""

from __future__ import annotations

import casadi as ca


def mass_matrix(kinetic_energy: ca.SX, qd: ca.SX) -> ca.SX:
    """``M = d^2 K / d qd^2`` (K is quadratic in qd, so this is exact)."""
    M, _ = ca.hessian(kinetic_energy, qd)
    return M


def gravity_vector(potential_energy: ca.SX, q: ca.SX) -> ca.SX:
    """``G = dU/dq`` as a column."""
    return ca.gradient(potential_energy, q)


def christoffel_coriolis(M: ca.SX, q: ca.SX, qd: ca.SX) -> ca.SX:
    """The Coriolis/centripetal matrix from Christoffel symbols of the first kind.

    ``C[k, j] = sum_i 1/2 (dM[k,j]/dq_i + dM[k,i]/dq_j - dM[i,j]/dq_k) qd_i``. With this choice
    ``M_dot - 2 C`` is skew-symmetric, the property the adaptive controllers' Lyapunov
    analyses rely on.
    """
    n = q.shape[0]
    dM = [ca.jacobian(M, q[i]) for i in range(n)]  # each n*n x 1, column-major vec of dM/dq_i
    dM = [ca.reshape(d, n, n) for d in dM]
    C = ca.SX.zeros(n, n)
    for k in range(n):
        for j in range(n):
            C[k, j] = sum(
                0.5 * (dM[i][k, j] + dM[j][k, i] - dM[k][i, j]) * qd[i] for i in range(n)
            )
    return C


def time_derivative(expr: ca.SX, q: ca.SX, qd: ca.SX) -> ca.SX:
    """``d/dt expr(q)`` along ``q_dot = qd``, for a vector or matrix expression."""
    rows, cols = expr.shape
    return ca.reshape(ca.jacobian(ca.vec(expr), q) @ qd, rows, cols)
