"""Three plant disturbances of issue 24's "everything at once" case (item 2), each a [plant] key,
default off: a delay that jitters between whole periods (``delay_jitter_periods``), encoder
noise in whole counts (``encoder_noise_counts``) and a torque-constant error
(``torque_constant_error``). Each changes what it should, and the C loops give the CasADi
reference's log with all three on."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from cochlea.errors import DescriptionError
from cochlea.sim import CKernelsWarning, load_scenario, simulate, unit_setups
from cochlea.sim import compiled as csim
from cochlea.sim.scenario import PLANT_PRESETS, Plant
from cochlea.sim.setup import delay_ages, quantise

REALISTIC = ["serial_joint_realistic", "serial_task_realistic", "parallel_joint_realistic",
             "parallel_task_realistic"]
#: Issue 24's values: delay 1..3 periods, +-1 count, a 5 % torque-constant error.
EVERYTHING = dict(delay_periods=1, delay_jitter_periods=2, encoder_noise_counts=1,
                  torque_constant_error=0.05)
FIELDS = ("q", "qd", "tau", "errors", "p_hat", "true_q", "true_qd", "pose", "desired")


def with_plant(sc, **changes):
    """``sc`` with its plant's keys changed; a scalar torque-constant error for every joint, as
    the scenario file's one number gives it."""
    e = changes.get("torque_constant_error")
    if e is not None:
        nq = 3 if sc.robot == "serial" else 5  # joints of a unit
        changes["torque_constant_error"] = np.broadcast_to(np.asarray(e, float), (nq,)).copy()
    return dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, **changes))


def scenario_with(tmp_path, name, lines):
    text = load_scenario(name).path.read_text()
    path = tmp_path / "s.toml"
    if "[plant]" in text:
        text = text.replace("[plant]", "[plant]\n" + "\n".join(lines), 1)
    else:
        text += "\n[plant]\n" + "\n".join(lines) + "\n"
    path.write_text(text)
    return path


# --- The keys --------------------------------------------------------------------------------


@pytest.mark.parametrize("line,key", [
    ("delay_jitter_periods = -1", "delay_jitter_periods"),
    ("delay_jitter_periods = 1.5", "delay_jitter_periods"),
    ("delay_jitter_periods = nan", "delay_jitter_periods"),
    ("delay_jitter_periods = true", "delay_jitter_periods"),
    ("delay_jitter_periods = 1001", "delay_jitter_periods"),
    ("delay_jitter_periods = 1000", "delay_jitter_periods"),  # with the preset's 1 period
    ("encoder_noise_counts = -1", "encoder_noise_counts"),
    ("encoder_noise_counts = 0.5", "encoder_noise_counts"),
    ("encoder_noise_counts = nan", "encoder_noise_counts"),
    ("encoder_noise_counts = 1001", "encoder_noise_counts"),
    ("torque_constant_error = nan", "torque_constant_error"),
    ("torque_constant_error = inf", "torque_constant_error"),
    ("torque_constant_error = 0.51", "torque_constant_error"),
    ("torque_constant_error = -0.6", "torque_constant_error"),
    ("torque_constant_error = [0.05, 0.05]", "torque_constant_error"),
    ("torque_constant_error = [0.05, nan, 0.05]", "torque_constant_error"),
    ("torque_constant_error = [0.05, 0.7, 0.05]", "torque_constant_error"),
    ('torque_constant_error = "5 %"', "torque_constant_error"),
])
def test_bad_disturbance_keys_are_refused_with_file_and_key(tmp_path, line, key):
    path = scenario_with(tmp_path, "serial_joint_realistic", [line])
    with pytest.raises(DescriptionError, match=f"plant.{key}") as caught:
        load_scenario(path)
    assert str(path) in str(caught.value)


def test_encoder_noise_needs_the_encoder_grid(tmp_path):
    path = scenario_with(tmp_path, "serial_joint", ["encoder_noise_counts = 1"])
    with pytest.raises(DescriptionError, match="position_encoder = true"):
        load_scenario(path)
    path = scenario_with(tmp_path, "serial_joint", ["encoder_noise_counts = 1",
                                                    "position_encoder = true"])
    assert load_scenario(path).plant.encoder_noise_counts == 1


def test_the_keys_read_as_written(tmp_path):
    sc = load_scenario(scenario_with(tmp_path, "serial_joint_realistic", [
        "delay_jitter_periods = 2", "encoder_noise_counts = 1", "torque_constant_error = 0.05"]))
    assert (sc.plant.delay_periods, sc.plant.delay_jitter_periods) == (1, 2)
    assert sc.plant.encoder_noise_counts == 1
    np.testing.assert_array_equal(sc.plant.torque_constant_error, [0.05] * 3)
    sc = load_scenario(scenario_with(tmp_path, "parallel_joint_realistic", [
        "torque_constant_error = [0.05, -0.05, 0.0, 0.1, -0.5]"]))
    np.testing.assert_array_equal(sc.plant.torque_constant_error, [0.05, -0.05, 0, 0.1, -0.5])
    np.testing.assert_array_equal(unit_setups(sc, gravity=False)[0].torque_scale,
                                  [1.05, 0.95, 1.0, 1.1, 0.5])


@pytest.mark.slow
def test_default_off_and_the_realistic_preset_unchanged():
    """Every shipped study loads with the three off; the realistic preset does not set them
    (the realistic studies set them in their own files)."""
    for key in ("delay_jitter_periods", "encoder_noise_counts", "torque_constant_error"):
        assert key not in PLANT_PRESETS["realistic"]
    assert (Plant().delay_jitter_periods, Plant().encoder_noise_counts,
            Plant().torque_constant_error) == (0, 0, None)
    for name in REALISTIC + ["serial_joint", "parallel_task"]:
        sc = load_scenario(name)
        assert sc.plant.delay_jitter_periods == sc.plant.encoder_noise_counts == 0
        assert sc.plant.torque_constant_error is None
        assert all(u.torque_scale is None for u in unit_setups(sc))


@pytest.mark.parametrize("kernels", ["c", "casadi"])
@pytest.mark.slow
def test_zero_disturbances_give_todays_log_bit_for_bit(kernels):
    sc = load_scenario("serial_joint_realistic")
    today = simulate(sc, 0.3, kernels=kernels)
    zeros = simulate(with_plant(sc, delay_jitter_periods=0, encoder_noise_counts=0,
                                torque_constant_error=0.0), 0.3, kernels=kernels)
    for a, b in zip(today.units, zeros.units):
        for key in FIELDS:
            np.testing.assert_array_equal(getattr(b, key), getattr(a, key), err_msg=key)


# --- Each effect -----------------------------------------------------------------------------


def _ages(unit, rows_from=4):
    """Per period from ``rows_from`` on, how many periods old the logged measurement is: the
    age a with measured [q, qd] equal to the true state of period k - a (exactly)."""
    seen = np.hstack([unit.q, unit.qd])
    true = np.hstack([unit.true_q, unit.true_qd])
    ages = []
    for k in range(rows_from, len(seen)):
        match = [a for a in range(0, rows_from + 1) if np.array_equal(seen[k], true[k - a])]
        assert len(match) == 1, (k, match)
        ages.append(match[0])
    return np.array(ages)


@pytest.mark.parametrize("kernels", ["c", "casadi"])
@pytest.mark.slow
def test_the_delay_jitters_between_whole_periods(kernels):
    """delay_periods 1, delay_jitter_periods 2: each period measures the state 1, 2 or 3
    periods old, about a third each, as drawn from the seed (the same draws in every unit:
    the system is read at once); without jitter every period is 1 period old."""
    sc = with_plant(load_scenario("serial_joint"), delay_periods=1, delay_jitter_periods=2,
                    seed=5)
    result = simulate(sc, 1.0, kernels=kernels)
    drawn = delay_ages(sc.plant, 1000)
    assert set(np.unique(drawn)) == {1, 2, 3}
    for u in result.units:
        ages = _ages(u)
        np.testing.assert_array_equal(ages, drawn[4:])
        share = np.bincount(ages, minlength=4)[1:] / len(ages)
        assert np.all((share > 0.28) & (share < 0.39)), share
    steady = simulate(with_plant(sc, delay_jitter_periods=0), 0.3, kernels=kernels)
    assert set(_ages(steady.units[0])) == {1}
    other = delay_ages(dataclasses.replace(sc.plant, seed=6), 1000)
    assert not np.array_equal(other, drawn)  # from the seed


@pytest.mark.slow
def test_the_jitter_leaves_the_gaussian_noise_as_it_was():
    """The jitter has its own stream of the seed: a noisy run's noise is the same numbers with
    and without it (measured minus the true state it measured)."""
    sc = with_plant(load_scenario("serial_joint"), delay_periods=1, noise_q_std=1e-4,
                    noise_qd_std=1e-3, seed=3)
    plain = simulate(sc, 0.3, kernels="casadi")
    jittered = simulate(with_plant(sc, delay_jitter_periods=2), 0.3, kernels="casadi")
    ages = delay_ages(jittered.scenario.plant, 300)
    k = np.arange(300)
    for a, b in zip(plain.units, jittered.units):
        true_a = np.hstack([a.true_q, a.true_qd])
        true_b = np.hstack([b.true_q, b.true_qd])
        noise_a = np.hstack([a.q, a.qd]) - true_a[np.maximum(k - 1, 0)]
        noise_b = np.hstack([b.q, b.qd]) - true_b[np.maximum(k - ages, 0)]
        np.testing.assert_allclose(noise_b, noise_a, rtol=0, atol=1e-15)
        assert np.abs(noise_a[:, :3]).max() > 1e-5


@pytest.mark.parametrize("counts", [1, 2])
@pytest.mark.parametrize("kernels", ["c", "casadi"])
@pytest.mark.slow
def test_encoder_noise_is_whole_counts_on_the_grid(kernels, counts):
    """encoder_noise_counts N: each joint's measured position is the encoder's reading of its
    true position off by an integer in -N..N counts, every value about equally often,
    independently per joint; still on the grid; the velocities untouched."""
    sc = with_plant(load_scenario("serial_joint"), position_encoder=True,
                    encoder_noise_counts=counts, seed=2)
    result = simulate(sc, 1.0, kernels=kernels)
    for u in result.units:
        n = u.setup.controller_model.nq
        quantum, offset = u.setup.quantum[:n], u.setup.grid_offset[:n]
        clean = quantise(u.true_q, quantum, offset)
        off = (u.q - clean) / quantum
        np.testing.assert_allclose(off, np.rint(off), rtol=0, atol=1e-6)  # whole counts
        off = np.rint(off).astype(int)
        assert off.min() == -counts and off.max() == counts
        share = np.bincount((off + counts).ravel()) / off.size
        assert np.all(np.abs(share - 1 / (2 * counts + 1)) < 0.05), share
        assert not np.array_equal(off[:, 0], off[:, 1])  # per joint
        on_grid = (u.q - offset) / quantum
        np.testing.assert_allclose(on_grid, np.rint(on_grid), rtol=0, atol=1e-6)
        np.testing.assert_array_equal(u.qd, u.true_qd)
    plain = simulate(with_plant(sc, encoder_noise_counts=0), 0.2, kernels=kernels)
    u = plain.units[0]
    n = u.setup.controller_model.nq
    np.testing.assert_array_equal(u.q, quantise(u.true_q, u.setup.quantum[:n],
                                                u.setup.grid_offset[:n]))


def _replayed(u, sc, scale):
    """Each logged period's next true state from the plant's own step under the logged
    applied effort times ``scale`` (the rigid plant: its state is the logged [q, qd])."""
    step = u.setup.plant_function(sc.plant_substeps)
    numbers = [u.setup.plant_params, u.setup.friction, sc.period]
    numbers += [] if u.setup.drive is None else [u.setup.drive]
    x = np.hstack([u.true_q, u.true_qd])
    return x, np.array([np.array(step(x[k], scale * u.tau[k], *numbers)).ravel()
                        for k in range(len(x) - 1)])


@pytest.mark.parametrize("kernels", ["c", "casadi"])
def test_the_plant_gets_the_torque_constant_error(kernels):
    """torque_constant_error e: the plant integrates (1 + e) times the applied effort the log
    holds (what the bridge believes it applied), per joint; e = 0 gives the effort itself."""
    sc = load_scenario("serial_joint")
    error = np.array([0.2, -0.1, 0.05])
    result = simulate(with_plant(sc, torque_constant_error=error), 0.1, kernels=kernels)
    for u in result.units:
        x, replayed = _replayed(u, sc, 1 + error)
        np.testing.assert_allclose(x[1:], replayed, rtol=1e-12, atol=1e-14)
        _, nominal = _replayed(u, sc, np.ones(3))
        assert np.abs(x[1:] - nominal).max() > 1e-9  # the error is felt


@pytest.mark.parametrize("kernels", ["c", "casadi"])
@pytest.mark.slow
def test_the_torque_at_the_current_limit_scales_too(kernels):
    """With the drives' rounding and saturation (current_quantisation): the log holds the
    applied effort on the effort grid, up to the largest the drive gives; the plant gets
    (1 + e) times it, beyond that where e > 0 (the Current Limit bounds the current, not the
    torque)."""
    sc = with_plant(load_scenario("serial_joint_realistic"), gearbox=False,
                    static_friction_ratio=1.0, current_quantisation=True,
                    torque_constant_error=0.05)
    result = simulate(sc, 0.1, kernels=kernels)
    saturated = 0
    for u in result.units:
        grid = u.setup.effort_grid
        saturated += int((np.abs(u.tau) == grid.top).sum())  # the largest the drive gives
        steps = u.tau / grid.quantum
        assert np.all(np.isclose(steps, np.rint(steps), rtol=0, atol=1e-9)
                      | (np.abs(u.tau) == grid.bound))
        x, replayed = _replayed(u, sc, np.full(3, 1.05))
        np.testing.assert_allclose(x[1:], replayed, rtol=1e-12, atol=1e-14)
    assert saturated > 0  # the start-up saturates: those periods' torque is 1.05 x the bound


# --- All three at once: C equals CasADi ------------------------------------------------------


@pytest.mark.parametrize("name", REALISTIC)
@pytest.mark.slow
def test_the_c_loops_equal_casadi_with_everything_at_once(name):
    """The realistic studies on the geared plant with issue 24's values (delay 1..3 periods,
    +-1 count, 5 % torque-constant error) and Gaussian noise on top: the C driver and the
    Python loop over the C kernels give the CasADi reference's log."""
    sc = with_plant(load_scenario(name), **EVERYTHING, noise_q_std=1e-5, noise_qd_std=1e-3,
                    seed=8)
    setups = unit_setups(sc)
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    with warnings.catch_warnings():
        warnings.simplefilter("error", CKernelsWarning)
        for loop in csim.LOOPS:
            result = csim.simulate_compiled(sc, 0.5, setups, loop=loop)
            for a, b in zip(reference.units, result.units):
                for key in FIELDS:
                    np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=1e-12,
                                               atol=1e-12, err_msg=f"{loop} {a.name}.{key}")
    u = reference.units[0]
    assert not np.array_equal(u.q, u.true_q)


def test_a_weaker_motor_that_cannot_hold_gravity_is_refused():
    """The gravity check before a run counts the torque-constant error: parallel_joint's
    heaviest-loaded joint needs 0.6 of its effort limit at the start; with e = -0.45 its motor
    gives 0.55 of it, and the run is refused; with e = -0.35 it still holds."""
    from cochlea.sim import GravityRefused

    sc = load_scenario("parallel_joint")
    unit_setups(with_plant(sc, torque_constant_error=-0.35))
    with pytest.raises(GravityRefused, match="torque_constant_error"):
        unit_setups(with_plant(sc, torque_constant_error=-0.45))


def test_a_sweep_varies_the_disturbances(tmp_path):
    """cochlea-sweep may vary the three keys (the loader's bounds); each sample's scenario
    file loads with them."""
    from cochlea.sweep import sampling
    from cochlea.sweep import spec as sweep_spec

    path = tmp_path / "spec.toml"
    path.write_text('format = "cochlea-sweep/1"\nscenario = "serial_joint_realistic"\n'
                    "samples = 3\nseed = 4\nduration_s = 0.2\n\n[perturb]\n"
                    "delay_jitter_periods = {choice = [0, 2]}\n"
                    "encoder_noise_counts = {choice = [1]}\n"
                    "torque_constant_error = {uniform = [-0.05, 0.05]}\n")
    spec = sweep_spec.load(path)
    for i in range(3):
        sample = tmp_path / f"sample{i}.toml"
        sample.write_text(sampling.scenario_text(spec, i))
        plant = load_scenario(sample).plant
        assert plant.encoder_noise_counts == 1 and plant.delay_jitter_periods in (0, 2)
        e = plant.torque_constant_error
        assert e.shape == (3,) and np.all(np.abs(e) <= 0.05) and len(set(e)) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text(path.read_text().replace("[-0.05, 0.05]", "[-0.05, 0.7]"))
    with pytest.raises(DescriptionError, match="torque_constant_error"):
        sweep_spec.load(bad)


@pytest.mark.slow
def test_the_emulated_motors_have_the_torque_constant_error(tmp_path):
    """cochlea-emulator on a scenario with torque_constant_error: each virtual motor gives
    1 + e times the torque its current gives without it (Present Current unchanged)."""
    from cochlea.dynamixel.control_table import CURRENT_MODE
    from cochlea.dynamixel.emulator import VirtualChain

    path = scenario_with(tmp_path, "serial_joint_realistic",
                         ["torque_constant_error = [0.05, -0.05, 0.1]"])
    chain = VirtualChain("serial", path)
    plain = VirtualChain("serial", load_scenario("serial_joint_realistic").path)
    assert [m.torque_scale for m in chain.motors] == [1.05, 0.95, 1.1] * 2
    assert {m.torque_scale for m in plain.motors} == {1.0}
    for m, p in zip(chain.motors, plain.motors):
        for motor in (m, p):  # torque on, current mode, a Goal Current of 300 LSB
            motor.table[64], motor.table[11] = 1, CURRENT_MODE
            motor.table[102:104] = (300).to_bytes(2, "little", signed=True)
            motor._key = ()
        assert m.state()[:2] == p.state()[:2] == (True, 300)
        assert m.state()[2] == pytest.approx(m.torque_scale * p.state()[2], rel=1e-15)
