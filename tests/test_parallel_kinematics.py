"""Kinematics of the parallel mechanism: FK against the thesis's numbers, J_p and A against
finite differences, closed-form IK with its branch choice, the target consistency and mirror
rules, and clear errors (never NaN) outside the workspace."""

from __future__ import annotations

import math

import numpy as np
import pytest

import cochlea
from cochlea.errors import KinematicsError
from cochlea.robots.parallel import SCENARIO_START

from .conftest import ev

N_STATES = 100


@pytest.fixture(scope="module")
def parallel():
    return cochlea.model("parallel")


def test_fk_at_the_joint_space_scenario_start(parallel):
    """q = [142 deg, 32.25 deg, 0.07075 m] (3.67 at t = 0) gives C = (0.1258, 0.1149) m and
    phi = 19.35 deg (model notes); the thesis's task-space start (3.85) is
    (0.1258, 0.1147, 19.25 deg), a fifth of a millimetre and a tenth of a degree away."""
    x = ev(parallel.fk, SCENARIO_START)
    assert abs(x[0] - 0.1258) < 5e-5 and abs(x[1] - 0.1149) < 5e-5
    assert abs(math.degrees(x[2]) - 19.35) < 5e-3
    assert abs(x[1] - 0.1147) < 3e-4 and abs(math.degrees(x[2]) - 19.25) < 0.15
    # The right side at th' = 180 deg - th mirrors the left.
    assert np.allclose(x[3:6], [-x[0], x[1], math.pi - x[2]], rtol=0, atol=1e-14)
    assert np.array_equal(ev(parallel.fk_world, SCENARIO_START), x)  # world = mechanism plane


def test_symbolic_and_numerical_fk_agree(parallel, rng):
    for _ in range(N_STATES):
        q = rng.uniform(-np.pi, np.pi, 5)
        assert np.allclose(ev(parallel.fk, q), parallel.geometry.fk(q), rtol=0, atol=1e-14)


def test_jacobian_matches_finite_differences(parallel, rng):
    h = 1e-6
    for _ in range(30):
        q = parallel.geometry.random_configuration(rng)
        J = ev(parallel.J, q)
        assert J.shape == (6, 5)
        for k in range(5):
            dq = np.zeros(5)
            dq[k] = h
            fd = (ev(parallel.fk, q + dq) - ev(parallel.fk, q - dq)) / (2 * h)
            assert np.allclose(J[:, k], fd, rtol=0, atol=1e-8)


def test_A_is_the_left_pseudo_inverse_and_its_rates_match(parallel, rng):
    """A = (J^T J)^-1 J^T; A_dot and J_dot are the time derivatives along qd."""
    h = 1e-6
    for _ in range(30):
        q = parallel.geometry.random_configuration(rng)
        qd = rng.uniform(-2, 2, 5)
        J, A = ev(parallel.J, q), ev(parallel.A, q)
        assert A.shape == (5, 6)
        # Accurate to the conditioning of J (large near a pantograph's stretched or folded
        # configuration, th1 - th2 near 0 or 180 deg).
        cond = np.linalg.cond(J)
        assert np.abs(A @ J - np.eye(5)).max() < 1e-11 * cond
        assert np.allclose(A, np.linalg.pinv(J), rtol=0, atol=1e-13 * cond * np.abs(A).max())
        fd_A = (ev(parallel.A, q + h * qd) - ev(parallel.A, q - h * qd)) / (2 * h)
        fd_J = (ev(parallel.J, q + h * qd) - ev(parallel.J, q - h * qd)) / (2 * h)
        assert np.allclose(ev(parallel.A_dot, q, qd), fd_A, rtol=0,
                           atol=1e-6 * max(1.0, np.abs(fd_A).max()))
        assert np.allclose(ev(parallel.J_dot, q, qd), fd_J, rtol=0,
                           atol=1e-6 * max(1.0, np.abs(fd_J).max()))
        # x_p_dot = J qd and qd = A x_p_dot: the controllers' x_N.
        assert np.allclose(A @ (J @ qd), qd, rtol=0, atol=1e-10)


def test_ik_round_trips_fk(parallel, rng):
    g = parallel.geometry
    for _ in range(N_STATES):
        q = g.random_configuration(rng)
        x = ev(parallel.fk, q)
        q_ik = g.ik(x, branches=g.branches(q))
        assert np.allclose(q_ik, q, rtol=0, atol=1e-9)
        assert np.allclose(ev(parallel.fk, q_ik), x, rtol=0, atol=1e-12)
        # The other branch reaches the same end points with each side's angles swapped.
        other = g.ik(x, branches=tuple(-b for b in g.branches(q)), check_limits=False)
        assert np.allclose(other[[1, 0, 2, 4, 3]], q, rtol=0, atol=1e-9)


def test_default_branches_are_the_thesis_configurations(parallel):
    """Left th1 > th2 ([142, 32.25] deg), right th1' < th2' ([43, 150] deg): +1 and -1."""
    g = parallel.geometry
    q0 = np.array([math.radians(131.5), math.radians(29.0), 0.073, math.radians(43.0),
                   math.radians(150.0)])  # the joint-space scenario's initial state
    for q in (SCENARIO_START, q0):
        assert g.branches(q) == (1, -1)
        assert g.in_workspace(q)
        assert np.allclose(g.ik(ev(parallel.fk, q)), q, rtol=0, atol=1e-12)


def test_consistency_and_mirror_rules(parallel, rng):
    """Given C and phi, the slider height is d1 = C_v - C_u tan(phi); the right side's target
    is C' = (-C_u, C_v), phi' = 180 deg - phi, reached at th' = 180 deg - th."""
    g = parallel.geometry
    for _ in range(N_STATES):
        q = g.random_configuration(rng)
        x = ev(parallel.fk, q)
        assert g.slider_height(x[0:2], x[2]) == pytest.approx(q[2], abs=1e-12)
        assert g.slider_height(x[3:5], x[5]) == pytest.approx(q[2], abs=1e-12)
    C, phi = np.array([0.1258, 0.1147]), math.radians(19.25)  # thesis (3.85) at t = 0
    target = g.target(C, phi)
    assert np.allclose(target, [0.1258, 0.1147, phi, -0.1258, 0.1147, math.pi - phi])
    q = g.ik(target)
    assert q[2] == pytest.approx(0.1147 - 0.1258 * math.tan(phi), abs=1e-15)
    assert np.allclose(q[3:5], np.pi - q[0:2], rtol=0, atol=1e-12)
    assert np.allclose(ev(parallel.fk, q), target, rtol=0, atol=1e-12)
    assert np.allclose(g.mirrored(q), q, rtol=0, atol=1e-12)


def test_the_scenarios_stay_in_the_workspace(parallel):
    """Both thesis scenarios (3.67 and 3.85, rest-to-rest cubics over 5 s) lie inside the joint
    limits, the slider stroke and the rods' reach chosen in the description."""
    g = parallel.geometry
    for t in np.linspace(0.0, 5.0, 51):
        th1 = math.radians(0.39206 * t**3 - 2.9415 * t**2 + 142)
        th2 = math.radians(0.036 * t**3 - 0.2255 * t**2 + 32.25)
        d1 = -0.000195 * t**3 + 0.0015 * t**2 + 0.07075
        q = g.mirrored([th1, th2, d1, 0.0, 0.0])
        assert g.violations(q) == []
        C = (-0.000547 * t**3 + 0.0041 * t**2 + 0.1258, -0.000388 * t**3 + 0.0029 * t**2 + 0.1147)
        assert g.violations(g.ik(g.target(C, math.radians(19.25)))) == []


TARGETS = {
    "out of reach": ([0.35, 0.1, 0.1, -0.35, 0.1, math.pi - 0.1],
                     ["(0.3500, 0.1000) m", "out of reach of the left pantograph",
                      "0 < |C - B| <= 2 l_p = 0.2 m"]),
    "at the base": ([0.12, 0.0, 0.0, -0.12, 0.0, math.pi],
                    ["C = (0.1200, 0.0000) m", "out of reach", "0 < |C - B|"]),
    "rod pointing away from C": ([0.1258, 0.1149, math.radians(160.0), -0.1258, 0.1149,
                                  math.radians(20.0)],
                                 ["phi = 160.000 deg is inconsistent",
                                  "C_u and cos(phi) have the same sign"]),
    "vertical rod": ([0.1258, 0.1149, math.pi / 2, -0.1258, 0.1149, math.pi / 2],
                     ["inconsistent"]),
    "sides disagree on d1": ([0.1258, 0.1149, math.radians(19.35), -0.1258, 0.1149,
                              math.radians(150.0)],
                             ["inconsistent", "needs the slider at d1 = 0.0707", "mirror rule"]),
    "slider out of stroke": ([0.1258, 0.1149, math.radians(-60.0), -0.1258, 0.1149,
                              math.radians(240.0)],
                             ["d1 = 0.33279 m, outside its stroke [0, 0.15] m"]),
    "joint limit": ([0.02, 0.02, math.radians(-30.0), -0.02, 0.02, math.radians(210.0)],
                    ["outside its limits", "deg"]),
    "rod too short": ([0.2, 0.1, 0.0, -0.2, 0.1, math.pi],
                      ["C = (0.2000, 0.1000) m is 0.2000 m from the slider pivot S",
                       "0.03 m <= |C - S| <= d3 = 0.19 m"]),
    "sleeve at the pivot": ([0.025, 0.11, 0.0, -0.025, 0.11, math.pi],
                            ["is 0.0250 m from the slider pivot S = (0, 0.1100) m"]),
    "not numbers": ([0.1, 0.1, float("nan"), -0.1, 0.1, 3.0], ["six finite numbers"]),
}


@pytest.mark.parametrize("case", TARGETS, ids=list(TARGETS))
def test_targets_outside_the_workspace_give_clear_errors(parallel, case):
    x_p, fragments = TARGETS[case]
    with pytest.raises(KinematicsError) as info:
        parallel.geometry.ik(x_p)
    assert isinstance(info.value, cochlea.CochleaError)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)


def test_ik_never_returns_nan(parallel, rng):
    """Random targets over a box far larger than the workspace: a q inside the workspace that
    reaches the target, or a KinematicsError."""
    g = parallel.geometry
    reached = 0
    for _ in range(2000):
        C = rng.uniform([-0.1, -0.1], [0.35, 0.35])
        phi = rng.uniform(-np.pi, np.pi)
        try:
            q = g.ik(g.target(C, phi))
        except KinematicsError:
            continue
        reached += 1
        assert np.all(np.isfinite(q)) and g.violations(q) == []
        assert np.allclose(ev(parallel.fk, q), g.target(C, phi), rtol=0, atol=1e-12)
    assert reached > 20  # the box does contain part of the workspace
