"""The parallel system: one 5-DoF mechanism of two pantographs sharing a vertical slider.

Geometry (thesis section 2.3 and Appendix A, reconstructed in model-notes section 2). Everything
lies in one vertical plane with coordinates ``(u, v)``, ``v`` up; the world frame of this robot
is that plane, origin on the slider axis at the height of the pantograph bases.

* Generalised coordinates ``q = [th1, th2, d1, th1', th2']`` (thesis 2.27): the two motor angles
  of the left pantograph, the slider height, the two motor angles of the right pantograph. All
  angles are measured from +u, counter-clockwise.
* Slider (link 6): translates on the vertical axis ``u = 0``; its pivot is ``S = (0, d1)``.
* Left pantograph (unprimed), base ``B = (+d2, 0)``: a parallelogram of four links of length
  ``l_p``. Links 1 (angle th1) and 4 (angle th2) are driven at B; link 2 hangs from link 1's tip
  with angle th2, link 3 from link 4's tip with angle th1. Its end point is
  ``C = B + l_p (cos th1 + cos th2, sin th1 + sin th2)``, where the end-effector body (link 5,
  the magnet) sits.
* Rod 7 pivots at S and slides through a sleeve on link 5, so it and link 5 both turn with
  ``phi = atan2(C_v - d1, C_u)``: the magnet always points at S.
* Right pantograph (primed): the mirror image, base ``B' = (-d2, 0)``, its own links 1'..5', 7'
  and ``phi' = atan2(C'_v - d1, C'_u)``. Only the slider couples the two sides.

Every body's pose is an explicit function of q (the closed loops are closed by construction), so
the Lagrangian needs no multipliers: ``K`` and ``U`` are sums over the bodies, ``M = hess(K, qd)``,
Christoffel ``C`` and ``G = dU/dq`` (:mod:`cochlea.lagrange`). Each planar body carries four
parameters in its body frame, ``[m, mx, my, Izz]`` (mass, first moments ``m c``, inertia about the
body-frame origin and the plane normal), on which K and U are linear; the slider only translates,
so its mass is its only parameter.

The regressor ``Y`` differentiates ``M qdd_r + C(q, qd) qd_r + G`` computed body by body instead
(:func:`cochlea.robots.parallel.forward.regressand`: the same Christoffel ``C``, to rounding, in
a quarter of the operations); ``M``, ``C``, ``G`` and the dynamics Functions keep this form.
"""


from __future__ import annotations

import re
from dataclasses import replace

import casadi as ca

from ..description import Actuator
from ..lagrange import christoffel_coriolis, gravity_vector, mass_matrix, time_derivative
from ..model import ARMATURE, RobotModel, assemble_model, check_options
from .description import SIDE_BODIES, ParallelSystem, Side, full_parameters
from .forward import regressand
from .geometry import ParallelGeometry


def rigid_system(system: ParallelSystem) -> ParallelSystem:
    """The mechanism without its drives' terms: the thesis's rigid links."""
    def rigid(joint):
        return replace(joint, actuator=Actuator())
    return replace(system, d1=rigid(system.d1),
                   left=replace(system.left, th1=rigid(system.left.th1),
                                th2=rigid(system.left.th2)),
                   right=replace(system.right, th1=rigid(system.right.th1),
                                 th2=rigid(system.right.th2)))

# --------------------------------------------------------------------------------------------
# Symbolic model
# --------------------------------------------------------------------------------------------


def _planar_energies(origin, cos, sin, omega, params, q, qd, gravity):
    """Kinetic and potential energy of a planar body, linear in ``params = [m, mx, my, Izz]``.

    The body frame sits at ``origin`` (an expression in q) turned by the angle whose cosine and
    sine are given, turning at ``omega``. A point at ``r`` in the body frame moves at
    ``o_dot + omega E r`` with ``E = R(angle + 90 deg)``, so
    ``K = m |o_dot|^2 / 2 + omega o_dot . (E h) + Izz omega^2 / 2`` and
    ``U = -g . (m o + R h)`` with ``h = (mx, my)``.
    """
    m, hx, hy, izz = params[0], params[1], params[2], params[3]
    v = ca.jacobian(origin, q) @ qd
    Eh = ca.vertcat(-sin * hx - cos * hy, cos * hx - sin * hy)
    Rh = ca.vertcat(cos * hx - sin * hy, sin * hx + cos * hy)
    K = 0.5 * m * ca.dot(v, v) + omega * ca.dot(v, Eh) + 0.5 * izz * omega**2
    U = -ca.dot(ca.DM(gravity), m * origin + Rh)
    return K, U


def _side_expressions(system: ParallelSystem, side: Side, th1, th2, d1, q, qd, phi_of):
    """Energies of one side's bodies, its end point C and rod angle phi, as expressions."""
    lp = system.link_length
    e = lambda a: ca.vertcat(ca.cos(a), ca.sin(a))  # noqa: E731
    B = ca.DM([side.sign * system.base_offset, 0.0])
    A1, A4 = B + lp * e(th1), B + lp * e(th2)
    C = A1 + lp * e(th2)
    S = ca.vertcat(0, d1)
    w = C - S
    r2 = ca.dot(w, w)
    r = ca.sqrt(r2)
    w_dot = ca.jacobian(w, q) @ qd
    phi_rate = (w[0] * w_dot[1] - w[1] * w_dot[0]) / r2  # d/dt atan2(w_v, w_u)
    th1_dot, th2_dot = ca.jacobian(th1, q) @ qd, ca.jacobian(th2, q) @ qd
    frames = {  # body: origin, cos, sin, angular rate
        "link1": (B + ca.SX.zeros(2), ca.cos(th1), ca.sin(th1), th1_dot),
        "link4": (B + ca.SX.zeros(2), ca.cos(th2), ca.sin(th2), th2_dot),
        "link2": (A1, ca.cos(th2), ca.sin(th2), th2_dot),
        "link3": (A4, ca.cos(th1), ca.sin(th1), th1_dot),
        "link5": (C, w[0] / r, w[1] / r, phi_rate),
        "link7": (S, w[0] / r, w[1] / r, phi_rate),
    }
    K, U = 0, 0
    for body in SIDE_BODIES:
        k, u = _planar_energies(*frames[body], phi_of(f"{side.name}.{body}"), q, qd,
                                system.gravity)
        K, U = K + k, U + u
    return K, U, C, ca.atan2(w[1], w[0])


def _left_pseudo_inverse(J: ca.SX) -> ca.SX:
    """``(J^T J)^-1 J^T`` of a tall J of full column rank, as ``R^-1 Q^T`` from the QR
    factorisation of J (CasADi's modified Gram-Schmidt) and back substitution.

    Solving the normal equations symbolically instead squares J's condition number and, with
    CasADi's symbolic solve, lost all accuracy near the pantographs' singular configurations
    (relative error 0.2 where ``cond(J) ~ 6e5``; QR: 2e-11).
    """
    Q, R = ca.qr(J)
    rows = [None] * R.shape[0]
    for i in reversed(range(R.shape[0])):
        acc = Q.T[i, :]
        for j in range(i + 1, R.shape[0]):
            acc = acc - R[i, j] * rows[j]
        rows[i] = acc / R[i, i]
    return ca.vertcat(*rows)


def _symbolic(system: ParallelSystem):
    """Expressions of the model in the full parameters: returns a dict of SX."""
    q = ca.SX.sym("q", 5)
    qd = ca.SX.sym("qd", 5)
    qdd = ca.SX.sym("qdd", 5)
    full, blocks = full_parameters(system)
    phi = ca.SX.sym("phi", len(full.names))
    block_of = dict(blocks)

    def phi_of(body):
        return phi[block_of[body]]

    d1 = q[2]
    K = 0.5 * phi_of("slider")[0] * qd[2] ** 2
    U = -phi_of("slider")[0] * float(system.gravity[1]) * d1  # S = (0, d1)
    task = []
    for side, (i1, i2) in zip(system.sides, ((0, 1), (3, 4))):
        k, u, C, angle = _side_expressions(system, side, q[i1], q[i2], d1, q, qd, phi_of)
        K, U = K + k, U + u
        task += [C[0], C[1], angle]
    for i, joint in enumerate(system.joints):  # the rotors, each on its own coordinate
        if joint.actuator.armature is not None:
            K = K + 0.5 * phi_of(f"{joint.name}.{ARMATURE}")[0] * qd[i] ** 2
    M = mass_matrix(K, qd)
    G = gravity_vector(U, q)
    Cor = christoffel_coriolis(M, q, qd)
    x_p = ca.vertcat(*task)
    J = ca.jacobian(x_p, q)
    A = _left_pseudo_inverse(J)
    J_dot = time_derivative(J, q, qd)
    # d/dt of (J^T J)^-1 J^T for J of full column rank, with (J^T J)^-1 = A A^T:
    A_dot = -A @ J_dot @ A + A @ A.T @ J_dot.T @ (ca.DM.eye(J.shape[0]) - J @ A)
    return dict(q=q, qd=qd, qdd=qdd, phi=phi, full=full, blocks=blocks, K=K, U=U, M=M, C=Cor,
                G=G, tau=M @ qdd + Cor @ qd + G, x_p=x_p, J=J, A=A, J_dot=J_dot, A_dot=A_dot)


def _function_prefix(name: str) -> str:
    prefix = re.sub(r"\W", "_", name)
    return prefix if prefix[:1].isalpha() else f"robot_{prefix}"


def build_model(system: ParallelSystem, parameterisation: str = "inertial",
                method: str = "lagrange", actuators: str = "none") -> RobotModel:
    """The symbolic model of a loaded parallel mechanism as a
    :class:`~cochlea.robots.model.RobotModel`.

    ``method`` is recorded but has one meaning here: the closed chain's model comes from its
    energies (Lagrange); ``"newton-euler"`` (the default of :func:`cochlea.model`, made for the
    serial chain) also yields it, and ``model.method`` says ``"lagrange"``.

    Besides the Functions every model has, this one has ``A(q)`` (5x6, ``(J^T J)^-1 J^T``),
    ``A_dot(q, qd)``, ``J_dot(q, qd)`` and ``energy(q, qd) -> [K, U]`` (J, at the nominal full
    parameters; U is zero with every mass at the world origin); ``model.geometry`` is the
    :class:`~cochlea.robots.parallel.geometry.ParallelGeometry` (closed-form IK, target
    consistency, workspace check).
    """
    check_options(parameterisation, method, actuators)
    if actuators == "none":
        system = rigid_system(system)
    x = _symbolic(system)
    q, qd = x["q"], x["qd"]
    prefix = _function_prefix(system.name)
    kinematics = {"fk": x["x_p"], "J": x["J"], "fk_world": x["x_p"], "J_world": x["J"],
                  "A": x["A"]}
    joints = tuple(j.info() for j in system.joints)
    model = assemble_model(system.name, prefix, joints=joints, q=q, qd=qd, qdd=x["qdd"],
                           phi=x["phi"], M=x["M"], C=x["C"], G=x["G"], tau=x["tau"],
                           kinematics=kinematics, full=x["full"], bodies=x["blocks"],
                           parameterisation=parameterisation, method="lagrange",
                           source=system.path,
                           friction=([(j.actuator.viscous, j.actuator.coulomb)
                                      for j in system.joints] if actuators == "all" else None),
                           actuators=actuators, regressand=regressand(system, x["phi"]))
    nominal = ca.DM(x["full"].nominal)
    energy = ca.substitute(ca.vertcat(x["K"], x["U"]), x["phi"], nominal)
    F = ca.Function
    model.functions.update({
        "A_dot": F(f"{prefix}_A_dot", [q, qd], [x["A_dot"]], ["q", "qd"], ["A_dot"]),
        "J_dot": F(f"{prefix}_J_dot", [q, qd], [x["J_dot"]], ["q", "qd"], ["J_dot"]),
        "energy": F(f"{prefix}_energy", [q, qd], [energy], ["q", "qd"], ["energy"]),
    })
    return replace(model, geometry=ParallelGeometry(system))

