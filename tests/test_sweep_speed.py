"""The per-process caches that make a sweep's sample cheap (issue 16): set-ups built once per
symbolic structure, descriptions read once per file content, desired samples computed once per
path. What they must not change: a sample's row and a simulation's logs, bit for bit, whatever
ran in the process before; what they must not do: carry one sample's numbers into another,
keep a failed check, or keep a description that changed on disk."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from cochlea.apps import cochlea_sweep
from cochlea.errors import CochleaError
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.robots import robot
from cochlea.sim import load_scenario, simulate, unit_setups
from cochlea.sim import setup as setup_mod
from cochlea.sim.scenario import Quantity, stressed
from cochlea.sweep import sampling
from cochlea.sweep import spec as sweep_spec

#: Each study with a gain it sweeps (unit, key).
STUDIES = {"serial_joint": ("arm1", "alpha", 4.0, 6.0),
           "serial_task": ("arm1", "G_g", 1.5, 2.5),
           "parallel_joint": ("mechanism", "G_f", 0.3, 0.4),
           "parallel_task": ("mechanism", "K_p", 1.5, 2.5),
           # The realistic plant: armature, Coulomb friction, encoder and register grids,
           # current quantisation, from the description's actuators.
           "serial_joint_realistic": ("arm2", "K_e", 4.0, 6.0)}
SPEC = """format = "cochlea-sweep/1"
scenario = "{study}"
samples = 3
seed = 11
duration_s = 0.25

[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{choice = [0, 1, 2]}}
noise_q_std_SI = {{uniform = [0.0, 1e-4]}}
viscous_friction_SI = {{uniform = [0.0, 1e-3]}}
position_encoder = {{choice = [true, false]}}

[gains.{unit}]
{gain} = {{uniform = [{lo}, {hi}]}}
"""


def _plain(row: dict) -> dict:
    """NaN as None: NaN equals nothing, itself included."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in row.items()}


def _spec(folder, study: str) -> sweep_spec.Spec:
    unit, gain, lo, hi = STUDIES[study]
    path = folder / "spec.toml"
    path.write_text(SPEC.format(study=study, unit=unit, gain=gain, lo=lo, hi=hi))
    return sweep_spec.load(path)


def _logs(result) -> list:
    keys = ("q", "qd", "desired", "desired_dot", "errors", "tau", "p_hat", "pose", "true_q",
            "true_qd", "true_x")
    return [result.time, result.diverged] + [getattr(u, k) for u in result.units for k in keys]


def _assert_same_logs(a, b) -> None:
    la, lb = _logs(a), _logs(b)
    assert la[1] == lb[1]
    for x, y in zip(la[:1] + la[2:], lb[:1] + lb[2:], strict=True):
        assert x.shape == y.shape
        assert np.array_equal(x, y, equal_nan=True)


@pytest.mark.parametrize("study", sorted(STUDIES))
@pytest.mark.slow
def test_a_row_through_the_cache_equals_the_row_built_from_scratch(study, tmp_path):
    spec = _spec(tmp_path, study)
    texts = [sampling.scenario_text(spec, i) for i in range(spec.total)]
    setup_mod.clear_cache()
    cached = [_plain(cochlea_sweep.evaluate(t)) for t in texts]
    # Sample 0 again, after the others went through the same cached structure.
    again = _plain(cochlea_sweep.evaluate(texts[0]))
    fresh = [_plain(cochlea_sweep.evaluate(t, cache=False)) for t in texts]
    assert cached == fresh
    assert again == cached[0]
    # The samples differ, so a number carried from one to the next would show.
    assert len({tuple(sorted((k, str(v)) for k, v in r.items())) for r in fresh}) == len(fresh)


@pytest.mark.parametrize("study", sorted(STUDIES))
@pytest.mark.slow
def test_simulate_on_cached_setups_equals_fresh_setups(study):
    base = dataclasses.replace(load_scenario(study), duration=0.25)
    sc = stressed(base, 1.2, delay_periods=1, payload_kg=0.02)
    other = stressed(base, 0.8, delay_periods=2, payload_kg=0.0)
    other = dataclasses.replace(other, plant=dataclasses.replace(other.plant, noise_q_std=1e-4,
                                                                 seed=3))
    setup_mod.clear_cache()
    simulate(other)  # fills the cache with another sample's numbers
    cached = simulate(sc)
    assert unit_setups(sc)[0].controller is unit_setups(other)[0].controller  # one structure
    fresh = simulate(sc, setups=unit_setups(sc, cache=False))
    _assert_same_logs(cached, fresh)
    with pytest.raises(AssertionError):  # the comparison does see a different plant
        _assert_same_logs(cached, simulate(other))


def test_a_setup_written_in_place_does_not_reach_the_next_sample():
    sc = dataclasses.replace(load_scenario("parallel_task"), duration=0.1)
    sc = dataclasses.replace(sc, initial_estimate="nominal")
    setup_mod.clear_cache()
    first = unit_setups(sc)
    for u in first:
        for array in (u.x0, u.p_hat0, u.gains, u.gamma, u.plant_params, u.friction):
            array[...] = 123.0
    second, fresh = unit_setups(sc), unit_setups(sc, cache=False)
    assert second[0].controller is first[0].controller  # the cache was used
    for a, b in zip(second, fresh, strict=True):
        for name in ("x0", "p_hat0", "gains", "gamma", "plant_params", "friction"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), name
    # The desired samples every run of the structure shares cannot be written.
    result = simulate(sc)
    with pytest.raises(ValueError):
        result.units[0].desired[0, 0] = 0.0


@pytest.mark.slow
def test_the_path_is_checked_once_per_structure(monkeypatch):
    base = dataclasses.replace(load_scenario("serial_task"), duration=0.2)
    adapter = type(robot("serial"))
    original = adapter.unit_plans
    calls = []

    def counted(self, system, sc):
        calls.append(sc.duration)
        return original(self, system, sc)

    monkeypatch.setattr(adapter, "unit_plans", counted)
    setup_mod.clear_cache()
    for mass in (0.8, 1.0, 1.2):  # masses, payloads, delays: numbers only
        unit_setups(stressed(base, mass, delay_periods=int(mass * 2), payload_kg=mass / 50))
    assert calls == [0.2]
    unit_setups(dataclasses.replace(base, duration=0.3))  # another run: its path is checked
    assert calls == [0.2, 0.3]
    unit_setups(base, cache=False)
    assert calls == [0.2, 0.3, 0.2]


@pytest.mark.slow
def test_a_refused_path_is_refused_every_time():
    sc = dataclasses.replace(load_scenario("serial_task"), duration=0.2)
    # A leader circle of 0.5 m: out of the arms' reach.
    bad = dataclasses.replace(sc, leader=(Quantity("0.5*cos(t)", "length", 1.0),
                                          Quantity("0.5*sin(t)", "length", 1.0),
                                          sc.leader[2]))
    setup_mod.clear_cache()
    for _ in range(2):
        with pytest.raises(CochleaError, match="workspace"):
            unit_setups(bad)
    unit_setups(sc)  # and the good one is still fine


@pytest.mark.slow
def test_an_edited_description_is_read_again(tmp_path):
    description = tmp_path / "serial.toml"
    original = (ROBOTS_DIR / "serial.toml").read_text()
    assert "mass_kg = 0.09518" in original
    description.write_text(original)
    text = (SCENARIOS_DIR / "serial_task.toml").read_text()
    text = text.replace('robot = "serial"\n', f'robot = "serial"\ndescription = "{description}"\n')
    text = text.replace("duration_s = 20.0", "duration_s = 0.2")
    path = tmp_path / "scenario.toml"
    path.write_text(text)
    setup_mod.clear_cache()
    a, b = load_scenario(path), load_scenario(path)
    assert a.system is b.system
    before = unit_setups(a)[0].plant_params
    description.write_text(original.replace("mass_kg = 0.09518", "mass_kg = 0.2"))
    c = load_scenario(path)
    assert c.system is not a.system
    after = unit_setups(c)
    assert not np.array_equal(after[0].plant_params, before)
    assert np.array_equal(after[0].plant_params, unit_setups(c, cache=False)[0].plant_params)
    assert after[0].plant_model is not unit_setups(a)[0].plant_model
