"""A sweep sample's cost outside its closed loop, the fifth pass (issue 30 item 3): what a
worker looks up, checks and copies every sample is kept per process where it cannot differ
between samples, and the measured states of a delayed run are a view of the driver's log. What
it must not change: any sample's row, verdict or summary (tests/test_sweep_overhead.py judges
every sample of the four studies both ways), nor serve a cached entry to an input that
differs. Each cache here is shown to miss on a changed input."""

from __future__ import annotations

import dataclasses
import os
import shutil

import numpy as np
import pytest

from cochlea.kernels import library as ckernels
from cochlea.kernels.library import LibraryError
from cochlea.sim import compiled, load_scenario, unit_setups
from cochlea.sim.setup import measurements, quantise

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
