"""Controllers: each regressor factors the expression it stands for, the variants differ where
the thesis's law differs, and the projection bounds the estimates."""

from __future__ import annotations

import numpy as np
import pytest

import cochlea
from cochlea.control import build

from .conftest import ev

SERIAL_CASES = [(k, v, par) for k in "eg" for v in ("corrected", "thesis")
                for par in ("base", "mass", "inertial")]


@pytest.fixture(scope="module")
def serial_models():
    return {par: cochlea.model("serial", parameterisation=par) for par in ("base", "mass",
                                                                           "inertial")}


def _random_inputs(rng, c):
    n, nd = c.nq, c.n_desired
    q = rng.uniform(-np.pi, np.pi, n)
    if c.space == "task":  # keep clear of the stretched-arm singularity
        q[1] = rng.choice([-1, 1]) * rng.uniform(0.4, 2.6)
    return (q, rng.uniform(-2, 2, n), rng.uniform(-0.05, 0.05, nd), rng.uniform(-0.1, 0.1, nd),
            rng.uniform(-0.5, 0.5, nd))


@pytest.mark.parametrize("kind,variant,par", SERIAL_CASES)
def test_regressor_factors_its_expression(serial_models, kind, variant, par, rng):
    """Y_x(...) p == f_x(...; p) for random states and random p, f built from M_p, C_p, G_p."""
    model = serial_models[par]
    c = build(model, kind, variant=variant, task_angles=(2,))
    for _ in range(50):
        args = _random_inputs(rng, c)
        gains = rng.uniform(0.1, 5.0, sum(c.gain_sizes))
        p = model.p_nominal * rng.uniform(0.2, 3.0, c.n_params)
        Y = ev(c.regressor, *args, gains, *c.neutral()[3:]).reshape(c.nq, c.n_params)
        f = ev(c.auxiliary, *args, gains, p, *c.neutral()[3:])
        assert np.abs(Y @ p - f).max() <= 1e-11 * max(1.0, np.abs(f).max())


def test_law_e_is_the_thesis_law(serial_models, rng):
    """tau = Y_e p^ + e + G_e r, p^' = Y_e' r (Gamma = 1), checked against M, C directly."""
    model = serial_models["mass"]
    c = build(model, "e")
    q, qd, xd, xd_dot, xd_ddot = _random_inputs(rng, c)
    alpha, G_e = np.array([5.0, 4.0, 3.0]), np.array([0.05, 0.04, 0.003])
    K_e = np.array([1.0, 0.5, 0.01])
    p_hat = model.p_nominal * 0.7
    tau, p_dot, errors = c.law(q, qd, xd, xd_dot, xd_ddot, p_hat, np.r_[alpha, G_e, K_e],
                               np.ones(3), 1e9, *c.neutral())
    e, e_dot = xd - q, xd_dot - qd
    r = e_dot + alpha * e
    M, C = ev(model.M_p, q, p_hat), ev(model.C_p, q, qd, p_hat)
    expected = M @ (xd_ddot + alpha * e_dot) + C @ (qd + r) + K_e * e + G_e * r
    assert np.allclose(np.array(tau).ravel(), expected, rtol=1e-12, atol=1e-15)
    Y = ev(c.regressor, q, qd, xd, xd_dot, xd_ddot, np.r_[alpha, G_e, K_e],
           *c.neutral()[3:]).reshape(3, 3)
    assert np.allclose(np.array(p_dot).ravel(), Y.T @ r, rtol=1e-12)
    assert np.allclose(np.array(errors).ravel(), np.r_[e, r])


def test_variant_g_differs_by_the_backstepping_cross_term(serial_models, rng):
    model = serial_models["mass"]
    corrected = build(model, "g", variant="corrected", task_angles=(2,))
    thesis = build(model, "g", variant="thesis", task_angles=(2,))
    args = _random_inputs(rng, corrected)
    K_c = np.array([1.0, 0.5, 0.01])
    gains = np.r_[2.0, 2.0, 3.0, 0.06, 0.06, 0.007, K_c]
    common = (model.p_nominal, gains, np.ones(3), 1e9)
    tau_c, _, errors = corrected.law(*args, *common, *corrected.neutral())
    tau_t, _, _ = thesis.law(*args, *common, *thesis.neutral())
    e_g = np.array(errors).ravel()[:3]
    J = ev(model.J_world, args[0])
    assert np.allclose(np.array(tau_c - tau_t).ravel(), -J.T @ (K_c * e_g), rtol=1e-10,
                       atol=1e-14)
    assert np.abs(J.T @ (K_c * e_g)).max() > 1e-3


def test_projection_keeps_estimates_in_the_ball(serial_models, rng):
    model = serial_models["mass"]
    c = build(model, "e")
    bound = 0.05
    for _ in range(50):
        args = _random_inputs(rng, c)
        direction = rng.standard_normal(3)
        p_hat = bound * direction / np.linalg.norm(direction)  # on the boundary
        gains = np.r_[5.0, 4.0, 3.0, 0.05, 0.04, 0.003, 1.0, 1.0, 1.0]
        _, p_dot, _ = c.law(*args, p_hat, gains, np.array([1.0, 2.0, 0.5]), bound,
                            *c.neutral())
        assert float(np.dot(p_hat, np.array(p_dot).ravel())) <= 1e-15
        _, p_next, _ = c.step(*args, p_hat, gains, np.ones(3), bound, 10.0, *c.neutral())
        assert np.linalg.norm(np.array(p_next).ravel()) <= bound * (1 + 1e-12)


@pytest.fixture(scope="module")
def parallel_models():
    return {par: cochlea.model("parallel", parameterisation=par) for par in ("mass", "base")}


@pytest.mark.parametrize("kind,variant,par", [(k, v, par) for k in "fd"
                                              for v in ("corrected", "thesis")
                                              for par in ("mass", "base")])
def test_parallel_regressor_factors_its_expression(parallel_models, kind, variant, par, rng):
    """Y_f, Y_d: the identity at random configurations inside the workspace."""
    model = parallel_models[par]
    c = build(model, kind, variant=variant, task_angles=(2, 5), task=(model.fk, model.J))
    for _ in range(20):
        q = model.geometry.random_configuration(rng)
        qd = rng.uniform(-1, 1, 5)
        if kind == "f":
            xd = q + rng.uniform(-0.05, 0.05, 5)
        else:
            xd = ev(model.fk, q) + rng.uniform(-0.005, 0.005, 6)
        xd_dot, xd_ddot = (rng.uniform(-0.1, 0.1, c.n_desired) for _ in range(2))
        gains = rng.uniform(0.1, 5.0, sum(c.gain_sizes))
        p = model.p_nominal * rng.uniform(0.2, 3.0, c.n_params)
        Y = ev(c.regressor, q, qd, xd, xd_dot, xd_ddot, gains,
               *c.neutral()[3:]).reshape(5, c.n_params)
        f = ev(c.auxiliary, q, qd, xd, xd_dot, xd_ddot, gains, p, *c.neutral()[3:])
        assert np.abs(Y @ p - f).max() <= 1e-10 * max(1.0, np.abs(f).max())


def _reference_and_its_derivative(reference, q, qd, xd, xd_dot, xd_ddot):
    """A reference signal's d/dt by differentiating its own expression (automatic
    differentiation through the solve or the QR): the form the laws replaced."""
    import casadi as ca
    return (ca.jacobian(reference, q) @ qd + ca.jacobian(reference, xd) @ xd_dot
            + ca.jacobian(reference, xd_dot) @ xd_ddot)


def _task_laws(serial_models, parallel_models):
    """(controller, model, reference) of the task-space laws: the reference velocity each
    regresses at (tau_v of g, x_Nd of d), built as the law's text says, in CasADi symbols."""
    import casadi as ca
    serial, parallel = serial_models["mass"], parallel_models["mass"]
    error = ca.Function("e_g", [q := ca.SX.sym("q", 3), xd := ca.SX.sym("xd", 3)],
                        [serial.fk_world(q) - xd])
    cases = []
    for task in (None, (serial.fk_world, serial.J_world, error)):
        c = build(serial, "g", task_angles=(2,) if task is None else (), task=task)

        def tau_v(q, xd, xd_dot, gains, wrap=task is None):
            e_g = serial.fk_world(q) - xd
            if wrap:
                e_g[2] = ca.atan2(ca.sin(e_g[2]), ca.cos(e_g[2]))
            return ca.solve(serial.J_world(q), xd_dot - gains[:3] * e_g)
        cases.append((c, serial, tau_v))
    c = build(parallel, "d", task_angles=(2, 5), task=(parallel.fk, parallel.J))

    def x_Nd(q, xd, xd_dot, gains):
        e_p = xd - parallel.fk(q)
        for i in (2, 5):
            e_p[i] = ca.atan2(ca.sin(e_p[i]), ca.cos(e_p[i]))
        return parallel.A(q) @ (xd_dot + gains[:6] * e_p)
    cases.append((c, parallel, x_Nd))
    return cases


def test_task_laws_regress_at_the_exact_derivative_of_their_reference(
        serial_models, parallel_models, rng):
    """g and d form the reference's derivative from J u = w (g) and the pseudo-inverse's
    derivative (d) rather than by differentiating the solve: the regressor equals the model's
    Y at the reference and its derivative by automatic differentiation of the reference."""
    import casadi as ca
    for c, model, reference in _task_laws(serial_models, parallel_models):
        n, nd = c.nq, c.n_desired
        q, qd = ca.SX.sym("q", n), ca.SX.sym("qd", n)
        xd, xd_dot, xd_ddot = (ca.SX.sym(s, nd) for s in ("xd", "xd_dot", "xd_ddot"))
        gains = ca.SX.sym("gains", sum(c.gain_sizes))
        u = reference(q, xd, xd_dot, gains)
        u_dot = _reference_and_its_derivative(u, q, qd, xd, xd_dot, xd_ddot)
        sign = -1 if c.kind == "g" else 1
        expected = ca.Function("Y", [q, qd, xd, xd_dot, xd_ddot, gains],
                               [sign * model.Y(q, qd, u, u_dot)])
        worst = 0.0
        for _ in range(40):
            if c.kind == "g":
                q0 = rng.uniform(-np.pi, np.pi, n)
                q0[1] = rng.choice([-1, 1]) * rng.uniform(0.4, 2.6)
                x0 = ev(model.fk_world, q0) + rng.uniform(-0.05, 0.05, nd)
            else:
                q0 = model.geometry.random_configuration(rng)
                x0 = ev(model.fk, q0) + rng.uniform(-0.005, 0.005, nd)
                if np.linalg.cond(ev(model.J, q0)) > 1e4:  # rounding grows as cond(J)^2
                    continue
            args = (q0, rng.uniform(-1, 1, n), x0, rng.uniform(-0.1, 0.1, nd),
                    rng.uniform(-0.5, 0.5, nd), rng.uniform(0.1, 5.0, sum(c.gain_sizes)))
            Y = ev(c.regressor, *args, *c.neutral()[3:]).reshape(n, c.n_params)
            Y_ref = ev(expected, *args).reshape(n, c.n_params)
            worst = max(worst, np.abs(Y - Y_ref).max() / max(1.0, np.abs(Y_ref).max()))
        assert worst <= 1e-11, (c.kind, worst)
