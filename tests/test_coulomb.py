"""Dry (Coulomb) friction in the plant (issue 11, item 2): a joint pushed below breakaway from
rest stays put, one pushed past it moves against the friction, a sliding joint stops and stays
stopped; the scenario key reaches the simulation, and without it the plant is unchanged."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

import cochlea
from cochlea.robots.plant import plant_step
from cochlea.sim import CKernelsWarning, load_scenario, simulate, unit_setups
from cochlea.sim.scenario import Plant

LEVEL = np.array([0.02, 0.015, 0.01])  # N m: the order of the Table C.1 fits' offsets
H = 1e-3  # s


@pytest.fixture(scope="module")
def arm():
    return cochlea.model("serial", parameterisation="inertial")


@pytest.fixture(scope="module")
def step(arm):
    return plant_step(arm, 1, coulomb=True)


#: Joints 2 and 3 with levels far above any reaction joint 1 puts on them: locked by friction.
LOCKED = np.array([LEVEL[0], 1.0, 1.0])


def dry(level):
    """The plant's dry-friction input for plain Coulomb friction: static = Coulomb."""
    return np.concatenate([level, level, np.full(len(level), 0.02)])


def run(step, arm, x0, tau, periods, level=LEVEL):
    x = np.array(x0, float)
    states = [x]
    for _ in range(periods):
        x = np.array(step(x, tau, arm.p_nominal, np.zeros(3), H, dry(level))).ravel()
        states.append(x)
    return np.array(states)


Q0 = np.radians([73.0, 83.0, 110.0])


def test_below_breakaway_the_joints_stay_exactly_put(step, arm):
    for tau in ([0.5 * LEVEL[0], 0.0, 0.0], 0.9 * LEVEL, [-0.01, 0.012, -0.009]):
        states = run(step, arm, np.r_[Q0, 0, 0, 0], np.array(tau), 500)
        assert np.array_equal(states[-1], states[0]), tau


def test_past_breakaway_a_joint_moves_against_the_friction(step, arm):
    """3x the level on joint 1 alone, joints 2 and 3 locked by friction: joint 1 accelerates
    with (3 - 1) x level over its inertia, and joints 2 and 3 do not move at all."""
    tau = np.array([3 * LEVEL[0], 0.0, 0.0])
    states = run(step, arm, np.r_[Q0, 0, 0, 0], tau, 100, LOCKED)
    assert np.array_equal(states[:, 1:3], np.tile(Q0[1:], (101, 1)))  # joints 2, 3 held
    M11 = float(np.array(arm.M(Q0))[0, 0])  # constant while joints 2 and 3 stay put
    t = 0.1
    assert states[-1, 3] == pytest.approx(2 * LEVEL[0] / M11 * t, rel=1e-3)
    frictionless = plant_step(arm, 1)
    x = np.r_[Q0, 0, 0, 0]
    for _ in range(100):
        x = np.array(frictionless(x, tau, arm.p_nominal, np.zeros(3), H)).ravel()
    assert abs(states[-1, 0] - Q0[0]) < abs(x[0] - Q0[0])
    # With the real, lower levels the reaction of joint 1's acceleration moves joints 2 and 3.
    slipping = run(step, arm, np.r_[Q0, 0, 0, 0], tau, 100)
    assert not np.allclose(slipping[-1, 1:3], Q0[1:], rtol=0, atol=1e-6)


def test_a_sliding_joint_stops_and_stays_stopped(step, arm):
    qd0 = 0.2  # rad/s on joint 1, no torque: the friction brakes it
    M11 = float(np.array(arm.M(Q0))[0, 0])
    stopping = M11 * qd0 / LEVEL[0]  # s, if joints 2 and 3 stay put
    states = run(step, arm, np.r_[Q0, qd0, 0, 0], np.zeros(3), int(3 * stopping / H), LOCKED)
    assert np.array_equal(states[-1, 3:], np.zeros(3))
    stopped = int(np.argmax(np.all(states[:, 3:] == 0, axis=1)))
    assert abs(stopped * H - stopping) <= H  # within the period it stops in
    assert np.array_equal(states[stopped:, :3], np.tile(states[stopped, :3], (len(states)
                                                                              - stopped, 1)))
    travel = states[-1, 0] - Q0[0]
    assert travel == pytest.approx(0.5 * qd0 ** 2 * M11 / LEVEL[0], rel=0.02)


def test_without_coulomb_the_plant_is_the_one_generated():
    """The plain plant Function is untouched by the option (same name, same graph)."""
    m = cochlea.model("serial", parameterisation="inertial")
    plain, again = plant_step(m, 1), plant_step(m, 1, coulomb=False)
    assert plain.name() == "serial_arm1_plant_step" and plain.serialize() == again.serialize()
    assert plant_step(m, 1, coulomb=True).name() == "serial_arm1_plant_step_coulomb"


@pytest.mark.slow
def test_scenario_coulomb_friction_reaches_the_plant():
    """The scenario key reaches the plant, and simulate() runs it in C (no fallback): the log
    equals the CasADi reference's."""
    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, plant=Plant(coulomb_friction=np.array([0.02, 0.015, 0.01])))
    setups = unit_setups(sc)
    assert np.array_equal(setups[0].coulomb, [0.02, 0.015, 0.01])
    assert np.array_equal(setups[0].drive[:6], [0.02, 0.015, 0.01] * 2)  # static = Coulomb
    reference = simulate(sc, 0.2, setups, kernels="casadi")
    with warnings.catch_warnings():
        warnings.simplefilter("error", CKernelsWarning)  # the C kernels run it
        compiled = simulate(sc, 0.2, setups)
    plain = simulate(load_scenario("serial_joint"), 0.2, kernels="casadi")
    for a, b, c in zip(reference.units, compiled.units, plain.units):
        for key in ("q", "qd", "tau", "errors", "p_hat"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=1e-10)
        assert not np.allclose(a.q, c.q, rtol=0, atol=1e-9)  # the friction acts


@pytest.mark.parametrize("name", ["serial_arm1", "serial_arm2", "parallel"])
def test_the_c_plant_step_equals_the_casadi_one(name):
    """``<unit>_plant_step_coulomb`` from the library against the Function, from rest below and
    above breakaway and while sliding (arm 2's kernel is an alias of arm 1's C)."""
    from cochlea.kernels import library

    arm, unit = (name.split("_") + [None])[:2]
    m = cochlea.model(arm, arm=unit, parameterisation="inertial")
    f = plant_step(m, 1, coulomb=True)
    kernel = library.load().kernel(f.name())
    assert kernel["x_next"].shape == (2 * m.nq,)
    if name == "serial_arm2":
        assert library.load().symbol(f.name()) == "serial_arm1_plant_step_coulomb"
    rng = np.random.default_rng(5)
    level = np.full(m.nq, 0.02)
    x = np.zeros(2 * m.nq)
    x[:m.nq] = [0.7, 1.2, 1.9] if m.nq == 3 else [2.478, 0.563, 0.07075, 0.663, 2.579]
    for tau_scale, speed in ((0.5, 0.0), (3.0, 0.0), (0.0, 0.3), (1.0, 0.05)):
        state = x.copy()
        state[m.nq:] = speed * rng.standard_normal(m.nq)
        tau = tau_scale * level * rng.choice([-1.0, 1.0], m.nq)
        friction = np.full(m.nq, 1e-3)
        static = np.concatenate([level, 1.5 * level, np.full(m.nq, 0.02)])
        want = np.array(f(state, tau, m.p_nominal, friction, H, static)).ravel()
        got, = kernel.evaluate(state, tau, m.p_nominal, friction, H, static)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


@pytest.mark.slow
def test_the_real_time_sim_backend_runs_the_c_plant():
    from cochlea.runtime.sim_backend import SimBackend
    from cochlea.sim.compiled import period_kernels

    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, plant=Plant(coulomb_friction=np.array([0.02, 0.015, 0.01])))
    setups = unit_setups(sc)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CKernelsWarning)
        kernels = period_kernels(setups[0], sc.plant_substeps)
        backend = SimBackend(setups, sc.period, sc.plant_substeps)
    assert kernels[3] == "c" and kernels[1].kernel.name == "serial_arm1_plant_step_coulomb"
    assert [f.kernel.name for f in backend._steps] == ["serial_arm1_plant_step_coulomb",
                                                       "serial_arm2_plant_step_coulomb"]
