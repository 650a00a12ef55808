"""The parallel mechanism's symbolic model: energy, structure, the thesis's legible closed forms,
an independent numerical oracle, and the regressor identities."""

from __future__ import annotations

import time

import casadi as ca
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import cochlea
from cochlea.robots.lagrange import time_derivative
from cochlea.robots.parallel import SCENARIO_START, load_parallel

from .conftest import ev

N_STATES = 100


@pytest.fixture(scope="module")
def parallel():
    return cochlea.model("parallel")


def workspace_state(model, rng, scale=2.0):
    """A random configuration in the workspace with random rates of order one."""
    return (model.geometry.random_configuration(rng), rng.uniform(-scale, scale, 5),
            rng.uniform(-scale, scale, 5))


def test_model_has_the_common_api_and_the_parallel_extras(parallel):
    for name in ("M", "C", "G", "fk", "J", "fk_world", "J_world", "Y", "M_p", "C_p", "G_p",
                 "inverse_dynamics", "inverse_dynamics_p", "forward_dynamics",
                 "forward_dynamics_p", "A", "A_dot", "J_dot", "energy"):
        assert isinstance(getattr(parallel, name), ca.Function), name
    assert parallel.nq == 5
    assert parallel.joint_names == ("left.th1", "left.th2", "slider.d1", "right.th1",
                                    "right.th2")
    assert parallel.method == "lagrange"
    assert parallel.A.size_out(0) == (5, 6) and parallel.J.size_out(0) == (6, 5)
    assert parallel.energy.size_out(0) == (2, 1)
    # The serial arms' default method name is accepted and still means the Lagrange model.
    assert cochlea.model("parallel", method="newton-euler").method == "lagrange"
    with pytest.raises(cochlea.ModelError, match="unknown method"):
        cochlea.model("parallel", method="recursive")
    with pytest.raises(cochlea.ModelError, match="unknown parameterisation"):
        cochlea.model("parallel", parameterisation="full")


# ------------------------------------------------------------------------------------------
# Energy
# ------------------------------------------------------------------------------------------


def test_power_balance_with_random_inputs(parallel, rng):
    """d(K + U)/dt == tau^T qd along the model's own accelerations, at random states."""
    q, qd = ca.SX.sym("q", 5), ca.SX.sym("qd", 5)
    E = ca.sum1(parallel.energy(q, qd))
    dE = ca.Function("dE", [q, qd], [ca.jacobian(E, q), ca.jacobian(E, qd)])
    for _ in range(N_STATES):
        qv, qdv, _ = workspace_state(parallel, rng)
        tau = rng.uniform(-2, 2, 5)
        qdd = ev(parallel.forward_dynamics, qv, qdv, tau)
        dEdq, dEdqd = (np.array(v).ravel() for v in dE(qv, qdv))
        power = dEdq @ qdv + dEdqd @ qdd
        assert power == pytest.approx(tau @ qdv, rel=1e-10, abs=1e-12)


@pytest.mark.slow
def test_energy_is_conserved_without_input(parallel, rng):
    """Zero input, no friction: K + U stays constant over 5 s of a DOP853 integration (rtol and
    atol 1e-12) from random initial states. The slider then falls freely (about 120 m in 5 s)
    while the pantographs swing; the drift is measured against the largest energy in play.

    The model is singular where a sleeve meets the slider's pivot (C = S, phi undefined; outside
    the physical workspace, see ``min_pivot_distance_m``): a trajectory that comes within 5 mm
    of it is stopped and another initial state drawn; at most as many as the ones kept."""
    x = ca.SX.sym("x", 10)
    rhs = ca.Function("rhs", [x], [ca.vertcat(x[5:], parallel.forward_dynamics(
        x[:5], x[5:], ca.DM.zeros(5)))])
    geometry = parallel.geometry

    def near_singular(t, y):
        p = geometry.points(y[:5])
        return min(np.linalg.norm(p["C"] - p["S"]), np.linalg.norm(p["C'"] - p["S"])) - 0.005

    near_singular.terminal = True
    kept, stopped = 0, 0
    while kept < 3:
        q0, qd0, _ = workspace_state(parallel, rng, scale=1.0)
        start = time.perf_counter()
        sol = solve_ivp(lambda t, y: np.array(rhs(y)).ravel(), (0.0, 5.0), np.r_[q0, qd0],
                        method="DOP853", rtol=1e-12, atol=1e-12, events=near_singular)
        elapsed = time.perf_counter() - start
        if sol.status == 1:
            stopped += 1
            assert stopped <= 3, "most trajectories run into the singular point C = S"
            continue
        assert sol.status == 0, sol.message
        kept += 1
        K, U = np.array([ev(parallel.energy, y[:5], y[5:]) for y in sol.y.T]).T
        E = K + U
        scale = max(abs(E[0]), K.max())
        drift = np.abs(E - E[0]).max() / scale
        print(f"energy drift {drift:.1e} relative ({np.abs(E - E[0]).max():.1e} J), "
              f"{sol.t.size} steps, {elapsed:.2f} s")
        assert drift < 1e-8
        assert K.max() > 10 * K[0]  # something happened: the energy really moved


# ------------------------------------------------------------------------------------------
# Structure
# ------------------------------------------------------------------------------------------


def test_mass_matrix_symmetric_positive_definite_over_the_workspace(parallel, rng):
    for _ in range(N_STATES):
        q, _, _ = workspace_state(parallel, rng)
        M = ev(parallel.M, q)
        assert np.array_equal(M, M.T)
        assert np.linalg.eigvalsh(M).min() > 0
        # Only the slider couples the two sides (thesis: M_p14 = M_p15 = M_p24 = M_p25 = 0).
        assert np.all(M[0:2, 3:5] == 0)


def test_mdot_minus_2c_is_skew_symmetric(parallel, rng):
    q, qd = ca.SX.sym("q", 5), ca.SX.sym("qd", 5)
    Mdot = ca.Function("Mdot", [q, qd], [time_derivative(parallel.M(q), q, qd)])
    for _ in range(N_STATES):
        qv, qdv, _ = workspace_state(parallel, rng)
        S = ev(Mdot, qv, qdv) - 2 * ev(parallel.C, qv, qdv)
        assert np.abs(S + S.T).max() < 1e-12
        assert np.abs(S).max() > 1e-6


def test_the_sides_mirror_each_other(parallel, rng):
    """At a mirrored configuration (th' = 180 deg - th, so th'_dot = -th_dot) the right side's
    blocks equal the left's, with the sign flips of the mirror."""
    for _ in range(20):
        q = parallel.geometry.mirrored(parallel.geometry.random_configuration(rng))
        assert np.allclose(q[3:5], np.pi - q[0:2], atol=1e-12)
        M, G = ev(parallel.M, q), ev(parallel.G, q)
        assert np.allclose(M[3:5, 3:5], M[0:2, 0:2], rtol=1e-12, atol=0)
        assert np.allclose(M[3:5, 2], -M[0:2, 2], rtol=1e-12, atol=0)
        assert np.allclose(G[3:5], -G[0:2], rtol=1e-12, atol=0)
        qd = rng.uniform(-1, 1, 5)
        qd[3:5] = -qd[0:2]
        h = ev(parallel.C, q, qd) @ qd
        assert np.allclose(h[3:5], -h[0:2], rtol=1e-10, atol=1e-14)


def thesis_entries(q, lp, d2, d3, m, I):
    """The legible entries of the thesis's M_p (2.35) with W, Z of Appendix A, typos corrected:
    A.3 ``l^2`` -> ``l_p^2``; A.2 the sign of the ``d2`` terms (as in A.5, A.6); M_p11 ``m_2`` ->
    ``m_p2``; M_p22 ``l_p^2 m_p4 / 2`` -> ``/ 4`` and ``2 l_p^2 m_p5`` -> ``l_p^2 m_p5`` (as in its
    mirror M_p55); M_p44 ``m_3`` -> ``m_p3``. ``I`` are inertias about the centres of mass."""
    t1, t2, d1, r1, r2 = q
    s1, s2, c1, c2 = np.sin(t1), np.sin(t2), np.cos(t1), np.cos(t2)
    c12 = np.cos(t1 - t2)
    W1 = 2 * lp**2 * c12 + d1**2 + d2**2 + 2 * lp**2 - 2 * d1 * lp * (s1 + s2) \
        + 2 * d2 * lp * (c1 + c2)
    W2 = 2 * lp**2 * np.cos(r1 - r2) + d1**2 + d2**2 + 2 * lp**2 \
        - 2 * d2 * lp * (np.cos(r1) + np.cos(r2)) - 2 * lp * d1 * (np.sin(r1) + np.sin(r2))
    Z1 = lp**2 * c12 + lp**2 + d2 * lp * c1 - d1 * lp * s1
    Z2 = lp**2 * c12 + lp**2 + d2 * lp * c2 - d1 * lp * s2
    Z3 = lp**2 * np.cos(r1 - r2) + lp**2 - d2 * lp * np.cos(r1) - d1 * lp * np.sin(r1)
    I57 = I[5] + I[7]
    M11 = (I[1] + I[3] + I57 * Z1**2 / W1**2 + lp**2 * m[3] / 4 + lp**2 * m[1] / 4
           + lp**2 * m[2] + lp**2 * m[5] + d3**2 * m[7] * Z1**2 / (4 * W1**2))
    M12 = (I57 * Z1 * Z2 / W1**2 + lp**2 * m[2] * c12 / 2 + lp**2 * m[3] * c12 / 2
           + lp**2 * m[5] * c12 + d3**2 * m[7] * Z1 * Z2 / (2 * W1) ** 2)
    M22 = (I[2] + I[4] + I57 * Z2**2 / W1**2 + lp**2 * m[2] / 4 + lp**2 * m[3]
           + lp**2 * m[4] / 4 + lp**2 * m[5] + d3**2 * m[7] * Z2**2 / (4 * W1**2))
    M44 = (I[1] + I[3] + I57 * Z3**2 / W2**2 + lp**2 * m[1] / 4 + lp**2 * m[2]
           + lp**2 * m[3] / 4 + lp**2 * m[5] + d3**2 * m[7] * Z3**2 / (2 * W2) ** 2)
    return M11, M12, M22, M44


def test_legible_entries_of_the_thesis_mass_matrix(parallel, rng):
    """Thesis (3.66) numbers; rods m l^2 / 12; I5 the description's chosen value."""
    lp, d2, d3 = 0.1, 0.12, 0.19
    m = {1: 0.25, 2: 0.25, 3: 0.25, 4: 0.25, 5: 1.0, 7: 0.364}
    I = {k: m[k] * lp**2 / 12 for k in (1, 2, 3, 4)}
    I[5] = load_parallel().left.body("link5").inertia_com
    I[7] = m[7] * d3**2 / 12
    for k in range(N_STATES):
        q = SCENARIO_START if k == 0 else workspace_state(parallel, rng)[0]
        M = ev(parallel.M, q)
        M11, M12, M22, M44 = thesis_entries(q, lp, d2, d3, m, I)
        assert np.allclose([M[0, 0], M[0, 1], M[1, 1], M[3, 3]], [M11, M12, M22, M44],
                           rtol=1e-12, atol=0)


def _oracle(geometry, system, q, h=1e-6):
    """M and G computed independently: body poses from the numerical geometry, their Jacobians
    by central differences, ``M = sum m Jc^T Jc + I_com Jw^T Jw``, ``G = -sum m Jc^T g``."""
    def poses(qv):
        p, x = geometry.points(qv), geometry.fk(qv)
        out = [(np.array([0.0, qv[2]]), 0.0, system.slider_mass, 0.0)]
        for side, mark, (t1, t2), phi in ((system.left, "", qv[0:2], x[2]),
                                           (system.right, "'", qv[3:5], x[5])):
            frames = {"link1": (p[f"B{mark}"], t1), "link4": (p[f"B{mark}"], t2),
                      "link2": (p[f"A1{mark}"], t2), "link3": (p[f"A4{mark}"], t1),
                      "link5": (p[f"C{mark}"], phi), "link7": (p["S"], phi)}
            for name, (origin, angle) in frames.items():
                body = side.body(name)
                R = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
                out.append((origin + R @ body.com, angle, body.mass, body.inertia_com))
        return out

    base = poses(q)
    Jc = [np.zeros((2, 5)) for _ in base]
    Jw = [np.zeros(5) for _ in base]
    for k in range(5):
        dq = np.zeros(5)
        dq[k] = h
        plus, minus = poses(q + dq), poses(q - dq)
        for i, (a, b) in enumerate(zip(plus, minus)):
            Jc[i][:, k] = (a[0] - b[0]) / (2 * h)
            Jw[i][k] = np.angle(np.exp(1j * (a[1] - b[1]))) / (2 * h)
    M = sum(m * J.T @ J + I * np.outer(w, w) for (_, _, m, I), J, w in zip(base, Jc, Jw))
    G = -sum(m * J.T @ system.gravity for (_, _, m, _), J in zip(base, Jc))
    return M, G


def test_against_an_independent_numerical_oracle(parallel, rng):
    geometry = parallel.geometry
    for k in range(30):
        q = SCENARIO_START if k == 0 else workspace_state(parallel, rng)[0]
        M_ref, G_ref = _oracle(geometry, geometry.system, q)
        assert np.allclose(ev(parallel.M, q), M_ref, rtol=0, atol=1e-8 * np.abs(M_ref).max())
        assert np.allclose(ev(parallel.G, q), G_ref, rtol=0, atol=1e-8 * np.abs(G_ref).max())


def test_forward_dynamics_inverts_inverse_dynamics(parallel, rng):
    for _ in range(N_STATES):
        q, qd, qdd = workspace_state(parallel, rng)
        tau = ev(parallel.inverse_dynamics, q, qd, qdd)
        assert np.allclose(ev(parallel.forward_dynamics, q, qd, tau), qdd, rtol=0, atol=1e-9)


# ------------------------------------------------------------------------------------------
# Regressor and parameter sets
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("parameterisation", ["inertial", "base", "mass"])
def test_regressor_identity(parameterisation, rng):
    """Y(q, qd, qd_r, qdd_r) p == M qdd_r + C qd_r + G for any p, in the workspace and at the
    arbitrary states the base-parameter search samples (d1 in [-pi, pi] m)."""
    model = cochlea.model("parallel", parameterisation=parameterisation)
    n_p = len(model.param_names)
    for k in range(N_STATES):
        if k % 2:
            q, qd, qdd_r = workspace_state(model, rng)
        else:
            q, qd, qdd_r = (rng.uniform(-np.pi, np.pi, 5) for _ in range(3))
        qd_r = rng.uniform(-2, 2, 5)
        p = model.p_nominal if k == 0 else model.p_nominal * rng.uniform(0.2, 3.0, n_p)
        Y = ev(model.Y, q, qd, qd_r, qdd_r).reshape(5, n_p)
        f = ev(model.M_p, q, p) @ qdd_r + ev(model.C_p, q, qd, p) @ qd_r + ev(model.G_p, q, p)
        assert np.all(np.isfinite(Y))
        assert np.abs(Y @ p - f).max() < 1e-12 * max(1.0, np.abs(f).max())


def test_base_parameters(rng):
    """27 base parameters: 13 per side and the total mass the slider carries; the thesis's
    ``I_p5 + I_p7`` appears as one combination on each side."""
    base = cochlea.model("parallel", parameterisation="base")
    full = cochlea.model("parallel", parameterisation="inertial")
    meanings = base.parameters.meanings
    assert len(meanings) == 27
    assert meanings[0] == "slider.m + 1*left.link7.m + 1*right.link7.m"
    assert base.p_nominal[0] == pytest.approx(0.136 + 2 * 0.364, rel=1e-12)
    for side in ("left", "right"):
        assert f"{side}.link5.Izz + 1*{side}.link7.Izz" in meanings
    rows_full, rows_base = [], []
    for _ in range(30):
        q, qd, qdd = workspace_state(full, rng)
        args = (q, qd, rng.uniform(-2, 2, 5), qdd)
        rows_full.append(ev(full.Y, *args).reshape(5, -1))
        rows_base.append(ev(base.Y, *args).reshape(5, -1))
    W, Wb = np.vstack(rows_full), np.vstack(rows_base)
    rank = np.linalg.matrix_rank(W, tol=1e-9 * np.abs(W).max())
    assert Wb.shape[1] == rank  # sampling far outside the workspace found the same rank
    assert np.linalg.matrix_rank(Wb, tol=1e-9 * np.abs(Wb).max()) == rank
    assert np.allclose(W @ full.p_nominal, Wb @ base.p_nominal, rtol=0, atol=1e-12)
    phi = full.p_nominal * rng.uniform(0.2, 3.0, full.p_nominal.size)
    beta = base.parameters.from_full @ phi
    assert np.allclose(W @ phi, Wb @ beta, rtol=0, atol=1e-11 * max(1.0, np.abs(W @ phi).max()))
    assert np.allclose(base.parameters.from_full @ base.parameters.to_full, np.eye(27),
                       rtol=0, atol=1e-12)


def test_mass_parameterisation(rng):
    mass = cochlea.model("parallel", parameterisation="mass")
    full = cochlea.model("parallel")
    assert mass.param_names[0] == "slider.m" and len(mass.param_names) == 13
    for _ in range(10):
        q, _, _ = workspace_state(full, rng)
        assert np.allclose(ev(mass.M, q), ev(full.M, q), rtol=1e-12, atol=0)
        # Twice every mass, same shapes: twice the mass matrix and gravity.
        assert np.allclose(ev(mass.M_p, q, 2 * mass.p_nominal), 2 * ev(full.M, q), rtol=1e-12)
        assert np.allclose(ev(mass.G_p, q, 2 * mass.p_nominal), 2 * ev(full.G, q), rtol=1e-12)
