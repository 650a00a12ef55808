"""The joints' drives in the models (issue 11, item 1): the shipped descriptions declare each
joint's armature, viscous and Coulomb friction; ``actuators="none"`` keeps the thesis's rigid
links, ``"armature"`` adds the rotors' inertia, ``"all"`` also makes both frictions estimated
parameters, so the regressor factors ``M qdd_r + C qd_r + G + F(qd)`` and every controller
compensates friction through it."""

from __future__ import annotations

import numpy as np
import pytest

import cochlea
from cochlea.control import build
from cochlea.robots import robot
from cochlea.robots.model import COULOMB_SMOOTHING

from .conftest import ev

ROBOTS = ("serial", "parallel")


def _state(model, rng):
    n = model.nq
    if model.geometry is not None:
        q = model.geometry.random_configuration(rng)
    else:
        q = rng.uniform(-np.pi, np.pi, n)
        q[1] = rng.choice([-1, 1]) * rng.uniform(0.4, 2.6)  # clear of the stretched arm
    return q, rng.uniform(-1, 1, n)


def test_every_shipped_joint_declares_its_drive():
    for name in ROBOTS:
        adapter = robot(name)
        for joint in adapter.actuated_joints(adapter.load()):
            a = joint.actuator
            assert a.armature > 0 and a.viscous > 0 and a.coulomb > 0, joint.name
    # The thesis's rigid links stay the default: no parameter beyond the bodies'.
    for name in ROBOTS:
        names = cochlea.model(name).parameters.names
        assert not any(n.rsplit(".", 1)[1] in ("Ia", "Fv", "Fc") for n in names)


@pytest.mark.parametrize("name", ROBOTS)
def test_friction_is_its_own_term_and_nothing_else(name, rng):
    """``all`` = ``armature`` + ``Fv qd + Fc tanh(qd / v)`` in the inverse dynamics, with the
    description's values; M, C and G do not change."""
    geared = cochlea.model(name, actuators="armature")
    full = cochlea.model(name, actuators="all")
    joints = robot(name).actuated_joints(robot(name).load())
    per_unit = joints[:full.nq]  # the serial system lists both arms: the first is arm1
    fv = np.array([j.actuator.viscous for j in per_unit])
    fc = np.array([j.actuator.coulomb for j in per_unit])
    smooth = np.array([COULOMB_SMOOTHING[j.type] for j in per_unit])
    assert full.param_names[:len(geared.param_names)] == geared.param_names
    for _ in range(5):
        q, qd = _state(full, rng)
        qdd = rng.uniform(-2, 2, full.nq)
        expected = fv * qd + fc * np.tanh(qd / smooth)
        added = ev(full.inverse_dynamics, q, qd, qdd) - ev(geared.inverse_dynamics, q, qd, qdd)
        assert np.allclose(added, expected, rtol=1e-12, atol=1e-14)
        assert np.allclose(ev(full.friction_p, qd, full.p_nominal), expected, rtol=1e-12)
        assert np.allclose(ev(full.M, q), ev(geared.M, q), rtol=0, atol=1e-14)
        assert np.allclose(ev(full.C, q, qd), ev(geared.C, q, qd), rtol=0, atol=1e-14)
        # Forward dynamics inverts the inverse dynamics with the friction in it.
        tau = ev(full.inverse_dynamics, q, qd, qdd)
        assert np.allclose(ev(full.forward_dynamics, q, qd, tau), qdd, rtol=1e-8, atol=1e-9)
    # The armature sits on the diagonal of M, as the description gives it.
    q, _ = _state(full, rng)
    armature = np.array([j.actuator.armature for j in per_unit])
    rigid = cochlea.model(name)
    assert np.allclose(ev(geared.M, q) - ev(rigid.M, q), np.diag(armature), rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", ROBOTS)
@pytest.mark.parametrize("parameterisation", ["inertial", "mass", "base"])
def test_regressor_identity_with_friction(name, parameterisation, rng):
    m = cochlea.model(name, parameterisation=parameterisation, actuators="all")
    geared = cochlea.model(name, parameterisation=parameterisation, actuators="armature")
    assert len(m.param_names) == len(geared.param_names) + 2 * m.nq  # each identifiable
    for _ in range(5):
        q, qd = _state(m, rng)
        qd_r, qdd_r = rng.uniform(-1, 1, m.nq), rng.uniform(-2, 2, m.nq)
        p = m.p_nominal * rng.uniform(0.5, 2.0, len(m.param_names))
        Y = ev(m.Y, q, qd, qd_r, qdd_r).reshape(m.nq, -1)
        f = (ev(m.M_p, q, p) @ qdd_r + ev(m.C_p, q, qd, p) @ qd_r + ev(m.G_p, q, p)
             + ev(m.friction_p, qd_r, p))  # friction at the reference velocity
        assert np.abs(Y @ p - f).max() <= 1e-11 * max(1.0, np.abs(f).max())


@pytest.mark.parametrize("kind", ["e", "g", "f", "d"])
def test_every_controller_regressor_factors_friction(kind, rng):
    name = "serial" if kind in "eg" else "parallel"
    m = cochlea.model(name, parameterisation="mass", actuators="all")
    task = (m.fk, m.J) if name == "parallel" else None
    c = build(m, kind, task_angles=(2,) if name == "serial" else (2, 5), task=task)
    fk = m.fk if name == "parallel" else m.fk_world
    for _ in range(10):
        q, qd = _state(m, rng)
        xd = q + rng.uniform(-0.05, 0.05, m.nq) if c.space == "joint" else \
            ev(fk, q) + rng.uniform(-0.005, 0.005, c.n_task)
        xd_dot, xd_ddot = (rng.uniform(-0.1, 0.1, c.n_desired) for _ in range(2))
        gains = rng.uniform(0.1, 5.0, sum(c.gain_sizes))
        p = m.p_nominal * rng.uniform(0.2, 3.0, c.n_params)
        Y = ev(c.regressor, q, qd, xd, xd_dot, xd_ddot, gains,
               *c.neutral()[3:]).reshape(m.nq, c.n_params)
        f = ev(c.auxiliary, q, qd, xd, xd_dot, xd_ddot, gains, p, *c.neutral()[3:])
        assert np.abs(Y @ p - f).max() <= 1e-10 * max(1.0, np.abs(f).max())
        # The friction columns are there and see the reference velocity, not the measured one.
        friction = np.array([n.endswith((".Fv", ".Fc")) for n in m.param_names])
        added = Y @ (p * np.where(friction, 2.0, 1.0)) - Y @ p
        assert np.abs(added).max() > 1e-6
        assert not np.allclose(added, ev(m.friction_p, qd, p), rtol=1e-6, atol=1e-9)


def test_a_bad_actuator_value_names_its_key(tmp_path):
    from cochlea.resources import ROBOTS_DIR
    text = (ROBOTS_DIR / "serial.toml").read_text().replace(
        "coulomb_friction_Nm = 0.155", "coulomb_friction_Nm = -0.155", 1)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(cochlea.DescriptionError, match="coulomb_friction_Nm"):
        cochlea.load_serial(path)
    with pytest.raises(cochlea.ModelError, match="actuators"):
        cochlea.model("serial", actuators="some")
