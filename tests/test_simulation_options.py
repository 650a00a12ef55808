"""The plant options of a scenario do what they say: measurement delay, noise, friction."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from cochlea.robots.plant import plant_step
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.scenario import Plant


def _joint_run(plant, duration=0.3):
    sc = load_scenario("serial_joint")
    return simulate(dataclasses.replace(sc, plant=plant), duration=duration).units[0]


def test_delay_feeds_the_controller_the_state_of_earlier_periods():
    delay = 3
    u = _joint_run(Plant(delay_periods=delay))
    e_logged = u.errors[:, :3]  # th_d(t_k) - th_measured(k)
    assert np.allclose(e_logged[delay:], u.desired[delay:] - u.true_q[:-delay], atol=1e-15)
    assert np.allclose(e_logged[:delay], u.desired[:delay] - u.true_q[0], atol=1e-15)
    # The log's measured state is what the controller saw: the true state delay periods ago.
    assert np.array_equal(u.q[delay:], u.true_q[:-delay])
    assert np.array_equal(u.qd[:delay], np.tile(u.true_qd[0], (delay, 1)))
    assert np.allclose(e_logged, u.desired - u.q, rtol=0, atol=1e-15)


def test_noise_is_added_to_the_measurement_with_the_given_spread():
    std = 1e-3
    u = _joint_run(Plant(noise_q_std=std, seed=7))
    noise = (u.desired - u.true_q) - u.errors[:, :3]  # measured minus true
    assert abs(noise.std() - std) < 0.1 * std and abs(noise.mean()) < 0.1 * std
    assert np.allclose(u.q - u.true_q, noise, rtol=0, atol=1e-15)  # the log's measurement
    again = _joint_run(Plant(noise_q_std=std, seed=7))
    assert np.array_equal(again.true_q, u.true_q)  # seeded: a run reproduces
    assert np.array_equal(again.q, u.q)


def test_viscous_friction_takes_energy_out_of_the_plant():
    setup = unit_setups(load_scenario("serial_joint"))[0]
    step = plant_step(setup.plant_model, 4)
    M = setup.plant_model.M_p
    x = np.r_[0.3, 1.0, -0.5, 2.0, -1.0, 3.0]

    def kinetic(state):
        q, qd = state[:3], state[3:]
        return 0.5 * qd @ np.array(M(q, setup.plant_params)) @ qd

    free = np.array(step(x, np.zeros(3), setup.plant_params, np.zeros(3), 1e-3)).ravel()
    damped = np.array(step(x, np.zeros(3), setup.plant_params, np.full(3, 1e-3), 1e-3)).ravel()
    assert abs(kinetic(free) - kinetic(x)) < 1e-9 * kinetic(x)  # horizontal arm: conserved
    assert kinetic(damped) < kinetic(x) * (1 - 1e-3)


@pytest.mark.parametrize("kernels", ["casadi", "c"])
def test_quantised_measurements_lie_on_the_encoder_grid(kernels):
    """With the motors' encoder and velocity register, controller e sees positions on the
    4096-count grid: e = xd - q_measured, so xd - e is a whole number of counts."""
    from cochlea.dynamixel.control_table import RAD_PER_COUNT

    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, plant=Plant(position_encoder=True, velocity_register=True))
    result = simulate(sc, duration=0.3, kernels=kernels)
    for u in result.units:
        n = u.setup.controller_model.nq
        assert np.allclose(u.setup.quantum[:n], RAD_PER_COUNT)
        seen = u.desired - u.errors[:, :n]  # rad: what the controller was given
        counts = seen / RAD_PER_COUNT
        assert np.allclose(counts, np.rint(counts), rtol=0, atol=1e-6)
        assert np.allclose(u.q, seen, rtol=0, atol=1e-15)  # the log's measured positions
        continuous = u.true_q / RAD_PER_COUNT  # the true joints are not on the grid
        assert not np.allclose(continuous, np.rint(continuous), rtol=0, atol=1e-6)


@pytest.mark.slow
def test_quantised_c_loop_equals_the_reference():
    sc = load_scenario("parallel_joint")
    sc = dataclasses.replace(sc, plant=Plant(position_encoder=True, velocity_register=True,
                                             noise_q_std=1e-4, delay_periods=1))
    setups = unit_setups(sc)
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    compiled = simulate(sc, 0.5, setups, kernels="c")
    for a, b in zip(compiled.units, reference.units):
        for key in ("q", "qd", "true_q", "true_qd", "pose", "true_x", "tau", "errors", "p_hat"):
            assert np.allclose(getattr(a, key), getattr(b, key), rtol=0, atol=1e-10), key
    slider = setups[0].quantum[2]  # m per count: through the pinion's radius
    assert slider == pytest.approx(2 * np.pi / 4096 * 0.02)
