"""The plant has what a gearbox has (issue 24, item 1): backlash between rotor and link with the
encoder on the link, static friction above Coulomb (Stribeck), the bridge's current conversion
with its offset, and the Current Limit's saturation at the motor's torque."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import cochlea
from cochlea.dynamixel.control_table import MODELS
from cochlea.errors import DescriptionError
from cochlea.robots.motor_fit import bridge_compensates_friction
from cochlea.robots.plant import GEAR_DRIVE, gear_plant_step, plant_step
from cochlea.sim import load_scenario, simulate, unit_setups

H = 1e-3
Q0 = np.radians([73.0, 83.0, 110.0])
BETA = math.radians(0.33)
IA = 3.4e-3


@pytest.fixture(scope="module")
def arm():
    return cochlea.model("serial", parameterisation="inertial")


@pytest.fixture(scope="module")
def gear(arm):
    return gear_plant_step(arm, 1)


def drive(n, *, beta=BETA, k=1000.0, c=0.1, fc=0.0, ratio=1.0, vs=0.02, ia=IA):
    rows = [ia, beta, k, c, fc, ratio * fc, vs]
    assert len(rows) == len(GEAR_DRIVE)
    return np.concatenate([np.full(n, float(r)) for r in rows])


def advance(step, model, x, tau, periods, d, viscous=0.0):
    states = [np.array(x, float)]
    for _ in range(periods):
        states.append(np.array(step(states[-1], tau, model.p_nominal,
                                    np.full(model.nq, viscous), H, d)).ravel())
    return np.array(states)


def test_a_rotor_moving_inside_the_band_leaves_the_link_still(gear, arm):
    """Rotor 3 turns at 0.02 rad/s from the band's centre, no friction, no torque: the link
    (the horizontal arm: no gravity) does not move by a single bit until the teeth meet."""
    x0 = np.r_[Q0, 0, 0, 0, Q0, 0, 0, 0.02]
    states = advance(gear, arm, x0, np.zeros(3), 100, drive(3))
    inside = np.abs(states[:, 8] - states[:, 2]) < BETA / 2
    assert inside[:-1].all() and inside.sum() >= 100
    assert np.array_equal(states[:, :6], np.tile(x0[:6], (101, 1)))  # the link is still
    assert states[-1, 8] - Q0[2] == pytest.approx(0.02 * 0.1, rel=1e-12)


def test_the_teeth_meet_then_the_rotor_drives_the_link(gear, arm):
    """The same rotor, pushed on: past half the backlash it carries the link with it."""
    x0 = np.r_[Q0, 0, 0, 0, Q0, 0, 0, 0.0]
    states = advance(gear, arm, x0, np.array([0.0, 0.0, 0.02]), 200, drive(3))
    first = int(np.argmax(states[:, 2] != Q0[2]))
    gap = states[first - 1, 8] - states[first - 1, 2]
    assert 0 < first and gap <= BETA / 2 + 1e-12  # still inside the band just before
    assert states[-1, 5] > 0 and states[-1, 2] > Q0[2]


def test_a_link_hangs_free_inside_the_band():
    """The parallel mechanism under gravity, its rotors held by friction, the teeth centred:
    for a period the links fall as the rigid links with no torque at all (the rotors' inertia
    and friction do not reach them)."""
    m = cochlea.model("parallel", parameterisation="inertial")
    step = gear_plant_step(m, 1)
    q0 = np.array([2.478, 0.563, 0.07075, 0.663, 2.579])
    beta = np.array([BETA, BETA, 0.02 * BETA, BETA, BETA])  # the slider's through its pinion
    d = np.concatenate([np.full(5, IA), beta, np.full(5, 1e3), np.full(5, 0.1),
                        np.full(5, 50.0), np.full(5, 50.0), np.full(5, 0.02)])
    x0 = np.r_[q0, np.zeros(5), q0, np.zeros(5)]
    x1 = np.array(step(x0, np.zeros(5), m.p_nominal, np.zeros(5), H, d)).ravel()
    assert np.array_equal(x1[10:], x0[10:])  # the rotors stuck
    assert (np.abs(x1[:5] - x1[10:15]) < beta / 2).all()  # still inside the band
    free = np.array(m.forward_dynamics(q0, np.zeros(5), np.zeros(5))).ravel()
    np.testing.assert_allclose(x1[5:10], H * free, rtol=2e-3, atol=1e-9)


def energy(arm, x, d, n=3):
    q, v, th, w = x[:n], x[n:2 * n], x[2 * n:3 * n], x[3 * n:]
    ia, beta, k = d[:n], d[n:2 * n], d[2 * n:3 * n]
    gap = th - q
    dz = np.where(gap > beta / 2, gap - beta / 2, np.where(gap < -beta / 2, gap + beta / 2, 0))
    return 0.5 * v @ np.array(arm.M(q)) @ v + 0.5 * ia * w @ w + 0.5 * k * dz @ dz


@pytest.mark.slow
def test_the_engaged_gear_only_dissipates(gear, arm):
    """No motor torque, no friction: the links and rotors start engaged and moving against each
    other; the energy (kinetic + the gear's spring) never grows (to 1e-7 of it per period: the
    Coriolis terms are taken at each step's start) and the mesh damps it."""
    d = drive(3)
    x = np.r_[Q0, 0.5, -0.3, 1.0, Q0 + 0.004, -0.5, 0.3, -1.0]
    states = advance(gear, arm, x, np.zeros(3), 2000, d)
    e = np.array([energy(arm, s, d) for s in states])
    assert e.max() <= e[0] * (1 + 1e-9)
    assert (np.diff(e) <= 1e-7 * e[0]).all()
    assert e[-1] < 0.5 * e[0]


def test_without_backlash_a_stiff_gear_is_the_rigid_plant_with_armature(gear, arm):
    """Zero backlash, a stiff gear: the links move as the rigid plant with the armature."""
    rigid_model = cochlea.model("serial", parameterisation="inertial", actuators="armature")
    rigid = plant_step(rigid_model, 1)
    tau = np.array([0.05, -0.03, 0.01])
    x = np.r_[Q0, 0, 0, 0, Q0, 0, 0, 0]
    y = np.r_[Q0, 0, 0, 0]
    for _ in range(300):
        x = np.array(gear(x, tau, arm.p_nominal, np.zeros(3), H, drive(3, beta=0.0,
                                                                          k=1e5))).ravel()
        y = np.array(rigid(y, tau, rigid_model.p_nominal, np.zeros(3), H)).ravel()
    np.testing.assert_allclose(x[:6], y, rtol=0, atol=2e-4 * np.abs(y).max())


# --- Stribeck: static friction above Coulomb -------------------------------------------------


@pytest.mark.parametrize("ratio,moves", [(1.5, False), (1.0, True)])
def test_breakaway_from_rest_at_the_static_level_in_the_rigid_plant(arm, ratio, moves):
    """1.3x the Coulomb level from rest: held by static friction 1.5x Coulomb, moves with 1x."""
    step = plant_step(arm, 1, coulomb=True)
    fc = np.array([0.02, 0.015, 0.01])
    dry = np.concatenate([fc, ratio * fc, np.full(3, 0.02)])
    x = np.r_[Q0, 0, 0, 0]
    for _ in range(100):
        x = np.array(step(x, 1.3 * fc * [1, 0, 0], arm.p_nominal, np.zeros(3), H, dry)).ravel()
    assert bool(x[0] != Q0[0]) is moves


def test_a_sliding_joint_meets_the_coulomb_level_not_the_static_one(arm):
    """Once it slides (far above the Stribeck velocity), the joint brakes with Coulomb's level."""
    step = plant_step(arm, 1, coulomb=True)
    fc = np.array([0.02, 1.0, 1.0])  # joints 2 and 3 locked
    dry = np.concatenate([fc, 1.5 * fc, np.full(3, 0.02)])
    x = np.r_[Q0, 0.5, 0, 0]
    nxt = np.array(step(x, np.zeros(3), arm.p_nominal, np.zeros(3), H, dry)).ravel()
    m11 = float(np.array(arm.M(Q0))[0, 0])
    assert (x[3] - nxt[3]) / H == pytest.approx(fc[0] / m11, rel=1e-3)


@pytest.mark.parametrize("push,moves", [(1.4, False), (1.6, True)])
def test_breakaway_of_the_geared_rotor_at_the_static_level(gear, arm, push, moves):
    """The rotor inside its band, static friction 1.5x Coulomb: 1.4x Coulomb leaves it at rest,
    1.6x breaks it away."""
    fc = 0.2
    x = np.r_[Q0, 0, 0, 0, Q0, 0, 0, 0]
    tau = np.array([push * fc, 0, 0])
    states = advance(gear, arm, x, tau, 20, drive(3, fc=fc, ratio=1.5))
    assert bool(states[-1, 6] != Q0[0]) is moves


# --- Scenario keys ---------------------------------------------------------------------------


def scenario_with(tmp_path, name, lines):
    text = load_scenario(name).path.read_text()
    path = tmp_path / "s.toml"
    if "[plant]" in text:
        text = text.replace("[plant]", "[plant]\n" + "\n".join(lines), 1)
    else:
        text += "\n[plant]\n" + "\n".join(lines) + "\n"
    path.write_text(text)
    return path


@pytest.mark.parametrize("line,key", [
    ("backlash_SI = [nan, 0.0, 0.0]", "backlash_SI"),
    ("backlash_SI = [-0.001, 0.0, 0.0]", "backlash_SI"),
    ("backlash_SI = [0.2, 0.0, 0.0]", "backlash_SI"),
    ("gear_stiffness_SI = [0.0, 1.0, 1.0]", "gear_stiffness_SI"),
    ("static_friction_ratio = 0.9", "static_friction_ratio"),
    ("static_friction_ratio = nan", "static_friction_ratio"),
    ("stribeck_velocity_SI = [0.0, 0.02, 0.02]", "stribeck_velocity_SI"),
    ('bridge_offset = "yes"', "bridge_offset"),
])
def test_bad_gearbox_keys_are_refused(tmp_path, line, key):
    path = scenario_with(tmp_path, "serial_joint_realistic", [line])
    with pytest.raises(DescriptionError, match=f"plant.{key}"):
        load_scenario(path)


def test_gear_keys_need_the_gearbox(tmp_path):
    path = scenario_with(tmp_path, "serial_joint", ["backlash_SI = [0.001, 0.001, 0.001]"])
    with pytest.raises(DescriptionError, match="gearbox = true"):
        load_scenario(path)


@pytest.mark.slow
def test_the_realistic_preset_has_the_datasheets_gearbox():
    """0.33 deg on every MX-64 joint, the XM540-W270's 0.25 deg through the slider's pinion;
    static friction 1.5x Coulomb; the bridge's offset as the bridge would add it."""
    assert MODELS["MX-64"].gearbox.backlash_arcmin == 20.0
    assert MODELS["XM540-W270"].gearbox.backlash_arcmin == 15.0
    serial = unit_setups(load_scenario("serial_joint_realistic"))[0]
    rows = serial.drive.reshape(len(GEAR_DRIVE), -1)
    assert serial.gearbox and len(serial.plant_x0) == 12
    np.testing.assert_allclose(rows[1], math.radians(20 / 60))
    np.testing.assert_allclose(rows[5], 1.5 * rows[4])
    parallel = unit_setups(load_scenario("parallel_joint_realistic"))[0]
    rows = parallel.drive.reshape(len(GEAR_DRIVE), -1)
    np.testing.assert_allclose(rows[1], [math.radians(20 / 60)] * 2 + [0.02 * math.radians(
        15 / 60)] + [math.radians(20 / 60)] * 2)


# --- The bridge's current conversion ---------------------------------------------------------


def test_the_bridge_compensates_unless_the_controller_models_friction():
    assert bridge_compensates_friction("none") and bridge_compensates_friction("armature")
    assert not bridge_compensates_friction("all")


def with_plant(sc, **changes):
    return dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, **changes))


@pytest.mark.slow
def test_the_bridge_offset_follows_the_rule():
    """auto: no offset for the realistic studies (their controllers carry friction), the offset
    for a controller on the rigid links; true/false force it."""
    realistic = load_scenario("serial_joint_realistic")
    assert unit_setups(realistic)[0].effort_grid.offset is None
    forced = unit_setups(with_plant(realistic, bridge_offset=True))[0].effort_grid
    np.testing.assert_allclose(forced.offset, [0.1547, 0.237, 0.237], rtol=1e-3)
    thesis = load_scenario("serial_joint", plant_preset="realistic")
    assert thesis.controller_actuators == "none"
    assert unit_setups(thesis)[0].effort_grid.offset is not None
    assert unit_setups(with_plant(thesis, bridge_offset=False))[0].effort_grid.offset is None


def test_the_bridge_offset_adds_the_fit_offset_current():
    """What the plant gets for a command: tau + a I0 clip(tau / ramp, -1, 1), on whole current
    LSBs, saturated at the motor's torque a I_lim."""
    grid = unit_setups(with_plant(load_scenario("serial_joint_realistic"),
                                  bridge_offset=True))[0].effort_grid
    tau = np.array([0.5, -0.01, 0.0])
    applied = grid.apply(tau.copy())
    want = tau + grid.offset * np.clip(tau / grid.ramp, -1, 1)
    assert np.all(np.abs(applied - want) <= grid.quantum / 2 + 1e-15)
    assert applied[0] > tau[0] + 0.15 and applied[1] < tau[1] - 0.04 and applied[2] == 0.0


def test_current_saturation_is_the_motors_torque_once_the_plant_has_the_friction():
    """The realistic plant carries the gearbox's friction, so the Current Limit saturates the
    motor's torque a I_lim; a plant without the description's friction keeps the fit's net
    effort (a I_lim + b)."""
    from cochlea.robots.motor_fit import Fit, current_limit_lsb

    sc = load_scenario("serial_joint_realistic")
    grid = unit_setups(sc)[0].effort_grid
    from cochlea.robots import robot

    joint = robot("serial").actuated_joints(sc.system)[0]
    motor = joint.motor
    fit = Fit.from_description(motor.fit)
    lsb = current_limit_lsb(motor, MODELS["MX-64"], fit, joint.effort_limit, joint.ratio)
    assert grid.saturation[0] == pytest.approx(fit.a * lsb * 3.36e-3)
    net = unit_setups(with_plant(sc, friction_from_description=False))[0].effort_grid
    assert net.saturation[0] == pytest.approx(fit.a * lsb * 3.36e-3 + fit.b)
    # With the bridge's offset a command at the limit (2.5 N m) gets the offset on top, within
    # the motor's saturation; anything past the Current Limit is cut there.
    offset = unit_setups(with_plant(sc, bridge_offset=True))[0].effort_grid
    at_limit = offset.apply(np.full(3, 2.5))[0]
    assert 2.5 + 0.1547 - offset.quantum[0] / 2 <= at_limit <= offset.saturation[0]
    assert offset.apply(np.full(3, 10.0))[0] == pytest.approx(offset.saturation[0])


@pytest.mark.slow
def test_double_compensation_shows(tmp_path):
    """A friction-compensating controller (actuators = "all") on a plant that also gets the
    bridge's offset: the efforts the motors apply differ from the commands by the offset."""
    sc = load_scenario("serial_joint_realistic")
    once = simulate(sc, 0.3, kernels="casadi")
    twice = simulate(with_plant(sc, bridge_offset=True), 0.3, kernels="casadi")
    assert not np.allclose(once.units[0].q, twice.units[0].q, rtol=0, atol=1e-6)


# --- The same plant in C, in the loops and in the sim backend --------------------------------


REALISTIC = ["serial_joint_realistic", "serial_task_realistic", "parallel_joint_realistic",
             "parallel_task_realistic"]


@pytest.mark.parametrize("offset", ["auto", True], ids=["auto", "offset"])
@pytest.mark.parametrize("name", REALISTIC)
@pytest.mark.slow
def test_the_c_loops_equal_casadi_on_the_geared_plant(name, offset):
    """The realistic studies on the geared plant (with the bridge's offset forced, too): the C
    driver and the Python loop over the C kernels give the CasADi reference's log."""
    import warnings

    from cochlea.kernels import library
    from cochlea.sim import CKernelsWarning
    from cochlea.sim.compiled import simulate_compiled, unit_kernels

    sc = with_plant(load_scenario(name), bridge_offset=offset)
    setups = unit_setups(sc)
    assert unit_kernels(library.load(), setups[0], 1).closed_loop.endswith("_closed_loop_gear")
    reference = simulate(sc, 0.6, setups, kernels="casadi")
    with warnings.catch_warnings():
        warnings.simplefilter("error", CKernelsWarning)
        for loop in ("c", "python"):
            result = simulate_compiled(sc, 0.6, setups, loop=loop)
            for a, b in zip(reference.units, result.units):
                for key in ("q", "qd", "tau", "errors", "p_hat", "true_q", "true_qd"):
                    np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=1e-12,
                                               atol=1e-12, err_msg=f"{loop} {a.name}.{key}")


@pytest.mark.slow
def test_the_sim_backend_runs_the_geared_plant():
    """The real-time loop back to back against SimBackend: the same commands as the as-fast
    run, on the C gear plant, measuring the link's [q, qd]."""
    from cochlea.runtime import RealTimeLoop, build_supervisor
    from cochlea.runtime.sim_backend import SimBackend

    sc = load_scenario("parallel_joint_realistic")
    setups = unit_setups(sc)
    periods = 300
    backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=periods)
    assert [f.kernel.name for f in backend._steps] == ["parallel_gear_plant_step"]
    loop = RealTimeLoop(setups, backend, build_supervisor(setups, None,
                                                          substeps=sc.plant_substeps),
                        sc.period, periods, realtime=False, substeps=sc.plant_substeps)
    assert loop.run().rule == "completed"
    looped, fast = loop.result(sc), simulate(sc, periods * sc.period, setups)
    for a, b in zip(fast.units, looped.units):
        for key in ("tau", "errors", "p_hat"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=1e-12,
                                       err_msg=f"{a.name}.{key}")


def test_the_emulated_motor_gives_a_I_where_the_plant_carries_the_friction():
    """The emulator's motors: the fit's net torque a I + b on a frictionless plant, the motor's
    own torque a I where the plant subtracts the gearbox's friction (the realistic preset)."""
    from cochlea.dynamixel.drives import joint_drives

    drive = joint_drives("serial")[0]
    lsb = 300.0
    amps = lsb * drive.spec.current_unit_mA * 1e-3
    assert drive.effort(lsb, slope_only=True) * drive.torque_per_effort == \
        pytest.approx(drive.fit.a * amps)
    assert drive.effort(lsb) * drive.torque_per_effort == pytest.approx(drive.fit.a * amps
                                                                        + drive.fit.b)
