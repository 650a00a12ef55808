"""The serial chain's cheaper exact dynamics (issue 25, speed): the articulated-body algorithm
(cochlea/robots/serial/aba.py) that the model's forward dynamics, hence the plant's RK4 step,
runs on, and the regressor's ``M qdd_r + C qd_r + G`` by two Newton-Euler passes.

Each against the forms they replace (the solve of ``M qdd = tau - bias``, the Christoffel
``C`` formed from the derivatives of ``M``), kept here as the reference, and the forward
dynamics against Pinocchio's ``aba``: 1e-9 relative on random states, for the 2-, 4- and
6-DoF test arms (tests/data/planar2.toml, tests/data/arm4.urdf imported, the UR5 of
example-robot-data), the hand-written general chain (prismatic joints, tilted axes, a rolled
base) and the shipped arms, with armatures and friction where the model carries them. And
that they are cheaper: fewer SX operations for the 4- and 6-DoF arms.
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np
import pinocchio as pin
import pytest

import cochlea
from cochlea.robots.lagrange import christoffel_coriolis
from cochlea.robots.serial import load_serial
from cochlea.robots.serial.aba import aba, n_operations
from cochlea.robots.serial.chain import inertial_parameters, n_parameters, rnea
from cochlea.robots.serial.model import rigid_arm
from cochlea.robots.serial.urdf import import_urdf

from .conftest import DATA
from .test_pinocchio_oracle import pinocchio_arm
from .test_urdf import UR5

TOL = 1e-9


@pytest.fixture(scope="module")
def arms(tmp_path_factory) -> dict[str, Path | str]:
    folder = tmp_path_factory.mktemp("aba")
    out = {"planar2": DATA / "planar2.toml", "general": DATA / "general_chain.toml",
           "shipped": "serial"}
    arm4 = folder / "arm4.toml"
    arm4.write_text(import_urdf(DATA / "arm4.urdf").text, encoding="utf-8")
    out["arm4"] = arm4
    if UR5 is not None:
        ur5 = folder / "ur5.toml"
        ur5.write_text(import_urdf(UR5).text, encoding="utf-8")
        out["ur5"] = ur5
    return out


def _reference(arm, gravity):
    """The forms replaced, in the full inertial parameters ``phi``: ``M``, the forward
    dynamics by the solve, and ``M qdd_r + C qd_r + G`` with the Christoffel ``C``."""
    n = len(arm.links)
    q, qd, qdd, tau, qd_r, qdd_r = (ca.SX.sym(s, n) for s in
                                    ("q", "qd", "qdd", "tau", "qd_r", "qdd_r"))
    phi = ca.SX.sym("phi", n_parameters(arm))
    M = ca.jacobian(rnea(arm, q, ca.SX.zeros(n), qdd, phi, np.zeros(3)), qdd)
    M = 0.5 * (M + M.T)
    bias = rnea(arm, q, qd, ca.SX.zeros(n), phi, gravity)
    G = rnea(arm, q, ca.SX.zeros(n), ca.SX.zeros(n), phi, gravity)
    C = christoffel_coriolis(M, q, qd)
    fd = ca.Function("fd", [q, qd, tau, phi], [ca.solve(M, tau - bias)])
    f_r = ca.Function("f_r", [q, qd, qd_r, qdd_r, phi], [M @ qdd_r + C @ qd_r + G])
    ours = ca.Function("aba", [q, qd, tau, phi], [aba(arm, q, qd, tau, phi, gravity)])
    return fd, f_r, ours, (q, qd, tau, phi)


def _phi(arm, rng):
    """The arm's own inertial parameters, then a random positive armature per declared one."""
    phi = np.concatenate([inertial_parameters(link) for link in arm.links])
    return np.concatenate([phi, rng.uniform(0.01, 0.1, n_parameters(arm) - phi.size)])


def _rel(a, b) -> float:
    a, b = np.asarray(a, float).ravel(), np.asarray(b, float).ravel()
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def _state(rng, n):
    return (rng.uniform(-np.pi, np.pi, n), rng.uniform(-3, 3, n), rng.uniform(-20, 20, n))


@pytest.mark.parametrize("which", ["planar2", "arm4", "ur5", "general", "shipped"])
def test_aba_is_the_solve_and_pinocchios_aba(which, arms, rng):
    if which not in arms:
        pytest.skip("example-robot-data is not installed")
    system = load_serial(arms[which])
    for arm in system.arms:
        rigid = rigid_arm(arm)
        gravity = rigid.base_rotation.T @ system.gravity
        fd, _, ours, _ = _reference(rigid, gravity)
        theirs = pinocchio_arm(system, rigid)
        data = theirs.createData()
        phi = _phi(rigid, rng)
        assert np.abs(np.asarray(gravity)).max() > 1.0  # gravity is exercised
        for _ in range(50):
            q, qd, tau = _state(rng, len(rigid.links))
            qdd = np.asarray(ours(q, qd, tau, phi)).ravel()
            assert _rel(qdd, fd(q, qd, tau, phi)) < TOL
            assert _rel(qdd, pin.aba(theirs, data, q, qd, tau)) < TOL


@pytest.mark.parametrize("which", ["arm4", "general"])
def test_aba_carries_the_armatures(which, arms, rng):
    """A declared armature adds to its joint's articulated inertia (``Ia`` on ``M``'s
    diagonal): against the solve with random armatures on every joint."""
    system = load_serial(arms[which])
    arm = system.arms[0]
    from dataclasses import replace
    arm = replace(arm, links=tuple(
        replace(link, joint=replace(link.joint, actuator=replace(link.joint.actuator,
                                                                 armature=0.05)))
        for link in arm.links))
    gravity = arm.base_rotation.T @ system.gravity
    fd, _, ours, _ = _reference(arm, gravity)
    phi = _phi(arm, rng)
    assert phi.size > 10 * len(arm.links)
    for _ in range(50):
        q, qd, tau = _state(rng, len(arm.links))
        assert _rel(ours(q, qd, tau, phi), fd(q, qd, tau, phi)) < TOL


@pytest.mark.parametrize("which", ["planar2", "arm4", "ur5", "general", "shipped"])
@pytest.mark.parametrize("actuators", ["none", "all"])
@pytest.mark.slow
def test_the_models_functions_are_the_replaced_forms(which, actuators, arms, rng):
    """The built model (any parameterisation's ``p``, friction when it carries it): its
    forward dynamics solves its own ``M`` and inverse dynamics, and its regressor ``Y`` gives
    ``M qdd_r + C qd_r + G + F(qd_r)`` with the Christoffel ``C`` of its own ``M``."""
    if which not in arms:
        pytest.skip("example-robot-data is not installed")
    for parameterisation in ("inertial", "base"):
        model = cochlea.model("serial", description=arms[which],
                              parameterisation=parameterisation, actuators=actuators)
        n = model.nq
        p = model.p_nominal * rng.uniform(0.8, 1.2, model.p_nominal.size)
        q_s, qd_s = ca.SX.sym("q", n), ca.SX.sym("qd", n)
        C_chr = ca.Function("C", [q_s, qd_s], [christoffel_coriolis(model.M_p(q_s, p), q_s,
                                                                    qd_s)])
        for _ in range(20):
            q, qd, tau = _state(rng, n)
            qd_r, qdd_r = rng.uniform(-3, 3, n), rng.uniform(-20, 20, n)
            M = np.asarray(model.M_p(q, p))
            bias = np.asarray(model.inverse_dynamics_p(q, qd, np.zeros(n), p)).ravel()
            qdd = np.asarray(model.forward_dynamics_p(q, qd, tau, p)).ravel()
            assert _rel(qdd, np.linalg.solve(M, tau - bias)) < TOL
            expected = (M @ qdd_r + np.asarray(C_chr(q, qd)) @ qd_r
                        + np.asarray(model.G_p(q, p)).ravel()
                        + np.asarray(model.friction_p(qd_r, p)).ravel())
            assert _rel(np.asarray(model.Y(q, qd, qd_r, qdd_r)) @ p, expected) < TOL


@pytest.mark.parametrize("which", ["arm4", "ur5"])
@pytest.mark.slow
def test_the_replacements_are_cheaper(which, arms):
    """Fewer SX operations than the forms they replace: the forward dynamics (in symbolic
    inertial parameters, as the plant step takes them) and the regressor."""
    if which not in arms:
        pytest.skip("example-robot-data is not installed")
    system = load_serial(arms[which])
    arm = rigid_arm(system.arms[0])
    gravity = arm.base_rotation.T @ system.gravity
    fd, f_r, ours, syms = _reference(arm, gravity)
    assert ours.n_instructions() < fd.n_instructions()
    n = len(arm.links)
    q, qd, qd_r, qdd_r = (ca.SX.sym(s, n) for s in ("q", "qd", "qd_r", "qdd_r"))
    phi = ca.SX.sym("phi", n_parameters(arm))
    old = ca.jacobian(f_r(q, qd, qd_r, qdd_r, phi), phi)
    model = cochlea.model("serial", description=arms[which], parameterisation="inertial")
    new = model.Y(q, qd, qd_r, qdd_r)
    assert n_operations(new, q, qd, qd_r, qdd_r) < 0.5 * n_operations(old, q, qd, qd_r,
                                                                      qdd_r, phi)
