"""The closed chain's forward dynamics in a cheaper exact form (issue 30, item 1).

The Lagrange model (:mod:`cochlea.robots.parallel.model`) differentiates the kinetic energy
twice for ``M``, once more for the Christoffel ``C`` and solves ``M qdd = tau - C qd - G`` with
CasADi's symbolic QR: 1688 operations an evaluation at the shipped plant's parameters, 1266 of
them the bias ``C qd + G``, 370 the solve. The same dynamics, computed body by body:

* every body's pose is an explicit function of q, so its origin moves at ``v = J_o qd`` and it
  turns at ``omega = j qd``; at ``qdd = 0`` its origin accelerates at ``a = J_o_dot qd`` and it
  at ``alpha = j_dot qd``, written out below from the geometry (no symbolic differentiation),
  the pantograph's terms reduced to ``cos(th1 - th2)`` and ``sin(th1 - th2)``;
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

At the shipped plant's parameters folded in, an evaluation is 369 operations instead of 1688
(docs/models.md); it agrees with the Lagrange model's forward dynamics to rounding
(tests/test_parallel_forward.py: 1e-12 relative on random states, 2e-14 measured). The rigid
plant's period (:func:`cochlea.robots.plant.plant_step`, so the simulation, the general C
kernel ``parallel_plant_step`` and the all-in-C simulation's specialised plant) integrates it:
the general step went from 9955 operations to 2389 (6-8 us to 0.6 us a call,
bench/time_kernel.c), and the ideal parallel studies' logs moved by rounding only (at most
1e-14). The geared plant (``gear_plant_step``, the realistic studies') keeps the Lagrange
model's, bit for bit what its studies ran: its backlash grows an ulp.
"""

from __future__ import annotations

import casadi as ca

from ...errors import ModelError
from ..model import ARMATURE, RobotModel
from .description import ParallelSystem, full_parameters


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


def _side_terms(system: ParallelSystem, side, q, qd, phi_of, qd_r=None):
    """M's block (upper triangle, ``M[k][l]`` for ``k <= l``) and the bias of one side's six
    bodies in its coordinates ``(th1, th2, d1)`` (``q``, ``qd``: those three), Kane's terms
    written out with the pantograph's identities. With ``qd_r`` (that side's three), the bias
    is ``C(q, qd) qd_r + G`` with the Christoffel ``C`` instead of ``C(q, qd) qd + G``: the
    velocity terms are a quadratic form ``h(qd)``, and the Christoffel ``C(q, a) b`` is the
    symmetric bilinear form with ``B(v, v) = h(v)`` (its symbols are symmetric in their last
    two indices), so each product of two terms linear in the velocity, ``x(v) y(v)``, becomes
    ``(x(a) y(b) + x(b) y(a)) / 2`` (polarisation, term by term).

    Notation: ``e_i = (cos th_i, sin th_i)``, ``e_i' = (-sin th_i, cos th_i)`` (its normal),
    ``C12 = cos(th1 - th2) = e_1 . e_2 = e_1' . e_2'``, ``S12 = sin(th1 - th2) = e_1 . e_2' =
    -e_1' . e_2``, ``a x b = a_u b_v - a_v b_u``. A body's ``R h = h_x e + h_y e'`` turned with
    it, ``E h`` that turned by 90 deg.

    * Links 1 and 4 turn about B; link 2 hangs at A1 (its origin moves at ``lp e_1' w1``,
      accelerates by ``-lp w1^2 e_1``) turned by th2, link 3 at A4 turned by th1. Together:
      ``M = [[Izz1 + Izz3 + m2 lp^2, lp ((hx2 + hx3) C12 + (hy2 - hy3) S12)], [., Izz4 + Izz2 +
      m3 lp^2]]`` and the bias ``(w2^2 P, -w1^2 P) + G`` with ``P = lp ((hx2 + hx3) S12 +
      (hy3 - hy2) C12)`` (= ``dM01/dth2``) and the gravity ``G``.
    * Links 5 (at C) and 7 (at S) turn with the rod: ``phi = atan2(w_v, w_u)``, ``w = C - S``,
      at the rate ``omega = j . qd`` with ``j = (lp w . e_1, lp w . e_2, -w_u) / |w|^2``, and
      ``alpha = (w x a_C - 2 (w . w_dot) omega) / |w|^2`` at ``qdd = 0``, where C accelerates by
      ``a_C = -lp (w1^2 e_1 + w2^2 e_2)``. Link 5's origin moves with C's columns ``lp e_1',
      lp e_2'``, link 7's with the slider.
    """
    th1, th2, d1 = q
    w1, w2, vd = qd
    r1, r2, rd = qd if qd_r is None else qd_r
    lp = system.link_length
    gu, gv = float(system.gravity[0]), float(system.gravity[1])
    c1, s1, c2, s2 = ca.cos(th1), ca.sin(th1), ca.cos(th2), ca.sin(th2)
    C12, S12 = c1 * c2 + s1 * s2, s1 * c2 - c1 * s2
    w1s, w2s = w1 * r1, w2 * r2  # w1^2, w2^2 (with qd_r: polarised)
    # Links 1 and 4 turn about a fixed point: their masses do not enter.
    _, hx1, hy1, izz1 = (phi_of(f"{side.name}.link1")[k] for k in range(4))
    _, hx4, hy4, izz4 = (phi_of(f"{side.name}.link4")[k] for k in range(4))
    m2, hx2, hy2, izz2 = (phi_of(f"{side.name}.link2")[k] for k in range(4))
    m3, hx3, hy3, izz3 = (phi_of(f"{side.name}.link3")[k] for k in range(4))
    m5, hx5, hy5, izz5 = (phi_of(f"{side.name}.link5")[k] for k in range(4))
    m7, hx7, hy7, izz7 = (phi_of(f"{side.name}.link7")[k] for k in range(4))
    lp2 = lp * lp
    # The pantograph (links 1-4). e_i' . g = e_i x g; e_i x g and e_i' x g give each link's
    # moment of gravity about its origin.
    x1g, y1g = c1 * gv - s1 * gu, -(s1 * gv + c1 * gu)  # e_1 x g, e_1' x g
    x2g, y2g = c2 * gv - s2 * gu, -(s2 * gv + c2 * gu)
    P = lp * ((hx2 + hx3) * S12 + (hy3 - hy2) * C12)
    M = [[izz1 + izz3 + m2 * lp2 + m5 * lp2, lp * ((hx2 + hx3) * C12 + (hy2 - hy3) * S12)
          + m5 * lp2 * C12, 0],
         [None, izz4 + izz2 + m3 * lp2 + m5 * lp2, 0],
         [None, None, m7]]
    b = [w2s * P - (hx1 + hx3 + lp * m2) * x1g - (hy1 + hy3) * y1g,
         -w1s * P - (hx4 + hx2 + lp * m3) * x2g - (hy4 + hy2) * y2g,
         -m7 * gv]
    # The rod (links 5 and 7).
    bu = side.sign * system.base_offset
    wu, wv = bu + lp * (c1 + c2), lp * (s1 + s2) - d1
    inv_r = _reciprocal(ca.sqrt(wu * wu + wv * wv))
    inv_r2 = inv_r * inv_r
    nu, nv = wu * inv_r, wv * inv_r  # (cos phi, sin phi)
    j = [lp * (wu * c1 + wv * s1) * inv_r2, lp * (wu * c2 + wv * s2) * inv_r2, -wu * inv_r2]
    omega = j[0] * w1 + j[1] * w2 + j[2] * vd
    wdu, wdv = -lp * (s1 * w1 + s2 * w2), lp * (c1 * w1 + c2 * w2) - vd  # w_dot
    w_x_aC = -lp * (w1s * (wu * s1 - wv * c1) + w2s * (wu * s2 - wv * c2))
    if qd_r is None:
        twice = 2 * (wu * wdu + wv * wdv) * omega  # 2 (w . w_dot) omega
        w_rod2 = omega * omega
    else:
        omega_r = j[0] * r1 + j[1] * r2 + j[2] * rd
        wdu_r, wdv_r = -lp * (s1 * r1 + s2 * r2), lp * (c1 * r1 + c2 * r2) - rd
        twice = (wu * wdu + wv * wdv) * omega_r + (wu * wdu_r + wv * wdv_r) * omega
        w_rod2 = omega * omega_r
    alpha = (w_x_aC - twice) * inv_r2
    R5 = (hx5 * nu - hy5 * nv, hx5 * nv + hy5 * nu)  # R h of link 5, link 7
    R7 = (hx7 * nu - hy7 * nv, hx7 * nv + hy7 * nu)
    # U = J^T E h: e_i' . E h = e_i . R h; the slider's column (0, 1) . E h7 = R7_u.
    U = [lp * (c1 * R5[0] + s1 * R5[1]), lp * (c2 * R5[0] + s2 * R5[1]), R7[0]]
    i_rod = izz5 + izz7
    t = [i_rod * jk for jk in j]
    for k in range(3):
        for col in range(k, 3):
            M[k][col] = M[k][col] + (t[k] * j[col] + U[k] * j[col] + U[col] * j[k])
    aC_g = (-lp * (w1s * c1 + w2s * c2) - gu, -lp * (w1s * s1 + w2s * s2) - gv)  # a_C - g
    N = (i_rod * alpha + (R5[0] * aC_g[1] - R5[1] * aC_g[0])
         - (R7[0] * gv - R7[1] * gu))
    # Link 5's force on C's columns: e_1' . a_C = lp w2^2 S12, e_2' . a_C = -lp w1^2 S12.
    b[0] = b[0] + lp * (m5 * (lp * w2s * S12 - x1g) - w_rod2 * (c1 * R5[1] - s1 * R5[0])) \
        + alpha * U[0] + j[0] * N
    b[1] = b[1] + lp * (m5 * (-lp * w1s * S12 - x2g) - w_rod2 * (c2 * R5[1] - s2 * R5[0])) \
        + alpha * U[1] + j[1] * N
    b[2] = b[2] + alpha * R7[0] - w_rod2 * R7[1] + j[2] * N
    return M, b


def parallel_dynamics(system: ParallelSystem, q, qd, phi, qd_r=None):
    """``(M, bias, full)`` of the mechanism at ``(q, qd)`` in its full parameters ``phi`` (the
    layout of :func:`~cochlea.robots.parallel.description.full_parameters`, returned as
    ``full``: the slider's mass, four per planar body, then the armatures), body by body
    (module docstring): ``M qdd + bias`` is the Lagrange model's inverse dynamics without
    friction. ``M`` is a 5x5 SX. With ``qd_r``, the bias is ``C(q, qd) qd_r + G`` with the
    Lagrange model's Christoffel ``C`` (:func:`_side_terms`)."""
    full, blocks = full_parameters(system)
    block_of = dict(blocks)

    def phi_of(body):
        return phi[block_of[body]]

    M = ca.SX.zeros(5, 5)
    bias = ca.SX.zeros(5)
    for side, idx in zip(system.sides, ((0, 1, 2), (3, 4, 2))):
        M_side, b_side = _side_terms(system, side, [q[i] for i in idx],
                                     [qd[i] for i in idx], phi_of,
                                     None if qd_r is None else [qd_r[i] for i in idx])
        for a in range(3):
            bias[idx[a]] = bias[idx[a]] + b_side[a]
            for b in range(a, 3):
                i, k = sorted((idx[a], idx[b]))  # upper triangle, mirrored below
                M[i, k] = M[i, k] + M_side[a][b]
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


def regressand(system: ParallelSystem, phi):
    """The regressor's ``M qdd_r + C(q, qd) qd_r + G`` (the Christoffel ``C``, no friction) in
    the full parameters ``phi``, body by body, as the callable ``(q, qd, qd_r, qdd_r) -> ...``
    of :func:`cochlea.robots.model.assemble_model`'s ``regressand``: the Lagrange model's
    expression to rounding, in fewer operations (docs/models.md)."""
    def f_r(q, qd, qd_r, qdd_r):
        M, bias, _ = parallel_dynamics(system, q, qd, phi, qd_r)
        return M @ qdd_r + bias
    return f_r


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
    full, _ = full_parameters(system)
    n_full = len(full.names)
    if tuple(model.full_parameters.names[:n_full]) != tuple(full.names):
        raise ModelError(f"model {model.name!r}: its parameters are not its description's")
    to_full = ca.DM(model.parameters.to_full)[:n_full, :]

    def forward(q, qd, tau, p):
        M, bias, _ = parallel_dynamics(system, q, qd, to_full @ p)
        return solve_arrow(M, tau - model.friction_p(qd, p) - bias)

    return forward
