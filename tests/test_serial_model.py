"""The serial arm's symbolic model: structural properties, Newton-Euler against Lagrange, the
thesis's closed forms, kinematics, and the regressor identities."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

import cochlea
from cochlea.robots.lagrange import time_derivative

from .conftest import DATA, ev, random_state

N_STATES = 100
DESCRIPTIONS = [None, DATA / "general_chain.toml"]


def _model(description, **kw):
    return cochlea.model("serial", description=description, **kw)


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_mass_matrix_symmetric_positive_definite(description, rng):
    model = _model(description)
    for _ in range(N_STATES):
        q, _, _ = random_state(rng, model.nq)
        M = ev(model.M, q)
        assert np.allclose(M, M.T, rtol=0, atol=1e-15)
        assert np.linalg.eigvalsh(M).min() > 0


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_mdot_minus_2c_is_skew_symmetric(description, rng):
    model = _model(description)
    q = ca.SX.sym("q", model.nq)
    qd = ca.SX.sym("qd", model.nq)
    Mdot = ca.Function("Mdot", [q, qd], [time_derivative(model.M(q), q, qd)])
    for _ in range(N_STATES):
        qv, qdv, _ = random_state(rng, model.nq)
        S = ev(Mdot, qv, qdv) - 2 * ev(model.C, qv, qdv)
        assert np.abs(S + S.T).max() < 1e-12
        # ... and is not trivially zero: the check has something to check.
        assert np.abs(S).max() > 1e-6


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_coriolis_matrix_reproduces_the_recursion(description, rng):
    """C(q, qd) qd + G(q) from Christoffel symbols equals RNEA(q, qd, 0)."""
    model = _model(description)
    for _ in range(N_STATES):
        q, qd, _ = random_state(rng, model.nq)
        lhs = ev(model.C, q, qd) @ qd + ev(model.G, q)
        rhs = ev(model.inverse_dynamics, q, qd, np.zeros(model.nq))
        assert np.allclose(lhs, rhs, rtol=0, atol=1e-12 * max(1.0, np.abs(rhs).max()))


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_newton_euler_equals_lagrange(description, rng):
    ne = _model(description, method="newton-euler")
    lg = _model(description, method="lagrange")
    for _ in range(N_STATES):
        q, qd, qdd = random_state(rng, ne.nq)
        for name, args in [("inverse_dynamics", (q, qd, qdd)), ("M", (q,)), ("C", (q, qd)),
                           ("G", (q,))]:
            a, b = ev(getattr(ne, name), *args), ev(getattr(lg, name), *args)
            assert np.abs(a - b).max() < 1e-12, name


def test_gravity_is_zero_for_the_horizontal_arms(rng):
    """The arms move in the horizontal plane with gravity along the joint axes (thesis 2.8)."""
    for arm in ("arm1", "arm2"):
        model = cochlea.model("serial", arm=arm)
        for _ in range(20):
            q, _, _ = random_state(rng, 3)
            assert np.abs(ev(model.G, q)).max() < 1e-15


def thesis_mass_matrix(th, l, m):
    """The closed-form entries of the thesis's M_s, equation (2.20), as printed."""
    l1, l2, l3 = l
    m1, m2, m3 = m
    _, t2, t3 = th
    c2, c3, c23 = np.cos(t2), np.cos(t3), np.cos(t2 + t3)
    M11 = (l1**2 * m1 / 3 + l1**2 * (m2 + m3) + m3 * l3**2 / 3 + l2**2 * m2 / 3 + l2**2 * m3
           + l1 * l3 * m3 * c23 + 2 * l1 * l2 * m3 * c2 + l1 * l2 * m2 * c2 + l2 * l3 * m3 * c3)
    M12 = (m3 * l3**2 / 3 + l2**2 * m2 / 3 + l2**2 * m3 + l1 * l3 * m3 * c23 / 2
           + l1 * l2 * m3 * c2 + l1 * l2 * m2 * c2 / 2 + l2 * l3 * m3 * c3)
    M13 = m3 * l3**2 / 3 + l2 * l3 * m3 * c3 / 2 + l1 * l3 * m3 * c23 / 2
    M22 = m3 * l3**2 / 3 + l2**2 * m2 / 3 + l2**2 * m3 + l2 * l3 * m3 * c3
    M23 = l2 * l3 * m3 * c3 / 2 + m3 * l3**2 / 3
    M33 = m3 * l3**2 / 3
    return np.array([[M11, M12, M13], [M12, M22, M23], [M13, M23, M33]])


def test_mass_matrix_matches_thesis_closed_form(serial_arm1, rng):
    """Thesis (3.18) parameters in (2.20); the description holds the same rods."""
    l, m = (0.105, 0.105, 0.04), (0.09518, 0.07878, 0.01119)
    for _ in range(N_STATES):
        q, _, _ = random_state(rng, 3)
        expected = thesis_mass_matrix(q, l, m)
        assert np.allclose(ev(serial_arm1.M, q), expected, rtol=1e-12, atol=0)


def test_forward_kinematics_matches_thesis(serial_arm1, rng):
    """x_s = [l1 c1 + l2 c12 + l3 c123, l1 s1 + l2 s12 + l3 s123, th1 + th2 + th3] (3.21)."""
    l1, l2, l3 = 0.105, 0.105, 0.04
    for _ in range(N_STATES):
        t, _, _ = random_state(rng, 3)
        a1, a12, a123 = t[0], t[0] + t[1], t.sum()
        expected = [l1 * np.cos(a1) + l2 * np.cos(a12) + l3 * np.cos(a123),
                    l1 * np.sin(a1) + l2 * np.sin(a12) + l3 * np.sin(a123), a123]
        assert np.allclose(ev(serial_arm1.fk, t), expected, rtol=0, atol=1e-15)
        # Jacobian: closed form with the index typos of (3.23) corrected.
        s1, s12, s123 = np.sin(a1), np.sin(a12), np.sin(a123)
        c1, c12, c123 = np.cos(a1), np.cos(a12), np.cos(a123)
        J = np.array([
            [-l1 * s1 - l2 * s12 - l3 * s123, -l2 * s12 - l3 * s123, -l3 * s123],
            [l1 * c1 + l2 * c12 + l3 * c123, l2 * c12 + l3 * c123, l3 * c123],
            [1.0, 1.0, 1.0]])
        assert np.allclose(ev(serial_arm1.J, t), J, rtol=0, atol=1e-15)


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_jacobian_matches_finite_differences(description, rng):
    model = _model(description)
    h = 1e-6
    for _ in range(20):
        q, _, _ = random_state(rng, model.nq)
        J = ev(model.J_world, q)
        for k in range(model.nq):
            dq = np.zeros(model.nq)
            dq[k] = h
            fd = (ev(model.fk_world, q + dq) - ev(model.fk_world, q - dq)) / (2 * h)
            assert np.allclose(J[:, k], fd, rtol=0, atol=1e-8)


def test_cochlea_frame_poses_from_the_notes():
    """Model notes section 1: the base poses put the thesis's initial poses where stated."""
    arm1 = cochlea.model("serial", arm="arm1")
    arm2 = cochlea.model("serial", arm="arm2")
    th_d0 = np.radians([81.14 - 3.007, 71.02 - 7.082, 117.8 - 4.074])  # (3.19) at t = 0
    x, y, _ = ev(arm1.fk_world, th_d0)
    assert abs(x - 0.030) < 5e-4 and abs(y - 0.0005) < 5e-4
    x, y, phi = ev(arm2.fk_world, np.radians([110.0, -128.0, 100.0]))
    assert abs(x - -0.0356) < 5e-4 and abs(y - 0.0008) < 5e-4
    assert abs(np.degrees(phi) - 82.0) < 1e-9


def test_forward_dynamics_inverts_inverse_dynamics(rng):
    model = _model(DATA / "general_chain.toml")
    for _ in range(N_STATES):
        q, qd, qdd = random_state(rng, model.nq)
        tau = ev(model.inverse_dynamics, q, qd, qdd)
        assert np.allclose(ev(model.forward_dynamics, q, qd, tau), qdd, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------
# Regressor
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("parameterisation", ["inertial", "base", "mass"])
@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_regressor_identity(description, parameterisation, rng):
    """Y(q, qd, qd_r, qdd_r) p == M(q) qdd_r + C(q, qd) qd_r + G(q), for any p, not only nominal."""
    model = _model(description, parameterisation=parameterisation)
    n, n_p = model.nq, len(model.param_names)
    for k in range(N_STATES):
        q, qd, qdd_r = random_state(rng, n)
        qd_r = rng.uniform(-2, 2, n)
        p = model.p_nominal if k == 0 else model.p_nominal * rng.uniform(0.2, 3.0, n_p)
        Y = ev(model.Y, q, qd, qd_r, qdd_r).reshape(n, n_p)
        f = (ev(model.M_p, q, p) @ qdd_r + ev(model.C_p, q, qd, p) @ qd_r + ev(model.G_p, q, p))
        assert np.abs(Y @ p - f).max() < 1e-12 * max(1.0, np.abs(f).max())


def test_base_parameters_of_the_planar_arm():
    """A horizontal planar 3R arm has 7 base parameters (3n - 2), with the classic grouping."""
    model = cochlea.model("serial", parameterisation="base")
    meanings = model.parameters.meanings
    assert len(meanings) == 7
    assert meanings[0] == "link1.Izz + 0.011025*link2.m + 0.011025*link3.m"  # l1^2 = 0.011025
    assert meanings[1] == "link2.mx + 0.105*link3.m"
    l1, m2, m3 = 0.105, 0.07878, 0.01119
    izz1_origin = 0.09518 * l1**2 / 3  # rod about its joint
    assert model.p_nominal[0] == pytest.approx(izz1_origin + l1**2 * (m2 + m3), rel=1e-12)


@pytest.mark.parametrize("description", DESCRIPTIONS, ids=["serial", "general"])
def test_base_regressor_has_full_column_rank_and_same_span(description, rng):
    full = _model(description, parameterisation="inertial")
    base = _model(description, parameterisation="base")
    rows_full, rows_base = [], []
    for _ in range(30):
        args = [rng.uniform(-np.pi, np.pi, full.nq) for _ in range(4)]
        rows_full.append(ev(full.Y, *args).reshape(full.nq, -1))
        rows_base.append(ev(base.Y, *args).reshape(base.nq, -1))
    W, Wb = np.vstack(rows_full), np.vstack(rows_base)
    rank = np.linalg.matrix_rank(W, tol=1e-9 * np.abs(W).max())
    assert Wb.shape[1] == rank
    assert np.linalg.matrix_rank(Wb, tol=1e-9 * np.abs(Wb).max()) == rank
    # Same dynamics: W phi_nominal == Wb beta_nominal.
    assert np.allclose(W @ full.p_nominal, Wb @ base.p_nominal, rtol=0, atol=1e-12)
    # Any full parameters (a perturbed plant's, an identified one) map onto the base set
    # through from_full with the same dynamics: what identification compares against.
    phi = full.p_nominal * rng.uniform(0.2, 3.0, full.p_nominal.size)
    beta = base.parameters.from_full @ phi
    assert np.allclose(W @ phi, Wb @ beta, rtol=0, atol=1e-12 * max(1.0, np.abs(W @ phi).max()))


def test_mass_parameterisation_scales_the_rods(tmp_path, rng):
    """M_p with every mass doubled equals the model of a description with doubled masses."""
    text = (cochlea.resources.ROBOTS_DIR / "serial.toml").read_text()
    doubled = text
    for m in ("0.09518", "0.07878", "0.01119"):
        doubled = doubled.replace(f"mass_kg = {m}", f"mass_kg = {2 * float(m)!r}")
    # Inertias scale with mass too (same rods, denser material).
    for i in ("1.18975e-06", "8.7446625e-05", "9.8475e-07", "7.2379125e-05", "1.39875e-07",
              "1.492e-06"):
        doubled = doubled.replace(i, repr(2 * float(i)))
    path = tmp_path / "heavy.toml"
    path.write_text(doubled)
    nominal = cochlea.model("serial", parameterisation="mass")
    heavy = cochlea.model("serial", description=path)
    assert nominal.param_names == ("link1.m", "link2.m", "link3.m")
    for _ in range(20):
        q, _, _ = random_state(rng, 3)
        assert np.allclose(ev(nominal.M_p, q, 2 * nominal.p_nominal), ev(heavy.M, q), rtol=1e-12)


def test_unknown_options_fail_clearly():
    with pytest.raises(cochlea.ModelError, match="unknown robot"):
        cochlea.model("delta")
    with pytest.raises(cochlea.ModelError, match="parameterisation"):
        cochlea.model("serial", parameterisation="full")
    with pytest.raises(cochlea.ModelError, match="no arm named 'arm3'"):
        cochlea.model("serial", arm="arm3")
