"""The closed chain's forward dynamics in a cheaper exact form (issue 30, item 1).

The Lagrange model (:mod:`cochlea.robots.parallel.model`) differentiates the kinetic energy
twice for ``M``, once more for the Christoffel ``C`` and solves ``M qdd = tau - C qd - G`` with
CasADi's symbolic QR: 1688 operations an evaluation at the shipped plant's parameters, 1266 of
them the bias ``C qd + G``, 370 the solve. The same dynamics, computed body by body:

* every body's pose is an explicit function of q, so its origin moves at ``v = J_o qd`` and it
  turns at ``omega = j qd``; at ``qdd = 0`` its origin accelerates at ``a = J_o_dot qd`` and it
  at ``alpha = j_dot qd``, written out below from the geometry (no symbolic differentiation);
* each planar body ``[m, h = (mx, my), Izz]`` (body frame at its origin, turned by its angle)
  then needs, about its origin, the force ``F = m (a - g) + alpha E h - omega^2 R h`` and the
  moment ``N = Izz alpha + (R h) x (a - g)`` (gravity as an acceleration of the world), and
  adds ``J_o^T F + j^T N`` to the bias and ``m J_o^T J_o + J_o^T (E h) j + j^T (E h)^T J_o +
  Izz j^T j`` to M (Kane's equations, which equal Lagrange's for these energies term by term);
* ``M`` couples the two sides only through the slider (``M[0:2, 3:5] = 0``): in the order
  ``(th1, th2, th1', th2', d1)`` it is two 2x2 blocks with a border, so ``M qdd = rhs`` is two
  2x2 solves and one scalar Schur complement (an LDL^T factorisation with no fill-in; M is
  symmetric positive definite, so no pivoting);
* the four motor angles' sines and cosines are computed once and shared by every body; each
  side takes one square root (the rod's direction ``(C - S) / |C - S|``).

At the shipped plant's parameters folded in, an evaluation is 429 operations instead of 1688
(docs/models.md); it agrees with the Lagrange model's forward dynamics to rounding
(tests/test_parallel_forward.py: 1e-12 relative on random states, 2e-14 measured). It is not
the general kernels' form (generated_c/ keeps the Lagrange one, bit for bit what every
simulation ran); the all-in-C simulation's plant, specialised to its scenario, runs it
(bench/embedded_bench.py).
"""

from __future__ import annotations

import casadi as ca

from ...errors import ModelError
from ..model import ARMATURE, RobotModel
from .description import ParallelSystem
from .model import _full_parameters


def _cross(a, b):
    """The planar cross product ``a_u b_v - a_v b_u``."""
    return a[0] * b[1] - a[1] * b[0]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1]


def _reciprocal(y):
    """``1 / y`` as a node that stays a product where it is used: CasADi rewrites ``x * (1 / y)``
    into ``x / y``, a division at every use (a division costs several multiplications).
    ``2 / (y + y)`` is the same double (the sum and the quotient are exact and correctly
    rounded)."""
    return 2 / (y + y)


class _Side:
    """One side's three coordinates ``(th1, th2, d1)``: M's 3x3 block (upper triangle) and the
    bias's three entries, accumulated body by body.

    A body is given by its origin's velocity columns ``J`` (per coordinate ``(vector, its
    squared length)``, or None for zero), its angular rate's row ``j`` (per coordinate an entry
    or None), the velocity-product accelerations ``a`` (origin) and ``alpha`` (angle) and the
    rate ``omega``. Bodies that turn alike (the same ``j``, named by ``turn``) share their
    rotational terms: their inertias ``Izz`` and moments are summed first, then multiplied by
    ``j`` once (fewer operations, and the folded constants add up before they meet a
    variable)."""

    def __init__(self):
        self.M = [[0, 0, 0] for _ in range(3)]
        self.b = [0, 0, 0]
        self.turns = {}  # turn -> [j, alpha, sum of Izz, sum of (R h) x (a - g), J^T E h]

    def body(self, turn, params, J, j, a, alpha, omega, cos, sin, gravity):
        m, hx, hy, izz = (params[k] for k in range(4))
        Rh = (cos * hx - sin * hy, sin * hx + cos * hy)
        Eh = (-Rh[1], Rh[0])
        ag = (a[0] - gravity[0], a[1] - gravity[1])
        group = self.turns.setdefault(turn, [j, alpha, 0, 0, [0, 0, 0]])
        group[2] = group[2] + izz
        group[3] = group[3] + _cross(Rh, ag)
        if all(c is None for c in J):
            return
        w2 = omega * omega
        F = (m * ag[0] + alpha * Eh[0] - w2 * Rh[0], m * ag[1] + alpha * Eh[1] - w2 * Rh[1])
        for k in range(3):
            if J[k] is None:
                continue
            self.b[k] = self.b[k] + _dot(J[k][0], F)
            group[4][k] = group[4][k] + _dot(J[k][0], Eh)
            for col in range(k, 3):
                if J[col] is not None:
                    self.M[k][col] = self.M[k][col] + m * (
                        J[k][1] if k == col else _dot(J[k][0], J[col][0]))

    def finish(self):
        """Add each turn's rotational terms: ``j^T (Izz alpha + sum (R h) x (a - g))`` to the
        bias, ``Izz j^T j + U j^T + j U^T`` to M with ``U = sum J^T E h``."""
        for j, alpha, izz, moment, U in self.turns.values():
            N = izz * alpha + moment
            t = [None if jk is None else izz * jk for jk in j]
            for k in range(3):
                if j[k] is not None:
                    self.b[k] = self.b[k] + j[k] * N
                for col in range(k, 3):
                    term = 0
                    if j[k] is not None and j[col] is not None:
                        term = term + t[k] * j[col]
                    if j[col] is not None:
                        term = term + U[k] * j[col]
                    if j[k] is not None:
                        term = term + U[col] * j[k]
                    self.M[k][col] = self.M[k][col] + term
        return self


def _side_terms(system: ParallelSystem, side, q, qd, phi_of):
    """M's block and the bias of one side's six bodies in its coordinates ``(th1, th2, d1)``
    (``q``, ``qd``: those three)."""
    th1, th2, d1 = q
    w1, w2, vd = qd
    lp = system.link_length
    g = (float(system.gravity[0]), float(system.gravity[1]))
    c1, s1, c2, s2 = ca.cos(th1), ca.sin(th1), ca.cos(th2), ca.sin(th2)
    bu = side.sign * system.base_offset
    out = _Side()
    none3 = (None, None, None)
    zero = (0, 0)

    def params(body):
        return phi_of(f"{side.name}.{body}")

    # Links 1 and 4 turn about the base: only their rotation and gravity.
    out.body("th1", params("link1"), none3, (1, None, None), zero, 0, w1, c1, s1, g)
    out.body("th2", params("link4"), none3, (None, 1, None), zero, 0, w2, c2, s2, g)
    # Link 2 hangs at link 1's tip A1 = B + lp e(th1), turned by th2; link 3 at A4, by th1.
    p1, p2 = (-lp * s1, lp * c1), (-lp * s2, lp * c2)  # d A1 / d th1, d A4 / d th2
    k1, k2 = lp * (w1 * w1), lp * (w2 * w2)
    a1, a2 = (-k1 * c1, -k1 * s1), (-k2 * c2, -k2 * s2)  # A1's and A4's accelerations
    J1, J2 = (p1, lp * lp), (p2, lp * lp)
    out.body("th2", params("link2"), (J1, None, None), (None, 1, None), a1, 0, w2, c2, s2, g)
    out.body("th1", params("link3"), (None, J2, None), (1, None, None), a2, 0, w1, c1, s1, g)
    # Links 5 (at C) and 7 (at S) turn with the rod, phi = atan2(C_v - d1, C_u).
    wu = bu + lp * (c1 + c2)
    wv = lp * (s1 + s2) - d1
    w = (wu, wv)
    inv_r = _reciprocal(ca.sqrt(wu * wu + wv * wv))
    inv_r2 = inv_r * inv_r
    cos_phi, sin_phi = wu * inv_r, wv * inv_r
    slider = ((0, 1), 1)
    w_dot = (p1[0] * w1 + p2[0] * w2, p1[1] * w1 + p2[1] * w2 - vd)
    j_rod = (_cross(w, p1) * inv_r2, _cross(w, p2) * inv_r2, -wu * inv_r2)  # w x (0, -1) = -wu
    omega = _cross(w, w_dot) * inv_r2
    aC = (a1[0] + a2[0], a1[1] + a2[1])
    alpha = (_cross(w, aC) - 2 * _dot(w, w_dot) * omega) * inv_r2
    out.body("rod", params("link5"), (J1, J2, None), j_rod, aC, alpha, omega, cos_phi, sin_phi,
             g)
    out.body("rod", params("link7"), (None, None, slider), j_rod, zero, alpha, omega, cos_phi,
             sin_phi, g)
    return out.finish()


def parallel_dynamics(system: ParallelSystem, q, qd, phi):
    """``(M, bias)`` of the mechanism at ``(q, qd)`` in its full parameters ``phi`` (the layout
    of :func:`cochlea.robots.parallel.model._full_parameters`: the slider's mass, four per
    planar body, then the armatures), body by body (module docstring): ``M qdd + bias`` is the
    Lagrange model's inverse dynamics without friction. ``M`` is a 5x5 SX."""
    full, blocks = _full_parameters(system)
    block_of = dict(blocks)

    def phi_of(body):
        return phi[block_of[body]]

    M = ca.SX.zeros(5, 5)
    bias = ca.SX.zeros(5)
    for side, idx in zip(system.sides, ((0, 1, 2), (3, 4, 2))):
        terms = _side_terms(system, side, [q[i] for i in idx], [qd[i] for i in idx], phi_of)
        for a in range(3):
            bias[idx[a]] = bias[idx[a]] + terms.b[a]
            for b in range(a, 3):
                i, k = sorted((idx[a], idx[b]))  # upper triangle, mirrored below
                M[i, k] = M[i, k] + terms.M[a][b]
    m_slider = phi_of("slider")[0]
    M[2, 2] = M[2, 2] + m_slider
    bias[2] = bias[2] - m_slider * float(system.gravity[1])
    for i, joint in enumerate(system.joints):
        if joint.actuator.armature is not None:
            M[i, i] = M[i, i] + phi_of(f"{joint.name}.{ARMATURE}")[0]
    for a in range(5):
        for b in range(a):
            M[a, b] = M[b, a]
    return M, bias, full


def solve_arrow(M, rhs):
    """``M^-1 rhs`` for the mechanism's mass matrix, whose sides couple only through the slider
    (``M[0:2, 3:5] = 0``): eliminate each side's 2x2 block, then the slider's Schur complement,
    then back-substitute (LDL^T in the order ``th1, th2, th1', th2', d1``, no fill-in)."""
    out = [None] * 5
    y, u = {}, {}
    for i, k in ((0, 1), (3, 4)):
        a, b, c = M[i, i], M[i, k], M[k, k]
        inv_det = _reciprocal(a * c - b * b)
        for vec, store in ((rhs, y), (M[:, 2], u)):
            store[i] = (c * vec[i] - b * vec[k]) * inv_det
            store[k] = (a * vec[k] - b * vec[i]) * inv_det
    schur = M[2, 2] - (M[0, 2] * u[0] + M[1, 2] * u[1] + M[3, 2] * u[3] + M[4, 2] * u[4])
    z = (rhs[2] - (M[0, 2] * y[0] + M[1, 2] * y[1] + M[3, 2] * y[3] + M[4, 2] * y[4])) / schur
    out[2] = z
    for i in (0, 1, 3, 4):
        out[i] = y[i] - u[i] * z
    return ca.vertcat(*out)


def forward_dynamics(model: RobotModel):
    """The closed chain's forward dynamics as a callable ``(q, qd, tau, p) -> qdd`` in the
    model's parameterisation (friction included as the model has it), for
    :func:`cochlea.robots.plant.plant_step`'s ``forward``: the same dynamics as
    ``model.forward_dynamics_p``, computed body by body and solved by blocks (module
    docstring). Refuses a model that is not a parallel mechanism's."""
    system = getattr(model.geometry, "system", None)
    if not isinstance(system, ParallelSystem):
        raise ModelError(f"model {model.name!r} is not a parallel mechanism: its forward "
                         "dynamics has no block form")
    full, _ = _full_parameters(system)
    n_full = len(full.names)
    if tuple(model.full_parameters.names[:n_full]) != tuple(full.names):
        raise ModelError(f"model {model.name!r}: its parameters are not its description's")
    to_full = ca.DM(model.parameters.to_full)[:n_full, :]

    def forward(q, qd, tau, p):
        M, bias, _ = parallel_dynamics(system, q, qd, to_full @ p)
        return solve_arrow(M, tau - model.friction_p(qd, p) - bias)

    return forward
