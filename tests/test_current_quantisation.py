"""Current quantisation and saturation (issue 11): with ``current_quantisation = true`` the
plant gets each command as the drives apply it -- whole Goal Current LSBs through the joint's
fit, saturated at the Current Limit -- identically in the CasADi reference, the C driver, the
Python loop over the C kernels and the real-time sim backend; a saturated command is counted."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cochlea import load_serial
from cochlea.dynamixel import drives
from cochlea.dynamixel.control_table import MX64, XM540_W270
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.robots import motor_fit
from cochlea.runtime import RealTimeLoop, build_supervisor, verdict
from cochlea.runtime.sim_backend import SimBackend
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.scenario import Plant

DURATION = 0.5  # s


def _quantised(name: str, **plant) -> tuple:
    sc = load_scenario(name)
    sc = dataclasses.replace(sc, plant=Plant(current_quantisation=True, **plant))
    return sc, unit_setups(sc)


def _on_grid(tau: np.ndarray, quantum: np.ndarray) -> np.ndarray:
    steps = tau / quantum
    return np.isclose(steps, np.rint(steps), rtol=0, atol=1e-9)


# ---- the scenario key and the grid -----------------------------------------------------------


def test_the_scenario_key_is_read_and_defaults_to_off(tmp_path):
    text = (SCENARIOS_DIR / "serial_joint.toml").read_text()
    assert load_scenario("serial_joint").plant.current_quantisation is False
    assert unit_setups(load_scenario("serial_joint"))[0].effort_grid is None
    path = tmp_path / "quantised.toml"
    path.write_text(text.replace("[control]", "[plant]\ncurrent_quantisation = true\n\n"
                                 "[control]", 1))
    assert load_scenario(path).plant.current_quantisation is True
    path.write_text(text.replace("[control]", "[plant]\ncurrent_quantisation = 1\n\n"
                                 "[control]", 1))
    with pytest.raises(Exception, match="plant.current_quantisation: expected true or false"):
        load_scenario(path)


def test_the_grid_is_one_current_lsb_through_each_joints_fit():
    """Serial arm 1, joint 1: MX-64, fit 108.2 N cm/A - 15.47 N cm, so 3.36 mA is 3.636 mN m.
    The slider: XM540-W270, 97.2 N cm/A on a 20 mm pinion, so 2.69 mA is 0.1307 N."""
    _, serial = _quantised("serial_joint")
    grid = serial[0].effort_grid
    assert grid.quantum[0] == pytest.approx(1.082 * 3.36e-3, rel=1e-12)
    assert grid.quantum[1] == pytest.approx(1.223 * MX64.current_unit_mA * 1e-3, rel=1e-12)
    assert np.array_equal(grid.limit, serial[0].effort_limit)
    # Without current_limit_mA the Current Limit is what the effort limit needs, rounded up.
    assert np.all(grid.saturation >= grid.limit) and np.all(grid.saturation < grid.limit
                                                            + grid.quantum)
    _, parallel = _quantised("parallel_joint")
    slider = parallel[0].effort_grid
    assert slider.quantum[2] == pytest.approx(0.972 * XM540_W270.current_unit_mA * 1e-3 / 0.02,
                                              rel=1e-12)
    assert slider.bound[2] == 100.0  # N: the force limit


def test_the_fit_lives_with_the_robots_and_the_bridge_uses_it():
    assert drives.Fit is motor_fit.Fit
    assert drives.current_limit_lsb is motor_fit.current_limit_lsb
    fit = motor_fit.Fit.from_description(load_serial().arms[0].links[1].motor.fit)
    motor = load_serial().arms[0].links[1].motor
    quantum, saturation = motor_fit.effort_grid(motor, 1.0, 2.5)
    limit = drives.joint_drives("serial")[1].current_limit_lsb
    assert saturation == pytest.approx(fit.a * limit * 3.36e-3 + fit.b, rel=1e-12)
    assert quantum == pytest.approx(fit.a * 3.36e-3, rel=1e-12)


def test_apply_rounds_half_to_even_and_bounds():
    grid = unit_setups(dataclasses.replace(
        load_scenario("serial_joint"), plant=Plant(current_quantisation=True)))[0].effort_grid
    q = grid.quantum
    tau = np.array([2.5 * q[0], -0.5 * q[1], 7.0])  # halves go to even; 7 N m: bounded
    out = np.empty(3)
    assert grid.apply(tau, out) is out
    assert np.array_equal(out, [2 * q[0], -0.0, grid.bound[2]])
    before = tau.copy()
    grid.apply(tau)
    assert np.array_equal(tau, out) and not np.array_equal(tau, before)


# ---- the same applied efforts everywhere ----------------------------------------------------


@pytest.mark.parametrize("kernels", ["casadi", "c"])
@pytest.mark.parametrize("name", ["serial_joint", "parallel_task"])
@pytest.mark.slow
def test_applied_efforts_lie_on_the_effort_grid(name, kernels):
    sc, setups = _quantised(name)
    result = simulate(sc, DURATION, setups, kernels=kernels)
    plain = simulate(load_scenario(name), DURATION, kernels=kernels)
    for u, p in zip(result.units, plain.units):
        grid = u.setup.effort_grid
        inside = np.abs(u.tau) < grid.bound
        assert np.all(_on_grid(u.tau, grid.quantum)[inside])
        assert np.all(np.abs(u.tau) <= grid.bound)
        assert not np.all(_on_grid(p.tau, grid.quantum))  # the continuous commands are not
    moved = [not np.allclose(u.q, p.q, rtol=0, atol=1e-9)
             for u, p in zip(result.units, plain.units)]
    assert any(moved)  # the rounding changes the motion


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("name", ["serial_task", "parallel_joint"])
@pytest.mark.slow
def test_c_loops_apply_what_the_reference_applies(name, loop):
    sc, setups = _quantised(name)
    reference = simulate(sc, DURATION, setups, kernels="casadi")
    result = csim.simulate_compiled(sc, DURATION, setups, loop=loop)
    for a, b in zip(result.units, reference.units):
        for key in ("q", "qd", "tau", "errors", "p_hat"):
            np.testing.assert_allclose(getattr(a, key), getattr(b, key), rtol=1e-10,
                                       atol=1e-10, err_msg=key)


# ---- saturation at the Current Limit ----------------------------------------------------------


@pytest.fixture(scope="module")
def weak_current(tmp_path_factory):
    """serial_joint on a description whose arm 1 link 2 motor has a 250 mA Current Limit:
    75 LSB, 0.252 A, through the fit 1.223 N m/A - 0.237 N m: 71 mN m, far below the 2.5 N m
    effort limit and below the 0.12 N m the controller asks early in the run."""
    text = (ROBOTS_DIR / "serial.toml").read_text()
    anchor = "id = 2\n"
    assert text.count(anchor) == 1
    path = tmp_path_factory.mktemp("weak") / "weak_current.toml"
    path.write_text(text.replace(anchor, anchor + "  current_limit_mA = 250.0\n"))
    sc = load_scenario("serial_joint")
    return dataclasses.replace(sc, description=str(path), system=load_serial(path))


@pytest.mark.slow
def test_a_command_above_the_current_limit_is_saturated_and_counted(weak_current):
    plain = simulate(weak_current, DURATION, kernels="casadi")
    sc = dataclasses.replace(weak_current, plant=Plant(current_quantisation=True))
    setups = unit_setups(sc)
    grid = setups[0].effort_grid
    fit = motor_fit.Fit.from_description(sc.system.arms[0].links[1].motor.fit)
    expected = float(fit.torque(math.ceil(250.0 / 3.36) * 3.36e-3))
    assert grid.saturation[1] == pytest.approx(expected, rel=1e-12)
    assert grid.bound[1] == grid.saturation[1] < 0.1 < grid.limit[1]
    assert np.abs(plain.units[0].tau[:, 1]).max() > grid.bound[1]  # the controller asks more
    sup = build_supervisor(setups, None, substeps=sc.plant_substeps)
    assert verdict(plain, sup)["saturated_periods"] == 0  # nothing reaches 2.5 N m
    for kernels in ("casadi", "c"):
        result = simulate(sc, DURATION, setups, kernels=kernels)
        link2 = result.units[0].tau[:, 1]
        assert np.abs(link2).max() == grid.bound[1]  # saturated exactly, never beyond
        held = int(np.sum(np.abs(link2) == grid.bound[1]))
        assert held >= 3  # the first periods ask up to 0.12 N m
        assert verdict(result, sup)["saturated_periods"] >= held


@pytest.mark.slow
def test_a_command_clipped_to_the_effort_limit_is_still_counted(tmp_path):
    """A 2 mN m torque limit, below one current LSB on every joint: the command clipped to it
    rounds to one LSB or none, bounded by the limit; those periods count as saturated."""
    weak = tmp_path / "weak.toml"
    weak.write_text((ROBOTS_DIR / "serial.toml").read_text().replace(
        "torque_limit_Nm = 2.5", "torque_limit_Nm = 0.002"))
    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, description=str(weak), system=load_serial(weak),
                             plant=Plant(current_quantisation=True))
    setups = unit_setups(sc)
    sup = build_supervisor(setups, None, substeps=sc.plant_substeps)
    result = simulate(sc, 0.3, setups)
    for u in result.units:
        grid = u.setup.effort_grid
        assert np.all(np.abs(u.tau) <= grid.top)
    assert verdict(result, sup)["saturated_periods"] > 100


# ---- the real-time sim backend -----------------------------------------------------------------


@pytest.mark.slow
def test_the_sim_backend_applies_and_logs_the_same_efforts(weak_current):
    """The loop against the simulated robot: the backend rounds and saturates the commands the
    supervisor let through, writes back what it applied, and the run equals the as-fast one."""
    sc = dataclasses.replace(weak_current, plant=Plant(current_quantisation=True))
    setups = unit_setups(sc)
    sup = build_supervisor(setups, None, substeps=sc.plant_substeps)
    periods = 300
    loop = RealTimeLoop(setups, SimBackend(setups, sc.period, sc.plant_substeps), sup,
                        sc.period, periods, realtime=False, substeps=sc.plant_substeps)
    assert loop.run().rule == "completed"
    looped = loop.result(sc)
    fast = simulate(sc, periods * sc.period, setups)
    for a, b in zip(fast.units, looped.units):
        for key in ("q", "qd", "tau", "errors", "p_hat"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=1e-12,
                                       err_msg=key)
        assert np.all(_on_grid(b.tau, a.setup.effort_grid.quantum)
                      | (np.abs(b.tau) == a.setup.effort_grid.bound))
    assert np.abs(looped.units[0].tau[:, 1]).max() == setups[0].effort_grid.bound[1]
