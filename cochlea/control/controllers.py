"""The four robust adaptive controllers of the thesis (chapter 3) as CasADi Functions.

=====  ==================  =========================================================
 id     robot / space        law (corrected variant, the default)
=====  ==================  =========================================================
 e      serial / joint       ``tau = Y_e p^ + e + G_e r``, ``p^' = Gamma Y_e' r``
 g      serial / task        ``tau = -Y_g p^ - G_a e_v - J' e_g``, ``p^' = Gamma Y_g' e_v``
 f      parallel / joint     ``tau = Y_f p^ + e + G_f r``, ``p^' = Gamma Y_f' r``
 d      parallel / task      ``tau = Y_d p^ + G_d e_d``, ``p^' = Gamma Y_d' e_d``
=====  ==================  =========================================================

Every regressor is the model's ``Y(q, qd, qd_r, qdd_r)`` (the Jacobian of
``M qdd_r + C qd_r + G + F(qd_r)`` with respect to the parameters, ``F`` the joints' friction
when the model carries it: ``actuators="all"``) at the controller's reference signals, never
typed by hand. Friction is compensated at the reference velocity (``qd_r``, ``tau_v``,
``x_Nd``): the mismatch with the plant's ``F(qd)`` is monotone in the sliding error and only
adds dissipation to each Lyapunov derivative.

* e, f: ``e = th_d - th``, ``r = e' + alpha e``; ``qd_r = th_d' + alpha e``,
  ``qdd_r = th_d'' + alpha e'``, so ``Y phi = M(th_d'' + alpha e') + C(th' + r) + G``.
  The thesis's (3.5) carries ``+ e`` inside the regressed term; it is a known signal, so here it
  is added to the torque outside the regressor (errata 6 of the model notes).
* g: ``e_g = x - x_d``, ``tau_v = J^-1 (x_d' - G_g e_g)``, ``e_v = th' - tau_v``;
  ``Y_g phi = -(M tau_v' + C tau_v + G)`` with ``tau_v'`` the exact time derivative including
  ``d/dt(J^-1)`` and ``x_d''`` (errata 1), as ``J^-1 (w' - J' tau_v)`` (``w`` the solve's
  right-hand side).
* d: ``e_p = x_pd - x_p``, ``x_Nd = A (x_pd' + K_p e_p)``, ``A = (J'J)^-1 J'``,
  ``e_d = x_Nd - th'``; ``Y_d phi = M x_Nd' + C x_Nd + G`` (errata 4 fixes the sign of K_p),
  ``x_Nd'`` with the exact derivative of ``A`` (:func:`_pseudo_inverse_derivative`).

Variants (``variant="thesis"`` reproduces the printed law where it differs):

* g: the thesis drops ``-J' e_g``; its Lyapunov derivative then keeps the cross term
  ``e_g' J e_v`` (errata 2), so only the corrected law is proven.
* e, f: the thesis's f has no ``+ e`` term and needs ``alpha, G_f > 1/2`` (errata 5), which its
  own gains violate; the corrected f adds the known ``+ e`` like e does, cancelling the cross term.
  For e the two variants agree.
* d: the thesis prints ``- G_d e_d`` (3.82) and ``- K_p e_p`` (Appendix D); the Lyapunov
  derivative with ``e_d = x_Nd - x_N`` needs ``+`` for both (errata 3, 4).

Adaptation: ``p^' = Gamma Y' s`` with a diagonal gain ``Gamma`` (ones reproduce the thesis),
projected onto the ball ``|p^| <= bound``: at the boundary the outward component is removed,
which keeps every Lyapunov argument (the true parameters lie inside the ball) and bounds the
estimates. The discrete ``step`` integrates one period with explicit Euler and clips to the ball.

Robust options (docs/controllers.md, "Robust adaptation"), trailing inputs of every Function;
their neutral values reproduce the law above bit for bit:

* ``deadzone`` (per joint, the signal's unit: rad/s or m/s; 0: none): the adaptation sees the
  continuous dead zone of its signal, ``s - clip(s, -deadzone, deadzone)`` (zero inside the
  band, continuous, no switch);
* ``p_min``, ``p_max`` (per parameter; -inf, inf: none): a box each estimate stays in, by
  parameter-wise projection of ``p^'`` (a component pushing out of its face is removed) and a
  clip after the Euler step, after the ball's;
* ``static_excess``, ``stribeck_velocity`` (per joint: ``F_s / F_c - 1``, dimensionless, 0:
  none; and rad/s or m/s): each Coulomb column of the regressor, ``tanh(v / v_s)``, becomes the
  Stribeck curve with a known static-to-Coulomb ratio, ``tanh(v / v_s) (1 + static_excess
  exp(-(v / stribeck_velocity)^2))``, still linear in the estimated Coulomb level.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..errors import ModelError
from ..robots.model import COULOMB, COULOMB_SMOOTHING, RobotModel
from .gains import CONTROLLERS, KINDS

VARIANTS = ("corrected", "thesis")
#: The robust options' inputs, after ``bound`` in ``law`` and after ``h`` in ``step``; the
#: last two (the static-friction shape) also follow ``gains`` (``p``) in ``regressor``
#: (``auxiliary``).
ROBUST_INPUTS = ("deadzone", "p_min", "p_max", "static_excess", "stribeck_velocity")


@dataclass(frozen=True)
class Controller:
    """A controller built on one model. All Functions take SI values.

    ``law(q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound, *robust) -> (tau, p_hat_dot,
    errors)``
    ``step(q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound, h, *robust) -> (tau,
    p_hat_next, errors)``
    ``regressor(q, qd, xd, xd_dot, xd_ddot, gains, *friction) -> Y`` (n x n_params)
    ``auxiliary(q, qd, xd, xd_dot, xd_ddot, gains, p, *friction) -> f``: the expression the
    regressor factors, built from ``M_p, C_p, G_p`` directly, so ``Y p == f`` can be checked.

    ``robust`` is ``(deadzone, p_min, p_max, static_excess, stribeck_velocity)`` and
    ``friction`` its last two (:data:`ROBUST_INPUTS`); :meth:`neutral` gives the values that
    leave the law as it was.

    ``xd`` is the desired joint position (joint space) or task pose (task space).
    ``gains`` stacks the diagonal gains in the order of ``gain_names``.
    """

    kind: str
    variant: str
    space: str
    nq: int
    n_task: int
    n_params: int
    gain_names: tuple[str, ...]
    gain_sizes: tuple[int, ...]
    error_names: tuple[str, ...]  # first block: tracking error; second: the sliding/aux error
    law: ca.Function
    step: ca.Function
    regressor: ca.Function
    auxiliary: ca.Function

    @property
    def n_desired(self) -> int:
        return self.nq if self.space == "joint" else self.n_task

    def neutral(self) -> tuple[np.ndarray, ...]:
        """The robust inputs (:data:`ROBUST_INPUTS`) that leave the law as without them: no
        dead zone, an unbounded box, no static friction above Coulomb (the Stribeck velocity
        is then unused; one keeps it finite)."""
        n, n_p = self.nq, self.n_params
        return (np.zeros(n), np.full(n_p, -np.inf), np.full(n_p, np.inf), np.zeros(n),
                np.ones(n))


def _wrap(angle):
    """``angle`` wrapped to (-pi, pi]: ``angle - 2 pi ceil(angle / 2 pi - 1/2)``, the angle
    itself (bit for bit) within that range and its derivative exactly 1. It was
    ``atan2(sin, cos)``, which rounds twice within the range and whose derivative CasADi forms
    as ``(cos^2 + sin^2) / (sin^2 + cos^2)``-like terms: the parallel d step had 2 atan2, 2 sin
    and 2 cos more (1983 operations, now 1955), the all-in-C parallel_task ran 5 % slower and
    serial_task 4 %; the thesis studies' logs moved by rounding only."""
    return angle - (2 * ca.pi) * ca.ceil(angle / (2 * ca.pi) - 0.5)


def _total_derivative(expr, q, qd, xd, xd_dot, xd_ddot):
    """d/dt of an expression in (q, xd, xd_dot) along q' = qd and the desired trajectory."""
    return (ca.jacobian(expr, q) @ qd + ca.jacobian(expr, xd) @ xd_dot
            + ca.jacobian(expr, xd_dot) @ xd_ddot)


def _solve_and_derivative(J, w, q, qd, xd, xd_dot, xd_ddot):
    """``(u, u')`` with ``u = J^-1 w`` for a square ``J`` and ``w`` in ``(q, xd, xd_dot)``.

    ``u' = J^-1 (w' - J' u)``: the exact derivative, from ``J u = w``. Differentiating the
    solve's own expression (the inverse by minors, or CasADi's QR beyond 3 x 3) instead gave a
    step three times the size (serial g: 1176 operations). ``u`` is the solve's, bit for bit:
    for at most 3 x 3 CasADi's solve is the inverse by minors times ``w``, formed here once for
    both products; beyond that each is a solve."""
    w_dot = _total_derivative(w, q, qd, xd, xd_dot, xd_ddot)
    J_dot = _matrix_derivative(J, q, qd, xd, xd_dot, xd_ddot)
    if J.shape[0] <= 3:
        J_inv = ca.inv(J)
        u = J_inv @ w
        return u, J_inv @ (w_dot - J_dot @ u)
    u = ca.solve(J, w)
    return u, ca.solve(J, w_dot - J_dot @ u)


def _pseudo_inverse_derivative(A, J, v, x_Nd, q, qd, xd, xd_dot, xd_ddot):
    """``d/dt (A v)`` with ``A = (J'J)^-1 J'`` (tall ``J`` of full column rank), ``v`` in
    ``(q, xd, xd_dot)`` and ``x_Nd = A v``: ``A v' + A' v`` with the exact
    ``A' = -A J' A + (J'J)^-1 J'^T (I - J A)`` and ``(J'J)^-1 = A A^T``, so that
    ``A' v = A (-J' x_Nd + A^T J'^T (v - J x_Nd))``: products of ``A`` with vectors only.
    Differentiating ``A``'s QR expression instead made the parallel d step 4271 operations,
    three quarters of them that derivative."""
    v_dot = _total_derivative(v, q, qd, xd, xd_dot, xd_ddot)
    J_dot = _matrix_derivative(J, q, qd, xd, xd_dot, xd_ddot)
    residual = v - J @ x_Nd
    return A @ (v_dot - J_dot @ x_Nd + A.T @ (J_dot.T @ residual))


def _matrix_derivative(J, q, qd, xd, xd_dot, xd_ddot):
    """d/dt of a matrix expression in (q, xd, xd_dot), as :func:`_total_derivative`."""
    rows, cols = J.shape
    return ca.reshape(_total_derivative(ca.vec(J), q, qd, xd, xd_dot, xd_ddot), rows, cols)


def build(model: RobotModel, kind: str, *, variant: str = "corrected",
          task_angles: tuple[int, ...] = (), task: tuple[ca.Function, ca.Function] | None = None
          ) -> Controller:
    """Build controller ``kind`` (``e, g, f, d``) on ``model``.

    Task-space controllers use ``task = (fk, J)`` (default: the model's ``fk_world`` and
    ``J_world``); the task coordinates listed in ``task_angles`` are angles whose error wraps
    to (-pi, pi]. ``task = (fk, J, error)``: controller g drives ``e_g = error(q, x_d)``
    instead of ``fk(q) - x_d`` (a full pose's orientation error), with ``J = de_g/dq`` and the
    feedforward ``-de_g/dx_d x_d'`` in place of ``x_d'``, so ``e_g' = J e_v - G_g e_g`` as
    before. Controller g needs a square ``J`` (as many joints as task coordinates).
    """
    if kind not in KINDS:
        raise ModelError(f"unknown controller {kind!r}; choose one of {', '.join(KINDS)}")
    if variant not in VARIANTS:
        raise ModelError(f"unknown controller variant {variant!r}; choose one of "
                         + ", ".join(VARIANTS))
    spec = CONTROLLERS[kind]
    space = spec.space
    n = model.nq
    n_p = len(model.param_names)
    fk_f, J_f, error_f = ((*task, None)[:3] if task is not None
                          else (model.fk_world, model.J_world, None))
    m = fk_f.size1_out(0) if space == "task" else n
    if kind == "g" and m != n:
        raise ModelError(f"controller g needs a square task Jacobian: {model.name} has {n} "
                         f"joints and the task {m} coordinates")
    if error_f is not None and kind != "g":
        raise ModelError(f"controller {kind} takes no task error function (only g does)")
    nd = n if space == "joint" else m

    q, qd = ca.SX.sym("q", n), ca.SX.sym("qd", n)
    xd, xd_dot, xd_ddot = ca.SX.sym("xd", nd), ca.SX.sym("xd_dot", nd), ca.SX.sym("xd_ddot", nd)
    p_hat, p = ca.SX.sym("p_hat", n_p), ca.SX.sym("p", n_p)
    Gamma, bound, h = ca.SX.sym("Gamma", n_p), ca.SX.sym("bound"), ca.SX.sym("h")
    deadzone = ca.SX.sym("deadzone", n)
    p_min, p_max = ca.SX.sym("p_min", n_p), ca.SX.sym("p_max", n_p)
    static_excess = ca.SX.sym("static_excess", n)
    stribeck_velocity = ca.SX.sym("stribeck_velocity", n)
    coulomb = _coulomb_columns(model)

    M, C, G = model.M_p(q, p), model.C_p(q, qd, p), model.G_p(q, p)
    # The joints' friction where the model estimates it (zero otherwise), at each law's
    # reference velocity as in the model's regressor, with the Stribeck excess of the static
    # friction option on each Coulomb term.
    def F(velocity):
        extra = ca.SX.zeros(n)
        for j, i, v_s in coulomb:
            extra[i] = extra[i] + p[j] * ca.tanh(velocity[i] / v_s) * (
                _stribeck(velocity[i], static_excess[i], stribeck_velocity[i]) - 1)
        return model.friction_p(velocity, p) + extra

    def shaped(Y, velocity):
        """``Y`` with each Coulomb column on the Stribeck curve (unchanged with no excess)."""
        for j, i, _ in coulomb:
            Y[:, j] = Y[:, j] * _stribeck(velocity[i], static_excess[i], stribeck_velocity[i])
        return Y

    if kind in ("e", "f"):
        gains = ca.SX.sym("gains", 3 * n)
        alpha, G_s, K_e = gains[:n], gains[n:2 * n], gains[2 * n:]
        e = xd - q
        e_dot = xd_dot - qd
        r = e_dot + alpha * e
        qd_r, qdd_r = xd_dot + alpha * e, xd_ddot + alpha * e_dot
        Y = shaped(model.Y(q, qd, qd_r, qdd_r), qd_r)
        f_aux = M @ qdd_r + C @ (qd + r) + G + F(qd_r)
        known = K_e * e if (kind == "e" or variant == "corrected") else ca.SX.zeros(n)
        tau = Y @ p_hat + known + G_s * r
        signal = r
        errors = ca.vertcat(e, r)
        error_names = ("e", "r")
    elif kind == "g":
        gains = ca.SX.sym("gains", 2 * m + n)
        G_g, G_a, K_c = gains[:m], gains[m:m + n], gains[m + n:]
        if error_f is None:
            x, J = fk_f(q), J_f(q)
            e_g = _task_error(x - xd, task_angles)
            w = xd_dot - G_g * e_g
        else:  # e_g(q, x_d): e_g' = J q' - v_d with J = de_g/dq, v_d = -de_g/dx_d x_d'
            e_g = error_f(q, xd)
            J = ca.jacobian(e_g, q)
            w = -ca.jacobian(e_g, xd) @ xd_dot - G_g * e_g
        tau_v, tau_v_dot = _solve_and_derivative(J, w, q, qd, xd, xd_dot, xd_ddot)
        e_v = qd - tau_v
        Y = shaped(-model.Y(q, qd, tau_v, tau_v_dot), tau_v)
        f_aux = -(M @ tau_v_dot + C @ tau_v + G + F(tau_v))
        tau = -Y @ p_hat - G_a * e_v
        if variant == "corrected":
            tau = tau - J.T @ (K_c * e_g)
        signal = e_v
        errors = ca.vertcat(e_g, e_v)
        error_names = ("e_g", "e_v")
    else:  # d
        gains = ca.SX.sym("gains", m + n)
        K_p, G_d = gains[:m], gains[m:]
        if "A" not in model.functions:
            raise ModelError(f"controller d needs the model's A = (J'J)^-1 J' ({model.name} "
                             "has none)")
        x = fk_f(q)
        e_p = _task_error(xd - x, task_angles)
        # The model's A comes from a QR factorisation of J: the normal equations solved
        # symbolically lose all accuracy near the pantographs' singular poses.
        A = model.A(q)
        k_sign = 1 if variant == "corrected" else -1
        v = xd_dot + k_sign * K_p * e_p
        x_Nd = A @ v
        x_Nd_dot = _pseudo_inverse_derivative(A, model.J(q), v, x_Nd, q, qd, xd, xd_dot, xd_ddot)
        e_d = x_Nd - qd
        Y = shaped(model.Y(q, qd, x_Nd, x_Nd_dot), x_Nd)
        f_aux = M @ x_Nd_dot + C @ x_Nd + G + F(x_Nd)
        g_sign = 1 if variant == "corrected" else -1
        tau = Y @ p_hat + g_sign * G_d * e_d
        signal = e_d
        errors = ca.vertcat(e_p, e_d)
        error_names = ("e_p", "e_d")

    # The continuous dead zone (exactly the signal when the width is zero).
    signal = signal - ca.fmin(ca.fmax(signal, -deadzone), deadzone)
    p_hat_dot = _projected_update(Y.T @ signal, p_hat, Gamma, bound)
    p_hat_dot = _box_update(p_hat_dot, p_hat, p_min, p_max)
    p_next = p_hat + h * p_hat_dot
    norm = ca.norm_2(p_next)
    p_next = p_next * ca.fmin(1, bound / ca.fmax(norm, 1e-300))
    p_next = ca.fmin(ca.fmax(p_next, p_min), p_max)

    prefix = f"{model.name.replace('/', '_')}_{kind}"
    ins = [q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound]
    in_names = ["q", "qd", "xd", "xd_dot", "xd_ddot", "p_hat", "gains", "Gamma", "bound"]
    friction = [static_excess, stribeck_velocity]
    robust = [deadzone, p_min, p_max] + friction
    law = ca.Function(f"{prefix}_law", ins + robust, [tau, p_hat_dot, errors],
                      in_names + list(ROBUST_INPUTS), ["tau", "p_hat_dot", "errors"])
    step = ca.Function(f"{prefix}_step", ins + [h] + robust, [tau, p_next, errors],
                       in_names + ["h"] + list(ROBUST_INPUTS), ["tau", "p_hat_next", "errors"])
    sig = [q, qd, xd, xd_dot, xd_ddot, gains]
    sig_names = ["q", "qd", "xd", "xd_dot", "xd_ddot", "gains"]
    regressor = ca.Function(f"{prefix}_Y", sig + friction, [Y], sig_names
                            + list(ROBUST_INPUTS[3:]), ["Y"])
    auxiliary = ca.Function(f"{prefix}_f", sig + [p] + friction, [f_aux],
                            sig_names + ["p"] + list(ROBUST_INPUTS[3:]), ["f"])
    gain_sizes = tuple(spec.size(name, n, m) for name in spec.names)
    return Controller(kind, variant, space, n, m, n_p, spec.names, gain_sizes, error_names,
                      law, step, regressor, auxiliary)


def _task_error(difference, angles):
    parts = [(_wrap(difference[i]) if i in angles else difference[i])
             for i in range(difference.shape[0])]
    return ca.vertcat(*parts)


def _coulomb_columns(model: RobotModel) -> list[tuple[int, int, float]]:
    """``(parameter index, joint index, v_s)`` of each estimated Coulomb level
    (``<joint>.Fc``, its column ``tanh(v / v_s)`` in the joint's row of ``Y``)."""
    joints = {j.name: (i, j.type) for i, j in enumerate(model.joints)}
    out = []
    for k, name in enumerate(model.param_names):
        owner, _, kind = name.rpartition(".")
        if kind == COULOMB and owner in joints:
            i, jtype = joints[owner]
            out.append((k, i, COULOMB_SMOOTHING[jtype]))
    return out


def _stribeck(v, excess, v_st):
    """``1 + excess exp(-(v / v_st)^2)``: the Stribeck curve over the Coulomb level (exactly 1
    with no excess; finite for a zero ``v_st``)."""
    return 1 + excess * ca.exp(-(v * v) / ca.fmax(v_st * v_st, 1e-300))


def _box_update(p_dot, p_hat, p_min, p_max):
    """``p_dot`` with each component that pushes its estimate out of ``[p_min, p_max]`` at a
    face removed: the parameter-wise projection, the Gamma-metric one for a diagonal Gamma."""
    out = []
    for i in range(p_dot.shape[0]):
        # "Free" written without a negation: CasADi turns if_else(c, 0, x) into a C `!` on a
        # real, which the embedded float build refuses (-Wfloat-conversion).
        free = ca.logic_and(ca.logic_or(p_hat[i] < p_max[i], p_dot[i] <= 0),
                            ca.logic_or(p_hat[i] > p_min[i], p_dot[i] >= 0))
        out.append(ca.if_else(free, p_dot[i], 0))
    return ca.vertcat(*out)


def _projected_update(y, p_hat, Gamma, bound):
    """``Gamma y`` with its outward part removed once ``|p_hat|`` reaches ``bound``."""
    raw = Gamma * y
    outward = ca.dot(p_hat, raw)
    metric = ca.fmax(ca.dot(p_hat, Gamma * p_hat), 1e-300)
    # The clip in ``step`` leaves |p_hat| at the bound up to rounding: count that as on it.
    active = ca.logic_and(ca.dot(p_hat, p_hat) >= (1 - 1e-9) * bound ** 2, outward > 0)
    return raw - ca.if_else(active, Gamma * p_hat * (outward / metric), ca.SX.zeros(raw.shape))
