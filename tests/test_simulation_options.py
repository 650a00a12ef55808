"""The plant options of a scenario do what they say: measurement delay, noise, friction."""

from __future__ import annotations

import dataclasses

import numpy as np

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
    assert np.allclose(e_logged[delay:], u.desired[delay:] - u.q[:-delay], atol=1e-15)
    assert np.allclose(e_logged[:delay], u.desired[:delay] - u.q[0], atol=1e-15)


def test_noise_is_added_to_the_measurement_with_the_given_spread():
    std = 1e-3
    u = _joint_run(Plant(noise_q_std=std, seed=7))
    noise = (u.desired - u.q) - u.errors[:, :3]  # measured minus true
    assert abs(noise.std() - std) < 0.1 * std and abs(noise.mean()) < 0.1 * std
    again = _joint_run(Plant(noise_q_std=std, seed=7))
    assert np.array_equal(again.q, u.q)  # seeded: a run reproduces


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
