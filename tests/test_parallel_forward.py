"""The closed chain's forward dynamics and the regressor's ``M qdd_r + C qd_r + G`` in their
block form (cochlea/robots/parallel/forward.py) against the Lagrange model's: the same dynamics
to rounding, in a fraction of the operations."""

from __future__ import annotations

import dataclasses

import casadi as ca
import numpy as np
import pytest

import cochlea
from cochlea.errors import ModelError
from cochlea.robots.lagrange import time_derivative
from cochlea.robots.parallel import build_model, load_parallel
from cochlea.robots.parallel.forward import (
    forward_dynamics,
    parallel_dynamics,
    regressand,
    solve_arrow,
)
from cochlea.robots.plant import plant_step

RELATIVE = 1e-12  # of the largest entry of the Lagrange model's result


@pytest.fixture(scope="module")
def rigid():
    return cochlea.model("parallel")


@pytest.fixture(scope="module")
def armature():
    return cochlea.model("parallel", actuators="armature")


@pytest.fixture(scope="module")
def actuated():
    """The realistic studies' controller model: armatures and friction, one mass each."""
    return cochlea.model("parallel", parameterisation="mass", actuators="all")


@pytest.fixture(scope="module")
def tilted():
    """The mechanism with gravity off the plane's vertical (a u component), which the shipped
    description does not have, so that every gravity term is exercised."""
    system = dataclasses.replace(load_parallel(), gravity=np.array([2.5, -9.81]))
    return build_model(system)


def _parameters(model, rng, scale: float) -> np.ndarray:
    """Nominal parameters moved by up to ``scale`` relative, and every body's ``my`` made
    nonzero (the shipped rods have ``my = 0``, which would hide its terms)."""
    p = model.p_nominal * (1 + rng.uniform(-scale, scale, model.p_nominal.size))
    for i, name in enumerate(model.param_names):
        if name.endswith(".my"):
            p[i] = rng.uniform(-0.01, 0.01)
    return p


def _states(model, rng, count: int):
    for _ in range(count):
        q = model.geometry.random_configuration(rng)
        qd = rng.normal(0.0, 2.0, 5)
        qd[2] *= 0.1  # m/s at the slider
        yield q, qd, rng.normal(0.0, 3.0, 5)


@pytest.mark.parametrize("which", ["rigid", "armature", "tilted"])
def test_forward_dynamics_is_the_lagrange_models(which, request):
    """On random workspace states and efforts, at the nominal and at perturbed parameters:
    ``qdd`` equals ``forward_dynamics_p`` to 1e-12 relative, and ``M``, the bias equal
    ``M_p`` and the inverse dynamics at ``qdd = 0`` to 1e-13."""
    model = request.getfixturevalue(which)
    rng = np.random.default_rng(30)
    q, qd, tau = (ca.SX.sym(n, 5) for n in ("q", "qd", "tau"))
    p = ca.SX.sym("p", len(model.param_names))
    fast = ca.Function("fast", [q, qd, tau, p], [forward_dynamics(model)(q, qd, tau, p)])
    M, bias, _ = parallel_dynamics(model.geometry.system, q, qd,
                                   ca.DM(model.parameters.to_full) @ p)
    parts = ca.Function("parts", [q, qd, p], [M, bias])
    worst = {"qdd": 0.0, "M": 0.0, "bias": 0.0}
    for k, (qv, qdv, tauv) in enumerate(_states(model, rng, 40)):
        pv = model.p_nominal if k % 2 == 0 else _parameters(model, rng, 0.3)
        ref = np.asarray(model.forward_dynamics_p(qv, qdv, tauv, pv)).ravel()
        got = np.asarray(fast(qv, qdv, tauv, pv)).ravel()
        worst["qdd"] = max(worst["qdd"], np.max(np.abs(got - ref)) / np.max(np.abs(ref)))
        M_ref = np.asarray(model.M_p(qv, pv))
        b_ref = np.asarray(model.inverse_dynamics_p(qv, qdv, np.zeros(5), pv)).ravel()
        M_got, b_got = (np.asarray(v) for v in parts(qv, qdv, pv))
        worst["M"] = max(worst["M"], np.max(np.abs(M_got - M_ref)) / np.max(np.abs(M_ref)))
        worst["bias"] = max(worst["bias"],
                            np.max(np.abs(b_got.ravel() - b_ref)) / np.max(np.abs(b_ref)))
    assert worst["qdd"] <= RELATIVE and worst["M"] <= 1e-13 and worst["bias"] <= 1e-13, worst


def test_the_arrow_solve_is_a_solve():
    """``solve_arrow`` on a random symmetric positive definite matrix of the mechanism's
    pattern (the sides coupled only through the slider) is ``numpy.linalg.solve``."""
    rng = np.random.default_rng(1)
    Ms, r = ca.SX.sym("M", 5, 5), ca.SX.sym("r", 5)
    solve = ca.Function("solve", [Ms, r], [solve_arrow(Ms, r)])
    for _ in range(50):
        A = rng.normal(size=(5, 5))
        M = A @ A.T + 0.1 * np.eye(5)
        M[np.ix_([0, 1], [3, 4])] = 0.0
        M[np.ix_([3, 4], [0, 1])] = 0.0
        M += 5 * np.eye(5)  # still positive definite after the cut
        b = rng.normal(size=5)
        np.testing.assert_allclose(np.asarray(solve(M, b)).ravel(), np.linalg.solve(M, b),
                                   rtol=1e-12, atol=1e-14)


def test_fewer_operations(rigid):
    """At the nominal parameters folded in, the block form costs under a third of the Lagrange
    model's operations (369 against 1688 when written)."""
    q, qd, tau = (ca.SX.sym(n, 5) for n in ("q", "qd", "tau"))
    p = ca.DM(rigid.p_nominal)
    fast = ca.Function("fast", [q, qd, tau], [forward_dynamics(rigid)(q, qd, tau, p)])
    slow = ca.Function("slow", [q, qd, tau], [rigid.forward_dynamics_p(q, qd, tau, p)])
    assert fast.n_instructions() * 3 < slow.n_instructions()


def test_plant_step_with_the_block_form(rigid):
    """The plant period (RK4) with ``forward`` given is the general one to rounding, with and
    without dry friction."""
    rng = np.random.default_rng(7)
    for coulomb in (False, True):
        general = plant_step(rigid, 1, coulomb=coulomb)
        fast = plant_step(rigid, 1, coulomb=coulomb, forward=forward_dynamics(rigid))
        assert fast.name() == general.name() and fast.n_in() == general.n_in()
        for q, qd, tau in _states(rigid, rng, 10):
            args = [np.concatenate([q, qd]), tau, rigid.p_nominal, np.full(5, 0.01), 1e-3]
            if coulomb:
                args.append(np.concatenate([np.full(5, 0.02), np.full(5, 0.03),
                                            np.full(5, 0.01)]))
            a = np.asarray(general(*args)).ravel()
            b = np.asarray(fast(*args)).ravel()
            assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(a))


def _lagrange_regressor(model):
    """The Lagrange model's ``Y``: the Jacobian in ``p`` of ``M_p qdd_r + C_p qd_r + G_p +
    F(qd_r)`` (its Christoffel ``C``), what the model's ``Y`` was before the block form."""
    q, qd, qd_r, qdd_r = (ca.SX.sym(n, 5) for n in ("q", "qd", "qd_r", "qdd_r"))
    p = ca.SX.sym("p", len(model.param_names))
    f_r = (model.M_p(q, p) @ qdd_r + model.C_p(q, qd, p) @ qd_r + model.G_p(q, p)
           + model.friction_p(qd_r, p))
    return ca.Function("Y_lagrange", [q, qd, qd_r, qdd_r], [ca.jacobian(f_r, p)])


@pytest.mark.parametrize("which", ["rigid", "actuated", "tilted"])
def test_the_regressor_is_the_lagrange_models(which, request):
    """The model's ``Y`` (the block form's ``M qdd_r + C(q, qd) qd_r + G``) equals the Lagrange
    form's entry by entry to 1e-12 of its largest, with ``qd_r`` unlike ``qd``: a ``C`` other
    than the Christoffel one (``C(q, qd_r) qd``, or the bias at ``qd_r``) fails."""
    model = request.getfixturevalue(which)
    reference = _lagrange_regressor(model)
    rng = np.random.default_rng(31)
    worst = 0.0
    for q, qd, qdd_r in _states(model, rng, 30):
        qd_r = rng.normal(0.0, 2.0, 5)
        qd_r[2] *= 0.1
        ref = np.asarray(reference(q, qd, qd_r, qdd_r))
        got = np.asarray(model.Y(q, qd, qd_r, qdd_r))
        worst = max(worst, np.max(np.abs(got - ref)) / np.max(np.abs(ref)))
    assert worst <= RELATIVE, worst


def test_the_block_forms_coriolis_matrix_is_christoffels(tilted):
    """``C(q, qd)``, read off the block form's regressand as its Jacobian in ``qd_r``, is the
    Lagrange model's ``C_p`` and keeps ``M_dot - 2 C`` skew-symmetric (the controllers'
    Lyapunov property), at perturbed parameters."""
    system = tilted.geometry.system
    q, qd, qd_r, qdd_r = (ca.SX.sym(n, 5) for n in ("q", "qd", "qd_r", "qdd_r"))
    rng = np.random.default_rng(32)
    p = _parameters(tilted, rng, 0.3)
    phi = ca.DM(tilted.parameters.to_full) @ p
    f_r = regressand(system, phi)(q, qd, qd_r, qdd_r)
    C = ca.Function("C", [q, qd], [ca.jacobian(f_r, qd_r)])
    M, _, _ = parallel_dynamics(system, q, qd, phi)
    M_dot = ca.Function("M_dot", [q, qd], [time_derivative(M, q, qd)])
    for q_v, qd_v, _ in _states(tilted, rng, 30):
        C_ref = np.asarray(tilted.C_p(q_v, qd_v, p))
        C_got = np.asarray(C(q_v, qd_v))
        assert np.max(np.abs(C_got - C_ref)) <= RELATIVE * np.max(np.abs(C_ref))
        S = np.asarray(M_dot(q_v, qd_v)) - 2 * C_got
        assert np.max(np.abs(S + S.T)) <= RELATIVE * np.max(np.abs(S))
        assert np.max(np.abs(S)) > 1e-3


def test_the_regressor_costs_fewer_operations(rigid):
    """The block form's ``Y`` costs under a third of the Lagrange form's operations (477
    against 2150 in the mass parameterisation when written)."""
    mass = cochlea.model("parallel", parameterisation="mass")
    assert mass.Y.n_instructions() * 3 < _lagrange_regressor(mass).n_instructions()


def test_refuses_a_serial_model():
    with pytest.raises(ModelError, match="not a parallel mechanism"):
        forward_dynamics(cochlea.model("serial"))
