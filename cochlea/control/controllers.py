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
  ``d/dt(J^-1)`` and ``x_d''`` (errata 1).
* d: ``e_p = x_pd - x_p``, ``x_Nd = A (x_pd' + K_p e_p)``, ``A = (J'J)^-1 J'``,
  ``e_d = x_Nd - th'``; ``Y_d phi = M x_Nd' + C x_Nd + G`` (errata 4 fixes the sign of K_p).

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
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as ca

from ..errors import ModelError
from ..robots.model import RobotModel
from .gains import CONTROLLERS, KINDS

VARIANTS = ("corrected", "thesis")


@dataclass(frozen=True)
class Controller:
    """A controller built on one model. All Functions take SI values.

    ``law(q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound) -> (tau, p_hat_dot, errors)``
    ``step(q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound, h) -> (tau, p_hat_next,
    errors)``
    ``regressor(q, qd, xd, xd_dot, xd_ddot, gains) -> Y`` (n x n_params)
    ``auxiliary(q, qd, xd, xd_dot, xd_ddot, gains, p) -> f``: the expression the regressor
    factors, built from ``M_p, C_p, G_p`` directly, so ``Y p == f`` can be checked.

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


def _wrap(angle):
    return ca.atan2(ca.sin(angle), ca.cos(angle))


def _total_derivative(expr, q, qd, xd, xd_dot, xd_ddot):
    """d/dt of an expression in (q, xd, xd_dot) along q' = qd and the desired trajectory."""
    return (ca.jacobian(expr, q) @ qd + ca.jacobian(expr, xd) @ xd_dot
            + ca.jacobian(expr, xd_dot) @ xd_ddot)


def build(model: RobotModel, kind: str, *, variant: str = "corrected",
          task_angles: tuple[int, ...] = (), task: tuple[ca.Function, ca.Function] | None = None
          ) -> Controller:
    """Build controller ``kind`` (``e, g, f, d``) on ``model``.

    Task-space controllers use ``task = (fk, J)`` (default: the model's ``fk_world`` and
    ``J_world``); the task coordinates listed in ``task_angles`` are angles whose error wraps
    to (-pi, pi].
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
    fk_f, J_f = task if task is not None else (model.fk_world, model.J_world)
    m = fk_f.size1_out(0) if space == "task" else n
    nd = n if space == "joint" else m

    q, qd = ca.SX.sym("q", n), ca.SX.sym("qd", n)
    xd, xd_dot, xd_ddot = ca.SX.sym("xd", nd), ca.SX.sym("xd_dot", nd), ca.SX.sym("xd_ddot", nd)
    p_hat, p = ca.SX.sym("p_hat", n_p), ca.SX.sym("p", n_p)
    Gamma, bound, h = ca.SX.sym("Gamma", n_p), ca.SX.sym("bound"), ca.SX.sym("h")

    M, C, G = model.M_p(q, p), model.C_p(q, qd, p), model.G_p(q, p)
    # The joints' friction where the model estimates it (zero otherwise), at each law's
    # reference velocity as in the model's regressor.
    def F(velocity):
        return model.friction_p(velocity, p)

    if kind in ("e", "f"):
        gains = ca.SX.sym("gains", 3 * n)
        alpha, G_s, K_e = gains[:n], gains[n:2 * n], gains[2 * n:]
        e = xd - q
        e_dot = xd_dot - qd
        r = e_dot + alpha * e
        qd_r, qdd_r = xd_dot + alpha * e, xd_ddot + alpha * e_dot
        Y = model.Y(q, qd, qd_r, qdd_r)
        f_aux = M @ qdd_r + C @ (qd + r) + G + F(qd_r)
        known = K_e * e if (kind == "e" or variant == "corrected") else ca.SX.zeros(n)
        tau = Y @ p_hat + known + G_s * r
        signal = r
        errors = ca.vertcat(e, r)
        error_names = ("e", "r")
    elif kind == "g":
        gains = ca.SX.sym("gains", 2 * m + n)
        G_g, G_a, K_c = gains[:m], gains[m:m + n], gains[m + n:]
        x, J = fk_f(q), J_f(q)
        e_g = _task_error(x - xd, task_angles)
        tau_v = ca.solve(J, xd_dot - G_g * e_g)
        tau_v_dot = _total_derivative(tau_v, q, qd, xd, xd_dot, xd_ddot)
        e_v = qd - tau_v
        Y = -model.Y(q, qd, tau_v, tau_v_dot)
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
        x_Nd = A @ (xd_dot + k_sign * K_p * e_p)
        x_Nd_dot = _total_derivative(x_Nd, q, qd, xd, xd_dot, xd_ddot)
        e_d = x_Nd - qd
        Y = model.Y(q, qd, x_Nd, x_Nd_dot)
        f_aux = M @ x_Nd_dot + C @ x_Nd + G + F(x_Nd)
        g_sign = 1 if variant == "corrected" else -1
        tau = Y @ p_hat + g_sign * G_d * e_d
        signal = e_d
        errors = ca.vertcat(e_p, e_d)
        error_names = ("e_p", "e_d")

    p_hat_dot = _projected_update(Y.T @ signal, p_hat, Gamma, bound)
    p_next = p_hat + h * p_hat_dot
    norm = ca.norm_2(p_next)
    p_next = p_next * ca.fmin(1, bound / ca.fmax(norm, 1e-300))

    prefix = f"{model.name.replace('/', '_')}_{kind}"
    ins = [q, qd, xd, xd_dot, xd_ddot, p_hat, gains, Gamma, bound]
    in_names = ["q", "qd", "xd", "xd_dot", "xd_ddot", "p_hat", "gains", "Gamma", "bound"]
    law = ca.Function(f"{prefix}_law", ins, [tau, p_hat_dot, errors], in_names,
                      ["tau", "p_hat_dot", "errors"])
    step = ca.Function(f"{prefix}_step", ins + [h], [tau, p_next, errors], in_names + ["h"],
                       ["tau", "p_hat_next", "errors"])
    sig = [q, qd, xd, xd_dot, xd_ddot, gains]
    sig_names = ["q", "qd", "xd", "xd_dot", "xd_ddot", "gains"]
    regressor = ca.Function(f"{prefix}_Y", sig, [Y], sig_names, ["Y"])
    auxiliary = ca.Function(f"{prefix}_f", sig + [p], [f_aux], sig_names + ["p"], ["f"])
    gain_sizes = tuple(spec.size(name, n, m) for name in spec.names)
    return Controller(kind, variant, space, n, m, n_p, spec.names, gain_sizes, error_names,
                      law, step, regressor, auxiliary)


def _task_error(difference, angles):
    parts = [(_wrap(difference[i]) if i in angles else difference[i])
             for i in range(difference.shape[0])]
    return ca.vertcat(*parts)


def _projected_update(y, p_hat, Gamma, bound):
    """``Gamma y`` with its outward part removed once ``|p_hat|`` reaches ``bound``."""
    raw = Gamma * y
    outward = ca.dot(p_hat, raw)
    metric = ca.fmax(ca.dot(p_hat, Gamma * p_hat), 1e-300)
    # The clip in ``step`` leaves |p_hat| at the bound up to rounding: count that as on it.
    active = ca.logic_and(ca.dot(p_hat, p_hat) >= (1 - 1e-9) * bound ** 2, outward > 0)
    return raw - ca.if_else(active, Gamma * p_hat * (outward / metric), ca.SX.zeros(raw.shape))
