"""The simulation on the C kernels gives the CasADi reference's log to 1e-10, for every scenario
in models/scenarios/, through the all-in-C loop and the Python loop over ctypes kernels."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest

import cochlea.sim
from cochlea import load_serial
from cochlea.errors import CochleaError
from cochlea.kernels import library as ckernels
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.sim import compiled as csim
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim.scenario import Plant
from cochlea.sim.setup import measurements
from tests.conftest import assert_periods_allocate_nothing

ROOT = Path(__file__).resolve().parent.parent

#: The generated C covers every shipped study, the realistic ones (the controller estimating
#: its drives' armature and friction, the plant with armature and sticking friction) included.
SCENARIOS = sorted(p.stem for p in SCENARIOS_DIR.glob("*.toml"))
#: The thesis's variants exist in C for the rigid-link controllers only.
RIGID = [name for name in SCENARIOS if load_scenario(name).controller_actuators == "none"]
FIELDS = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose", "true_q",
          "true_qd", "true_x")
DURATION = 1.5  # s: short, to keep the suite fast (the benchmark runs full length)


@pytest.fixture(scope="module", autouse=True)
def library():
    subprocess.run(["make", "-s", "lib"], cwd=ROOT, check=True, capture_output=True)


def assert_same_log(result, reference, tol=1e-10, rows=None):
    """Every logged array equal to ``tol`` (relative and absolute); ``rows`` limits the
    comparison to the first rows (a diverging run's last rows grow past 1e100, where any two
    correct evaluations part ways)."""
    assert np.array_equal(result.time, reference.time)
    assert result.diverged == reference.diverged
    assert [u.name for u in result.units] == [u.name for u in reference.units]
    for u, r in zip(result.units, reference.units):
        for key in FIELDS:
            a, b = getattr(u, key), getattr(r, key)
            assert a.shape == b.shape, (u.name, key)
            np.testing.assert_allclose(a[:rows], b[:rows], rtol=tol, atol=tol,
                                       err_msg=f"{u.name}.{key}")


@pytest.fixture(scope="module")
def references():
    runs = {}
    for name in SCENARIOS:
        sc = load_scenario(name)
        setups = unit_setups(sc)
        runs[name] = (sc, setups, simulate(sc, DURATION, setups, kernels="casadi"))
    return runs


def test_every_scenario_is_covered():
    assert {"serial_joint", "serial_task", "parallel_task_realistic"} <= set(SCENARIOS)
    assert {"serial_joint", "parallel_task"} <= set(RIGID)


@pytest.mark.parametrize("name", ["serial_task_realistic", "parallel_joint_realistic"])
@pytest.mark.slow
def test_the_realistic_studies_run_the_actuated_kernels(name):
    """Controller with the drives modelled, plant with their rotors behind geared drives (the
    gearbox with backlash and dry friction); without the gearbox, the rigid links with their
    armature and dry friction."""
    sc = load_scenario(name)
    lib = ckernels.load()
    for u in unit_setups(sc):
        names = csim.unit_kernels(lib, u, sc.plant_substeps)
        assert names.step.endswith(f"_{sc.controller}_actuated_step")
        assert names.plant.endswith("_gear_plant_step")
        assert names.closed_loop.endswith("_actuated_closed_loop_gear")
        assert lib.manifest["kernels"][names.step]["actuators"] == "all"
        assert lib.manifest["closed_loops"][names.closed_loop]["nx"] == 4 * u.plant_model.nq
    rigid = dataclasses.replace(sc, plant=dataclasses.replace(sc.plant, gearbox=False))
    for u in unit_setups(rigid):
        names = csim.unit_kernels(lib, u, sc.plant_substeps)
        assert names.plant.endswith("_armature_plant_step_coulomb")
        assert names.closed_loop.endswith("_actuated_closed_loop_armature_coulomb")
        assert lib.manifest["kernels"][names.plant]["actuators"] == "armature"


@pytest.mark.slow
def test_controllers_outside_the_catalogue_fall_back_to_casadi_with_a_warning():
    """The thesis's law with the drives modelled, and a model with the armature alone, are not
    generated: they run on CasADi, with a warning naming the missing kernel."""
    realistic = load_scenario("serial_joint_realistic")
    for sc in (dataclasses.replace(realistic, variant="thesis"),
               dataclasses.replace(realistic, controller_actuators="armature")):
        with pytest.raises(csim.CKernelsUnavailable, match="has no kernel serial_arm1_e"):
            csim.simulate_compiled(sc, 0.01)
        with pytest.warns(csim.CKernelsWarning, match="on the CasADi kernels"):
            fallback = csim.simulate_compiled(sc, 0.01, fallback=True)
        assert len(fallback.time) == 10


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_c_kernels_give_the_reference_log(references, name, loop):
    sc, setups, reference = references[name]
    result = csim.simulate_compiled(sc, DURATION, setups, loop=loop)  # no fallback: C or fail
    assert_same_log(result, reference)
    assert len(result.time) == round(DURATION * sc.rate_hz)


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("name", RIGID)
@pytest.mark.slow
def test_thesis_variants_run_on_the_c_kernels(name, loop):
    """The printed thesis's laws by name, though the C of a law that computes what the corrected
    one does is that law's (serial_arm*_e_thesis_step and its driver are aliases): the source
    hashes still check, and the log is the reference's up to a divergence (the printed task-space
    law of the parallel mechanism blows up within 0.2 s: it drives the pantographs into their
    singular pose, where a difference in the last bit grows from 1e-16 to 1e-6 within five
    periods, its velocities from 30 to 4000 rad/s, and an ulp by 1e5 a period after that; the
    differences come from the plant's constants folded into the reference's fused graph and
    from the C plant's inline sin and cos, libm's only within an ulp (docs/codegen.md). So the
    rows are compared while every value is below 1e3)."""
    sc = dataclasses.replace(load_scenario(name), variant="thesis")
    setups = unit_setups(sc)
    if name == "serial_joint":
        lib = ckernels.load()
        for u in setups:
            names = csim.unit_kernels(lib, u, sc.plant_substeps)
            assert lib.symbol(names.step) == "serial_arm1_e_step"
            assert lib.manifest["closed_loops"][names.closed_loop]["symbol"] != names.closed_loop
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    result = csim.simulate_compiled(sc, 0.5, setups, loop=loop)
    wild = [np.abs(getattr(u, key)).max(axis=1) > 1e3 for u in reference.units for key in FIELDS]
    tame = min(int(np.argmax(w)) if w.any() else len(w) for w in wild)
    assert tame >= 100
    assert_same_log(result, reference, rows=tame)


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_default_kernels_are_c(references, name, monkeypatch):
    sc, setups, reference = references[name]
    calls = []
    real = csim.simulate_compiled
    monkeypatch.setattr(cochlea.sim, "simulate_compiled",
                        lambda *a, **k: calls.append(k) or real(*a, **k))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no fallback to CasADi
        result = simulate(sc, DURATION, setups)
    assert calls == [{"fallback": True, "threads": True, "library": None}]
    assert result.kernels["used"] == "c" and result.kernels["requested"] == "auto"
    assert_same_log(result, reference)


@pytest.mark.parametrize("loop", csim.LOOPS)
def test_noise_delay_and_friction_match(loop):
    sc = load_scenario("serial_joint")
    sc = dataclasses.replace(sc, plant=Plant(noise_q_std=1e-3, noise_qd_std=1e-2,
                                             delay_periods=3, viscous_friction=np.full(3, 1e-3),
                                             mass_scale=np.full(3, 1.2), payload_kg=0.01,
                                             seed=11))
    setups = unit_setups(sc)
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    assert_same_log(csim.simulate_compiled(sc, 0.5, setups, loop=loop), reference)


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("name", ["serial_task", "parallel_joint"])
@pytest.mark.slow
def test_coulomb_friction_runs_in_c(name, loop):
    """A plant with dry friction runs on ``<unit>_plant_step_coulomb`` and its driver
    ``*_closed_loop_coulomb``, not on the CasADi fallback, and gives the reference's log."""
    sc = load_scenario(name)
    n = 3 if sc.robot == "serial" else 5
    sc = dataclasses.replace(sc, plant=Plant(coulomb_friction=np.linspace(0.01, 0.03, n),
                                             viscous_friction=np.full(n, 1e-3)))
    setups = unit_setups(sc)
    lib = ckernels.load()
    for u in setups:
        names = csim.unit_kernels(lib, u, sc.plant_substeps)
        assert names.plant.endswith("_plant_step_coulomb")
        assert names.closed_loop.endswith("_closed_loop_coulomb")
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    assert_same_log(csim.simulate_compiled(sc, 0.5, setups, loop=loop), reference)


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.slow
def test_every_plant_option_at_once_matches(name, loop):
    """Dry friction, both measurement grids, current quantisation, delay and noise together,
    with the delay jittering, whole encoder counts of noise and a torque-constant error: the C
    loops give the reference's log (and the applied efforts sit on the effort grid)."""
    sc = load_scenario(name)
    n = 3 if sc.robot == "serial" else 5
    sc = dataclasses.replace(sc, plant=Plant(
        coulomb_friction=np.full(n, 0.01), viscous_friction=np.full(n, 1e-3),
        position_encoder=True, velocity_register=True, current_quantisation=True,
        delay_periods=2, noise_q_std=1e-4, noise_qd_std=1e-3, seed=5,
        delay_jitter_periods=1, encoder_noise_counts=1,
        torque_constant_error=np.linspace(-0.05, 0.05, n),
        armature=sc.plant.armature))  # the realistic gains are for a plant with its rotors
    setups = unit_setups(sc)
    reference = simulate(sc, 0.5, setups, kernels="casadi")
    assert_same_log(csim.simulate_compiled(sc, 0.5, setups, loop=loop), reference)
    for u in reference.units:
        grid = u.setup.effort_grid
        steps = u.tau / grid.quantum
        on_grid = np.isclose(steps, np.rint(steps), rtol=0, atol=1e-9)
        assert np.all(on_grid | (np.abs(u.tau) == grid.bound))


#: The plant options a real-time run on the sim backend must reproduce: the grids and a delay,
#: then everything at once (noise, dry friction and current quantisation too).
MEASURED = {
    "grids+delay": dict(position_encoder=True, velocity_register=True, delay_periods=2),
    "everything": dict(position_encoder=True, velocity_register=True, delay_periods=2,
                       noise_q_std=1e-4, noise_qd_std=1e-3, seed=9, current_quantisation=True,
                       coulomb=0.01),
    "disturbances": dict(position_encoder=True, velocity_register=True, delay_periods=1,
                         delay_jitter_periods=2, encoder_noise_counts=1, noise_q_std=1e-4,
                         noise_qd_std=1e-3, seed=9, current_quantisation=True, coulomb=0.01,
                         torque_constant_error=0.05),
}


@pytest.mark.parametrize("options", MEASURED, ids=list(MEASURED))
@pytest.mark.parametrize("name", ["serial_joint", "parallel_task"])
def test_the_sim_backend_measures_as_the_as_fast_run(name, options):
    """The real-time loop (run back to back) against SimBackend over N periods sees, commands
    and estimates exactly what the as-fast run does; both logs hold the measurement (the true
    state `delay` periods before, or each period's jittering delay, noisy, put on the grid) as
    q and qd, and the plant's state as true_q and true_qd."""
    from cochlea.runtime import RealTimeLoop, build_supervisor
    from cochlea.runtime.sim_backend import SimBackend
    from cochlea.sim.setup import delay_ages, quantise

    sc = load_scenario(name)
    n = 3 if sc.robot == "serial" else 5
    plant = dict(MEASURED[options])
    coulomb = plant.pop("coulomb", None)
    if "torque_constant_error" in plant:
        plant["torque_constant_error"] = np.full(n, plant["torque_constant_error"])
    sc = dataclasses.replace(sc, plant=Plant(**plant, coulomb_friction=None if coulomb is None
                                             else np.full(n, coulomb)))
    setups = unit_setups(sc)
    periods = 400
    backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=periods)
    loop = RealTimeLoop(setups, backend, build_supervisor(setups, None,
                                                          substeps=sc.plant_substeps),
                        sc.period, periods, realtime=False, substeps=sc.plant_substeps)
    assert loop.run().rule == "completed"
    looped = loop.result(sc)
    fast = simulate(sc, periods * sc.period, setups)
    ages = delay_ages(sc.plant, periods)
    delay = sc.plant.delay_periods if ages is None else ages
    for a, b in zip(fast.units, looped.units):
        for key in ("tau", "errors", "p_hat", "desired"):
            np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=0, atol=1e-12,
                                       err_msg=f"{a.name}.{key}")
        state = np.hstack([a.true_q, a.true_qd])
        np.testing.assert_allclose(np.hstack([b.true_q, b.true_qd]), state, rtol=0, atol=1e-12)
        true = state[np.maximum(np.arange(periods) - delay, 0)]
        seen = np.hstack([b.q, b.qd])
        if not sc.plant.noise_q_std and not sc.plant.encoder_noise_counts:
            np.testing.assert_array_equal(seen, quantise(true, a.setup.quantum,
                                                         a.setup.grid_offset))
        else:  # noisy, then on the grid: within the noise of the delayed true state
            counts = sc.plant.encoder_noise_counts * a.setup.quantum[:n].max()
            assert np.abs(seen - true)[:, :n].max() < 10 * sc.plant.noise_q_std + 1e-3 + counts
        assert not np.array_equal(seen, state)  # the log holds what was measured
        # ... and so does the as-fast log, value for value (the noise replayed).
        np.testing.assert_allclose(np.hstack([a.q, a.qd]), seen, rtol=0, atol=1e-12)


@pytest.mark.parametrize("options", ["everything", "disturbances"])
@pytest.mark.slow
def test_the_sim_backend_reads_and_writes_without_growing_memory(options):
    from cochlea.runtime.sim_backend import SimBackend

    sc = load_scenario("serial_joint")
    plant = {k: v for k, v in MEASURED[options].items() if k != "coulomb"}
    if "torque_constant_error" in plant:
        plant["torque_constant_error"] = np.full(3, plant["torque_constant_error"])
    sc = dataclasses.replace(sc, plant=Plant(**plant))
    setups = unit_setups(sc)
    backend = SimBackend(setups, sc.period, sc.plant_substeps, plant=sc.plant, steps=6000)
    backend.enable()
    assert_periods_allocate_nothing(backend, np.zeros(12), np.full(6, 1e-3))


@pytest.mark.parametrize("loop", csim.LOOPS)
@pytest.mark.slow
def test_divergence_stops_both_kernels_at_the_same_period(loop, tmp_path):
    """Arm 2's printed G_a diverges within 0.1 s once its torques are not clipped (a
    description with no effective torque limit): same rows, same time, and the noise of the
    units after it drawn as the reference does. (1000 N m: the largest torque limit a
    description may give, far beyond what these links need.)"""
    unlimited = tmp_path / "unlimited.toml"
    unlimited.write_text(re.sub(r"torque_limit_Nm = [0-9.]+", "torque_limit_Nm = 1000.0",
                                (ROBOTS_DIR / "serial.toml").read_text()))
    sc = load_scenario("serial_task")
    sc = dataclasses.replace(sc, description=str(unlimited), system=load_serial(unlimited))
    units = list(sc.units)
    units[1] = dataclasses.replace(units[1], gains={**units[1].gains,
                                                    "G_a": np.array([0.1, 0.05, 1.0])})
    for plant in (Plant(), Plant(noise_q_std=1e-6, seed=3)):
        diverging = dataclasses.replace(sc, units=tuple(units), plant=plant)
        setups = unit_setups(diverging)
        reference = simulate(diverging, 0.3, setups, kernels="casadi")
        assert reference.diverged and "arm2" in reference.diverged
        result = csim.simulate_compiled(diverging, 0.3, setups, loop=loop)
        wild = [np.abs(getattr(u, key)).max(axis=1) > 1e6 for u in reference.units
                for key in FIELDS]
        tame = min(int(np.argmax(w)) if w.any() else len(w) for w in wild)
        assert tame >= 3  # the rows before the blow-up are compared
        assert_same_log(result, reference, rows=tame)


@pytest.mark.slow
def test_unavailable_kernels_fall_back_with_a_warning(tmp_path):
    sc = load_scenario("serial_joint")
    base = dataclasses.replace(sc, parameterisation="base", adaptation_gain=1e-4)
    setups = unit_setups(base)
    with pytest.raises(csim.CKernelsUnavailable, match="computes something else|no kernel"):
        csim.simulate_compiled(base, 0.05, setups)
    with pytest.warns(csim.CKernelsWarning, match="CasADi kernels"):
        result = simulate(base, 0.05, setups)
    assert_same_log(result, simulate(base, 0.05, setups, kernels="casadi"), tol=0)
    with pytest.raises(csim.CKernelsUnavailable, match="make lib"):
        csim.simulate_compiled(sc, 0.05, library=tmp_path / "missing.so")


@pytest.mark.slow
def test_other_rk4_substeps_are_not_generated():
    sc = dataclasses.replace(load_scenario("serial_joint"), plant_substeps=2)
    with pytest.raises(csim.CKernelsUnavailable, match="2 RK4 sub-steps"):
        csim.simulate_compiled(sc, 0.01)


def test_bad_kernels_and_loop_are_user_errors():
    sc = load_scenario("serial_joint")
    with pytest.raises(CochleaError, match="unknown kernels 'fortran'"):
        simulate(sc, 0.01, kernels="fortran")
    with pytest.raises(CochleaError, match="unknown loop"):
        csim.simulate_compiled(sc, 0.01, loop="rust")


@pytest.mark.slow
def test_desired_samples_are_the_desired_function(references):
    sc, setups, _ = references["serial_task"]
    time = np.arange(50) * sc.period
    xd, xd_dot, xd_ddot = csim.desired_samples(setups[1], time)
    for k in (0, 17, 49):
        expected = [np.array(v).ravel() for v in setups[1].desired(time[k])]
        for got, want in zip((xd[k], xd_dot[k], xd_ddot[k]), expected):
            assert np.allclose(got, want, rtol=1e-14, atol=1e-15)


def test_the_in_place_measurement_grid_equals_quantise(rng):
    """The per-period grid (Python loop, sim backend) gives quantise's values bit for bit,
    halves included, and leaves a continuous coordinate alone."""
    from cochlea.sim.setup import MeasurementGrid, quantise

    quantum = np.array([1.5e-3, 0.0, 2.4e-2, 3.1e-5])
    offset = np.array([0.3, 0.0, 0.0, -0.01])
    grid = MeasurementGrid(quantum, offset)
    values = rng.uniform(-3, 3, (500, 4))
    values[:50] = offset + quantum * (np.arange(50)[:, None] - 24.5)  # exact halves
    for row in values:
        x = row.copy()
        assert grid.apply(x) is x
        np.testing.assert_array_equal(x, quantise(row, quantum, offset))
        assert x[1] == row[1]
    everywhere = MeasurementGrid(quantum[[0, 2]], offset[[0, 2]])
    x = values[7, [0, 2]].copy()
    np.testing.assert_array_equal(everywhere.apply(x), quantise(values[7, [0, 2]],
                                                                quantum[[0, 2]], offset[[0, 2]]))


@pytest.mark.parametrize("delay", [0, 1, 3, 7, 8, 20])
def test_measurements_through_one_delay_are_the_delayed_rows(delay):
    """One delay shifts the rows by slices (not a fancy index): row k is row max(k - delay, 0),
    a copy; a delay of the run's length or more is the first row throughout."""
    states = np.random.default_rng(delay).normal(size=(8, 4))
    expected = states[np.maximum(np.arange(8) - delay, 0)]
    seen = measurements(states, delay, noise=np.zeros((8, 4)))  # noise: a copy even at 0
    assert np.array_equal(seen, expected) and not np.shares_memory(seen, states)
    assert np.array_equal(measurements(states, delay), expected)
    assert measurements(states[:0], delay).shape == (0, 4)


def test_desired_samples_are_kept_for_the_same_grid_bit_for_bit():
    """A structure's desired samples are computed once per time grid: the same grid (a new
    array) finds them; a grid that differs in one bit (-0.0 for 0.0) computes its own."""
    sc = dataclasses.replace(load_scenario("serial_task"), duration=0.05)
    u = unit_setups(sc)[0]
    time = np.arange(50) * sc.period
    first = csim.desired_samples(u, time)
    assert csim.desired_samples(u, time.copy()) is first
    assert csim.desired_samples(u, np.repeat(time, 2)[::2]) is first  # a strided view too
    other = time.copy()
    other[0] = -0.0
    assert csim.desired_samples(u, other) is not first
