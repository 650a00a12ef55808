"""The example user robots in models/examples/ (issue 25, item 7): every description and
scenario there loads, and the 2-DoF planar arm's starter scenario converges in simulation."""

from __future__ import annotations

import tomllib

import pytest

import cochlea
from cochlea.apps import report
from cochlea.resources import EXAMPLES_DIR
from cochlea.sim import load_scenario, simulate

TOMLS = sorted(EXAMPLES_DIR.glob("*.toml"))
DESCRIPTIONS = [p for p in TOMLS if tomllib.loads(p.read_text())["format"] == "cochlea-robot/1"]
SCENARIOS = [p for p in TOMLS if p not in DESCRIPTIONS]


def test_the_examples_are_there():
    names = {p.name for p in TOMLS}
    assert {"planar2_xm540.toml", "planar2_xm540_joint.toml"} <= names
    assert DESCRIPTIONS and SCENARIOS


@pytest.mark.parametrize("path", DESCRIPTIONS, ids=lambda p: p.stem)
def test_each_example_description_loads_and_says_what_is_estimated(path):
    header = path.read_text().split("\nformat", 1)[0]
    assert "EXAMPLE" in header and "ESTIMATED" in header
    system = cochlea.load_serial(path)
    for arm in system.arms:
        model = cochlea.model("serial", arm=arm.name, description=path)
        assert len(model.joints) == len(arm.links)


@pytest.mark.parametrize("path", SCENARIOS, ids=lambda p: p.stem)
def test_each_example_scenario_loads(path):
    scenario = load_scenario(path)
    assert scenario.robot == "serial"


@pytest.mark.slow
def test_the_planar_arm_starter_converges(tmp_path, monkeypatch):
    """A short run of the 2-DoF arm's starter, from another working directory (the scenario
    names its description relative to itself)."""
    monkeypatch.chdir(tmp_path)
    scenario = load_scenario(EXAMPLES_DIR / "planar2_xm540_joint.toml")
    result = simulate(scenario, duration=4.0, kernels="casadi")
    summary = report.summary(result)
    assert summary["converged"] and not summary["diverged"], summary
    for unit in summary["units"].values():
        for c in unit["tracked"].values():
            assert c["initial_abs_error"] > 1e-2
            assert c["converged"]
