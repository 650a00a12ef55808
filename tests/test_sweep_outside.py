"""A sweep sample's cost outside its closed loop, the fifth pass (issue 30 item 3): what a
worker looks up, checks and copies every sample is kept per process where it cannot differ
between samples, and the measured states of a delayed run are a view of the driver's log. What
it must not change: any sample's row, verdict or summary (tests/test_sweep_overhead.py judges
every sample of the four studies both ways), nor serve a cached entry to an input that
differs. Each cache here is shown to miss on a changed input."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import time
import tomllib

import casadi as ca
import numpy as np
import pytest

from cochlea.apps import cochlea_sweep, report
from cochlea.errors import CochleaError
from cochlea.kernels import library as ckernels
from cochlea.kernels.library import LibraryError
from cochlea.resources import ROBOTS_DIR, SCENARIOS_DIR
from cochlea.runtime import build_supervisor
from cochlea.runtime import supervisor as sv
from cochlea.sim import compiled, load_scenario, simulate, unit_setups
from cochlea.sim import scenario as scenario_mod
from cochlea.sim import setup as setup_mod
from cochlea.sim.setup import measurements, quantise
from cochlea.sweep import sampling
from cochlea.sweep import spec as sweep_spec

# --------------------------------------------------------------------------------------------
# The library: found again in one stat, never a file it no longer names
# --------------------------------------------------------------------------------------------


def test_a_library_is_found_again_only_while_its_name_names_the_same_file(tmp_path):
    built = ckernels.load()
    one, two = tmp_path / "one.so", tmp_path / "two.so"
    shutil.copyfile(built.path, one)
    shutil.copyfile(built.path, two)
    link = tmp_path / "libcochlea.so"
    link.symlink_to(one)
    first = ckernels.load(link)
    assert first.path == one.resolve()
    assert ckernels.load(link) is first  # the same name, the same file: the same library
    assert ckernels.load(tmp_path) is first  # a folder names its libcochlea.so
    link.unlink()
    link.symlink_to(two)  # the name now names another file: looked up anew
    assert ckernels.load(link).path == two.resolve()
    link.unlink()
    with pytest.raises(LibraryError, match="does not exist"):
        ckernels.load(link)  # gone: the loader's own error, whatever was found before


def test_a_relative_library_name_is_found_from_the_working_directory(tmp_path, monkeypatch):
    built = ckernels.load()
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        shutil.copyfile(built.path, tmp_path / name / "lib.so")
    monkeypatch.chdir(tmp_path / "a")
    assert ckernels.load("lib.so").path == (tmp_path / "a" / "lib.so").resolve()
    monkeypatch.chdir(tmp_path / "b")
    assert ckernels.load("lib.so").path == (tmp_path / "b" / "lib.so").resolve()


def test_the_environment_s_library_is_read_at_every_call(tmp_path, monkeypatch):
    built = ckernels.load()
    other = tmp_path / "other.so"
    shutil.copyfile(built.path, other)
    monkeypatch.setenv(ckernels.ENVIRONMENT, str(other))
    assert ckernels.load().path == other.resolve()
    monkeypatch.delenv(ckernels.ENVIRONMENT)
    assert ckernels.load() is built


def test_a_closed_loop_driver_is_bound_once_per_library_and_name():
    lib = ckernels.load()
    loop = lib.closed_loop("serial_arm1_e_closed_loop")
    assert lib.closed_loop("serial_arm1_e_closed_loop") is loop
    assert lib.closed_loop("serial_arm2_e_closed_loop") is not loop
    with pytest.raises(LibraryError, match="no closed loop"):
        lib.closed_loop("serial_arm1_x_closed_loop")


# --------------------------------------------------------------------------------------------
# A unit's kernels: looked up and checked once per library, Functions and options
# --------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_unit_s_kernels_are_checked_again_for_another_controller_or_library(tmp_path):
    lib = ckernels.load()
    corrected = unit_setups(load_scenario("serial_joint"), gravity=False)
    found = compiled.unit_kernels(lib, corrected[0], 1)
    assert compiled.unit_kernels(lib, corrected[0], 1) is found
    # Another controller (the thesis variant): its own kernels, not the corrected one's.
    sc = load_scenario("serial_joint")
    thesis = unit_setups(dataclasses.replace(sc, variant="thesis"), gravity=False)
    assert compiled.unit_kernels(lib, thesis[0], 1).step == "serial_arm1_e_thesis_step"
    # ... on the same plant and pose Functions as the corrected unit's
    mixed = dataclasses.replace(corrected[0], controller=thesis[0].controller)
    assert compiled.unit_kernels(lib, mixed, 1).step == "serial_arm1_e_thesis_step"
    assert compiled.unit_kernels(lib, corrected[0], 1).step == "serial_arm1_e_step"
    # Another plant option (the plant with dry friction): its own plant step and driver.
    dry = dataclasses.replace(corrected[0], drive=np.zeros(9))
    assert compiled.unit_kernels(lib, dry, 1).plant == "serial_arm1_plant_step_coulomb"
    # Other sub-steps: a kernel the library does not have, refused every time.
    for _ in range(2):
        with pytest.raises(compiled.CKernelsUnavailable, match="sub-steps"):
            compiled.unit_kernels(lib, corrected[0], 7)
    # Another library that lacks the unit's kernels: refused, though they were found in the
    # shipped one.
    empty = ckernels.Library(lib.path)
    empty.manifest = {**lib.manifest, "kernels": {}}
    with pytest.raises(compiled.CKernelsUnavailable, match="no kernel"):
        compiled.unit_kernels(empty, corrected[0], 1)


# --------------------------------------------------------------------------------------------
# The measured states of a delayed run: a view of the driver's log, the copy's values
# --------------------------------------------------------------------------------------------


def _run(lead: int, n: int = 50, delay: int = 0):
    lib = ckernels.load()
    loop = lib.closed_loop("serial_arm1_e_closed_loop")
    rng = np.random.default_rng(4)
    t = np.arange(n) * 1e-3
    xd = np.column_stack([1.2 + 0.1 * np.sin(t), 1.3 + 0.1 * np.cos(t), 2.0 + 0 * t])
    return loop.run(n, x0=np.r_[1.25, 1.4, 1.9, 0, 0, 0], p_hat0=np.zeros(3), xd=xd,
                    xd_dot=np.zeros((n, 3)), xd_ddot=np.zeros((n, 3)),
                    gains=rng.uniform(0.5, 2, loop.n_gains), Gamma=np.ones(3), bound=10.0,
                    h=1e-3, plant_p=np.full(30, 0.01), friction=np.zeros(3), delay=delay,
                    lead=lead)


@pytest.mark.parametrize("delay", [1, 2, 5, 50, 60])
def test_a_log_with_rows_in_front_runs_as_without_them(delay):
    plain, padded = _run(0, delay=delay), _run(delay, delay=delay)
    assert padded.rows == plain.rows == 50
    for name in ("x", "p_hat", "tau", "errors", "pose"):
        assert np.array_equal(getattr(padded, name), getattr(plain, name)), name
    assert padded.x.flags.c_contiguous and padded.x.shape == plain.x.shape


@pytest.mark.parametrize("delay", [0, 1, 2, 3, 49, 50])
@pytest.mark.parametrize("rows", [1, 2, 3, 50])
@pytest.mark.parametrize("extra", ["none", "noise", "grid", "both"])
def test_the_delayed_view_measures_as_the_copy_bit_for_bit(delay, rows, extra):
    log = _run(delay)
    states = log.x[:rows]
    rng = np.random.default_rng(delay)
    noise = rng.normal(0, 1e-3, (50, 6)) if extra in ("noise", "both") else None
    quantum = offset = None
    if extra in ("grid", "both"):
        quantum = np.r_[np.full(3, 2 * np.pi / 4096), 0.0, 0.024, 0.024]
        offset = rng.uniform(-1e-4, 1e-4, 6)
    shifted = log.delayed(delay, rows)
    assert shifted is not None and not shifted.flags.writeable
    old = measurements(states, delay, noise, quantum, offset)
    new = measurements(states, delay, noise, quantum, offset, shifted=shifted)
    assert new.tobytes() == old.tobytes()
    # The log itself is as it was: nothing was written into the true states.
    assert np.array_equal(states, _run(delay).x[:rows])


def test_the_delayed_view_is_none_where_the_log_has_too_few_rows_in_front():
    log = _run(2)
    assert log.delayed(3, 50) is None
    assert log.delayed(2, 51) is None
    assert log.delayed(2, 0) is None
    assert _run(0).delayed(1, 50) is None
    with pytest.raises(ckernels.KernelError, match="lead"):
        _run(-1)
    with pytest.raises(ValueError, match="shifted"):
        measurements(log.x[:10], 2, shifted=log.delayed(2, 9))


def test_quantise_reads_a_read_only_view():
    a = np.linspace(0, 1, 12).reshape(2, 6)
    a.flags.writeable = False
    assert quantise(a, np.full(6, 0.1), np.zeros(6)).flags.writeable


def test_no_cache_of_this_pass_outlives_its_bound():
    assert len(compiled._UNIT_KERNELS) <= compiled.UNIT_KERNEL_CACHE_SIZE
    assert all(os.path.isabs(v[2]) for v in ckernels._FOUND.values())


# --------------------------------------------------------------------------------------------
# A scenario: taken from the template of its structure, only the plant and the gains read
# --------------------------------------------------------------------------------------------


def _same(a, b, where="scenario"):
    """Equal field by field, of the same types, arrays bit for bit (the system by identity)."""
    assert type(a) is type(b), where
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            if f.name == "system":
                assert getattr(a, f.name) is getattr(b, f.name), where
            else:
                _same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), where
        assert a is not b or a.size == 0, f"{where}: shared"
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _same(x, y, f"{where}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), where
        for k in a:
            _same(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, float) and np.isnan(a):
        assert np.isnan(b), where
    else:
        assert a == b and (not isinstance(a, float) or repr(a) == repr(b)), where


def _full(path, data, preset=None):
    """The scenario read whole, as before the templates."""
    scenario_mod.check_nesting(scenario_mod.resolve(path), data)
    return scenario_mod._load(scenario_mod.resolve(path), preset, data)[0]


SPEC_TEXT = """format = "cochlea-sweep/1"
scenario = "{study}"
samples = 4
seed = 9

[perturb]
mass_scale = {{uniform = [0.7, 1.3]}}
payload_kg = {{uniform = [0.0, 0.05]}}
delay_periods = {{choice = [0, 1, 2]}}
{extra}
"""


@pytest.mark.parametrize("study", ["serial_joint", "serial_task", "parallel_joint",
                                   "parallel_task_realistic", "serial_joint_realistic"])
@pytest.mark.parametrize("preset", [None, "realistic"])
def test_every_sample_s_scenario_is_what_the_full_load_reads(study, preset, tmp_path):
    gains = {"serial_joint": "[gains.arm1]\nalpha = {uniform = [1.0, 9.0]}",
             "serial_task": "[gains.arm2]\nG_g = {uniform = [1.0, 9.0], each = true}"}.get(
                 study, "")
    path = tmp_path / "spec.toml"
    path.write_text(SPEC_TEXT.format(study=study, extra=gains))
    spec = sweep_spec.load(path)
    for i in range(spec.total):
        data = sampling.scenario_data(spec, i)
        fast = load_scenario(cochlea_sweep.SAMPLE_FILE, preset, data=data)
        _same(fast, _full(cochlea_sweep.SAMPLE_FILE, sampling.scenario_data(spec, i), preset))
        assert data == sampling.scenario_data(spec, i)  # the data is not changed
    # The same from a file and from its text.
    text = sampling.scenario_text(spec, 1)
    (tmp_path / "sample.toml").write_text(text)
    for sc in (load_scenario(tmp_path / "sample.toml", preset),
               load_scenario(tmp_path / "sample.toml", preset, text=text)):
        _same(sc, _full(tmp_path / "sample.toml", tomllib.loads(text), preset))


def _sample(**changes) -> dict:
    data = tomllib.loads((SCENARIOS_DIR / "serial_joint.toml").read_text())
    for dotted, value in changes.items():
        *parents, last = dotted.split("/")
        table = data
        for p in parents:
            table = table[int(p)] if p.isdigit() else table.setdefault(p, {})
        table[last] = value
    return data


@pytest.mark.parametrize("change", [
    {"duration_s": 7.0}, {"duration_s": 7}, {"control/rate_Hz": 500.0},
    {"control/estimate_bound": 5.0}, {"control/variant": "thesis"},
    {"unit/0/initial_joint": ["74 deg", "83 deg", "110 deg"]},
    {"unit/1/elbow": 1}, {"desired/define": {"w": "0.5"}},
    {"control/adaptation_deadzone_SI": [0.0, -0.0, 0.0]},
    {"control/adaptation_deadzone_SI": [0.0, 0.0, 0.0]},
    {"control/adaptation_deadzone_SI": [0, 0, 0]},
])
def test_a_scenario_that_differs_elsewhere_is_read_whole(change):
    """Anything but the plant and the gains (a float's sign, an int for a float) is part of
    the template's key: a scenario that differs there is never given another's."""
    load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample())  # the template of the base
    try:
        expected = _full(cochlea_sweep.SAMPLE_FILE, _sample(**change))
    except CochleaError as exc:
        with pytest.raises(CochleaError, match=re.escape(str(exc))):
            load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample(**change))
        return
    for _ in range(2):  # read whole, then from its own template
        _same(load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample(**change)), expected)


@pytest.mark.parametrize("change", [
    {"unit/0/gains/alpha": [5.0, 4.0, -3.0]}, {"unit/0/gains/alpha": [5.0, 4.0]},
    {"unit/1/gains/K_e": "0.2"}, {"unit/1/gains/extra": [1.0]}, {"unit/0/gains": 5},
    {"plant/payload_kg": -1.0}, {"plant/mass_scale": [1.0]}, {"plant/unknown": 1},
    {"plant/plant": "gentle"}, {"plant/seed": 2**64}, {"plant": [1, 2]},
    {"plant/encoder_noise_counts": 1},
])
def test_a_bad_plant_or_gain_is_refused_as_by_the_full_load(change):
    good = load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample(**{"plant/payload_kg": 0.01}))
    assert good.plant.payload_kg == 0.01
    with pytest.raises(CochleaError) as full:
        _full(cochlea_sweep.SAMPLE_FILE, _sample(**change))
    for _ in range(2):
        with pytest.raises(CochleaError) as fast:
            load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample(**change))
        assert str(fast.value) == str(full.value) and type(fast.value) is type(full.value)


def test_gains_read_before_are_copies_and_a_scenario_s_arrays_its_own():
    first = load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample())
    first.units[0].gains["alpha"][:] = 99.0
    first.units[0].initial_joint[:] = 99.0
    second = load_scenario(cochlea_sweep.SAMPLE_FILE, data=_sample())
    _same(second, _full(cochlea_sweep.SAMPLE_FILE, _sample()))
    other = load_scenario(cochlea_sweep.SAMPLE_FILE,
                          data=_sample(**{"unit/0/gains/alpha": [1.0, 2.0, 3.0]}))
    assert other.units[0].gains["alpha"].tolist() == [1.0, 2.0, 3.0]
    assert second.units[0].gains["alpha"].tolist() == [5.0, 4.0, 3.0]


def test_the_template_is_not_used_for_another_description_file(tmp_path):
    """A user's description named by path: edited (another content, even one of the same
    size written within the same clock tick), the scenario gets the new system."""
    source = (ROBOTS_DIR / "serial.toml").read_text()
    desc = tmp_path / "robot.toml"
    desc.write_text(source)
    old = time.time_ns() - 10**10
    os.utime(desc, ns=(old, old))  # settled: the next loads do not read it again
    data = _sample(description=str(desc))
    first = load_scenario(cochlea_sweep.SAMPLE_FILE, data=data)
    assert load_scenario(cochlea_sweep.SAMPLE_FILE, data=data).system is first.system
    edited = source.replace("0.", "1.", 1)
    assert len(edited) == len(source) and edited != source
    desc.write_text(edited)
    os.utime(desc, ns=(old, old))  # the same size and times of change: its status changed
    second = load_scenario(cochlea_sweep.SAMPLE_FILE, data=data)
    assert second.system is not first.system
    desc.write_text(source)  # back: the first content's system again
    assert load_scenario(cochlea_sweep.SAMPLE_FILE, data=data).system is first.system
    desc.unlink()
    with pytest.raises(CochleaError, match="robot.toml"):
        load_scenario(cochlea_sweep.SAMPLE_FILE, data=data)


def test_a_description_changed_in_its_last_seconds_is_read_every_time(tmp_path, monkeypatch):
    desc = tmp_path / "robot.toml"
    desc.write_text((ROBOTS_DIR / "serial.toml").read_text())
    reads = []
    real = scenario_mod.robot_adapter("serial").load

    def counted(description):
        reads.append(description)
        return real(description)

    monkeypatch.setattr(scenario_mod.robot_adapter("serial"), "load", counted)
    opened = []
    monkeypatch.setattr(scenario_mod, "_file_state",
                        lambda p: opened.append(p) or _state(p))
    for _ in range(3):
        scenario_mod.load_system("serial", str(desc))
    assert len(opened) == 3  # fresh: its state read, and the file with it, every time


def _state(path):
    st = os.stat(path)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


# --------------------------------------------------------------------------------------------
# The verdict's and the summary's reductions: fewer numpy calls, the same numbers
# --------------------------------------------------------------------------------------------


def _old_column_extremes(a):
    """column_extremes as it was (the third pass): a block's rows reduced in one call, the
    rows after the last block on their own."""
    n, m = a.shape
    low, high = np.full(m, np.inf), np.full(m, -np.inf)
    full = n // 256 * 256
    if full:
        blocks = a[:full].reshape(-1, 256 * m)
        low = np.minimum.reduce(blocks, axis=0).reshape(256, m).min(axis=0)
        high = np.maximum.reduce(blocks, axis=0).reshape(256, m).max(axis=0)
    if full < n:
        low = np.minimum(low, a[full:].min(axis=0))
        high = np.maximum(high, a[full:].max(axis=0))
    return low, high


def _old_row_squares(p):
    total = np.multiply(p[:, 0], p[:, 0])
    square = np.empty_like(total)
    for j in range(1, p.shape[1]):
        total += np.multiply(p[:, j], p[:, j], out=square)
    return total


@pytest.mark.parametrize("rows", [0, 1, 255, 256, 257, 511, 512, 4113, 20_000, 20_001])
@pytest.mark.parametrize("columns", [0, 1, 2, 6, 13])
def test_column_extremes_are_the_old_ones(rows, columns):
    rng = np.random.default_rng(rows + columns)
    a = rng.normal(size=(rows, columns)) * 10.0 ** rng.integers(-3, 4, size=columns)
    for r in ([] if not rows or not columns else [0, rows // 2, rows - 1]):
        a[r, r % columns] = [np.nan, np.inf, -np.inf][r % 3]
    new = sv.column_extremes(a)
    # (The old one could not reshape a log of no columns: theirs are empty.)
    old = _old_column_extremes(a) if columns else (np.zeros(0), np.zeros(0))
    for x, y in zip(new, old):
        assert x.shape == y.shape == (columns,)
        assert np.array_equal(x, y, equal_nan=True)
    if rows:
        assert np.array_equal(new[0], np.min(a, axis=0), equal_nan=True)
        assert np.array_equal(new[1], np.max(a, axis=0), equal_nan=True)


@pytest.mark.parametrize("columns", [1, 2, 3, 5, 8])
def test_row_squares_are_the_old_ones_bit_for_bit(columns):
    rng = np.random.default_rng(columns)
    p = rng.normal(size=(3001, columns)) * 10.0 ** rng.integers(-150, 150, size=columns)
    p[7, 0], p[9, -1] = np.nan, np.inf
    assert sv.row_squares(p).tobytes() == _old_row_squares(p).tobytes()


# --------------------------------------------------------------------------------------------
# The gravity check: G_p through buffers, the call's numbers
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("study", ["serial_joint", "parallel_task_realistic"])
def test_gravity_through_buffers_is_the_call_bit_for_bit(study):
    rng = np.random.default_rng(1)
    for u in unit_setups(load_scenario(study), gravity=False):
        G = u.plant_model.G_p
        for _ in range(20):
            q = rng.uniform(-2, 2, u.controller_model.nq)
            p = u.plant_params * rng.uniform(0.5, 2.0, len(u.plant_params))
            got = setup_mod.evaluate_column(G, q, p)
            assert got.tobytes() == np.array(G(q, p), float).ravel().tobytes()
        # Not its sizes: the call's own result or error, as before.
        with pytest.raises(RuntimeError):
            setup_mod.evaluate_column(G, np.zeros(u.controller_model.nq + 1), u.plant_params)


def test_a_function_with_a_sparse_output_is_called_as_before():
    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [ca.vertcat(x[0] * 2, ca.SX(1, 1))])  # a structural zero
    assert not f.sparsity_out(0).is_dense()
    assert setup_mod.evaluate_column(f, np.array([1.5, 2.0])).tolist() == [3.0, 0.0]
    g = ca.Function("g", [x], [x * 3])
    assert setup_mod.evaluate_column(g, np.array([1.0, -2.0])).tolist() == [3.0, -6.0]
    assert setup_mod.evaluate_column(g, np.array([2.0, 1.0])).tolist() == [6.0, 3.0]


# --------------------------------------------------------------------------------------------
# A sweep's row: from a summary of only what it reads, bit for bit the full summary's row
# --------------------------------------------------------------------------------------------


def _row_both_ways(result, setups, sup):
    reductions = [sv.log_reductions(u) for u in result.units]
    result.supervisor = sv.verdict(result, sup, reductions)
    limits = {u.name: {j.name: float(lim) for j, lim in
                       zip(u.controller_model.joints, u.effort_limit)} for u in setups}
    full = report.summary(result, 0.0, reductions=reductions)
    row = report.summary(result, 0.0, reductions=reductions, row=True)
    a, b = cochlea_sweep.measures(full, limits), cochlea_sweep.measures(row, limits)
    assert json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)
    # Everything but the measured error and a settled norm is the full summary's.
    for name, u in row["units"].items():
        for coord, c in u["tracked"].items():
            for key, value in c.items():
                if not key.startswith("measured_"):
                    assert repr(value) == repr(full["units"][name]["tracked"][coord][key])
        e, f = u["estimates"], full["units"][name]["estimates"]
        assert e["bounded"] == f["bounded"]
        assert e["max_norm"] is None or repr(e["max_norm"]) == repr(f["max_norm"])
    return a


@pytest.mark.parametrize("study", ["serial_joint", "serial_task", "parallel_joint",
                                   "parallel_task", "serial_task_realistic"])
def test_a_row_from_the_row_s_summary_is_the_full_summary_s(study, tmp_path):
    path = tmp_path / "spec.toml"
    path.write_text(SPEC_TEXT.format(study=study, extra="").replace(
        "samples = 4", "samples = 2\nduration_s = 2.0"))
    spec = sweep_spec.load(path)
    for i in range(spec.total):
        sc = load_scenario(cochlea_sweep.SAMPLE_FILE, data=sampling.scenario_data(spec, i))
        setups = unit_setups(sc)
        result = simulate(sc, None, setups, threads=False)
        sup = build_supervisor(setups, sc.system.keep_out_radius, substeps=sc.plant_substeps)
        _row_both_ways(result, setups, sup)
        # Estimates at, past and far past the bound, not finite, or overflowing a square.
        for u in result.units:
            p, bound = u.p_hat.copy(), u.setup.bound
            direction = np.ones(p.shape[1]) / np.sqrt(p.shape[1])
            for k, value in enumerate([bound * (1 + 1e-9) * direction, bound * direction,
                                       bound * (1 - 1e-13) * direction,
                                       bound * (1 + 2e-9) * direction, 1e200 * direction,
                                       np.nan * direction, np.inf * direction]):
                u.p_hat = p.copy()
                u.p_hat[(k * 37) % len(p)] = value
                row = _row_both_ways(result, setups, sup)
                if k in (3, 4, 5, 6):
                    assert row["estimate_bound_hit"]
            u.p_hat = p


class _EvictedByAnotherThread(dict):
    """A cache whose entry another thread evicts right after this one found it (between the
    lookup and its move to the end), and which another thread empties before an eviction."""

    def get(self, key, default=None):
        value = super().get(key, default)
        if value is not None:
            del self[key]
        return value

    def move_to_end(self, key, last=True):
        raise KeyError(key) if key not in self else None

    def popitem(self, last=True):
        self.clear()  # another thread evicted them all first
        raise KeyError("dictionary is empty")


@pytest.mark.slow
def test_the_older_caches_do_not_fail_a_sample_another_thread_evicts_from(monkeypatch):
    """A dask worker runs samples on several threads: the desired samples', the structures'
    and the pose kernels' caches may lose an entry between its lookup and its move, or be
    emptied before an eviction; the sample goes on with what it found or built."""
    sc = load_scenario("serial_joint")
    u = unit_setups(sc)[0]
    time_grid = np.arange(5) * 1e-3
    monkeypatch.setattr(compiled, "_DESIRED", _EvictedByAnotherThread())
    monkeypatch.setattr(compiled, "DESIRED_CACHE_SIZE", 0)  # every insertion evicts
    first = compiled.desired_samples(u, time_grid)
    monkeypatch.setattr(compiled, "DESIRED_CACHE_SIZE", 16)  # kept, then found and evicted
    compiled.desired_samples(u, time_grid)
    again = compiled.desired_samples(u, time_grid)
    assert all(np.array_equal(a, b) for a, b in zip(first, again))

    monkeypatch.setattr(setup_mod, "_STRUCTURES", _EvictedByAnotherThread())
    monkeypatch.setattr(setup_mod, "STRUCTURE_CACHE_SIZE", 0)
    for _ in range(2):
        assert [s.name for s in unit_setups(sc)] == ["arm1", "arm2"]

    monkeypatch.setattr(sv, "_POSE_KERNELS", _EvictedByAnotherThread())
    monkeypatch.setattr(sv, "POSE_KERNEL_CACHE_SIZE", 0)
    for _ in range(2):
        build_supervisor(unit_setups(sc), sc.system.keep_out_radius, kernels="c",
                         substeps=sc.plant_substeps, cache=True)
