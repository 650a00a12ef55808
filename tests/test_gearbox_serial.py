"""Issue 24, item 2, the serial arms: the measuring tool of docs/robustness.md ("The serial
studies: not converged") measures the case the issue is about.

``bench/gearbox.py --cases everything`` writes the serial rows of the everything-at-once case;
its plant must be the one ``tests/test_gearbox_survival.py`` holds the parallel studies to (and
the serial ones to their honest "not converged"), or the table would answer another question.
``--settings shipped`` must run the scenario files as they are.
"""

from __future__ import annotations

import dataclasses
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from cochlea.robots import robot
from cochlea.sim import load_scenario, unit_setups

from .test_gearbox_survival import everything

BENCH = Path(__file__).resolve().parents[1] / "bench" / "gearbox.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_gearbox", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _plant_fields(p):
    return {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return a is not None and b is not None and np.array_equal(a, b)
    return a == b


@pytest.mark.parametrize("study", ["serial_joint", "serial_task"])
def test_the_bench_everything_case_is_the_survival_tests_plant(bench, study):
    """Each ``--cases everything`` row's plant equals test_gearbox_survival's ``everything``
    for the same torque-constant error, field by field (the seed aside: the bench's own)."""
    assert len(bench.EVERYTHING) == 2
    for changes in bench.EVERYTHING.values():
        sc = load_scenario(f"{study}_realistic")
        n = robot(sc.robot).layout(sc.system, sc.space).n_joint
        error = changes["torque_constant_error"]
        mine = dataclasses.replace(sc.plant, **dict(
            changes, torque_constant_error=np.full(n, error)))
        theirs = everything(f"{study}_realistic", error).plant
        a, b = _plant_fields(mine), _plant_fields(theirs)
        differ = [k for k in a if k != "seed" and not _same(a[k], b[k])]
        assert not differ, differ


def test_the_shipped_settings_change_nothing(bench):
    """``--settings shipped`` leaves the scenario's gains and robust options as the file has
    them; another named setting does change them (so the flag is not a no-op)."""
    assert bench.SETTINGS["shipped"] == {}
    sc = load_scenario("serial_joint_realistic")
    shipped = unit_setups(sc)
    robust = bench.SETTINGS["robust"]
    assert not np.array_equal(np.asarray(robust["gains"]["serial_joint"], float),
                              shipped[0].gains)
    assert robust["robust"]["startup_ramp"] != sc.robust.startup_ramp
