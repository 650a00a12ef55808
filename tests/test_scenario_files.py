"""Bad scenario files fail with one clear error naming the key; unreachable targets fail before
anything runs."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

from cochlea import CochleaError, DescriptionError
from cochlea.resources import SCENARIOS_DIR
from cochlea.robots.serial.ik import UnreachableTarget
from cochlea.sim import load_scenario, unit_setups

JOINT = (SCENARIOS_DIR / "serial_joint.toml").read_text()
TASK = (SCENARIOS_DIR / "serial_task.toml").read_text()

CASES = {
    "missing key": (JOINT, "duration_s = 20.0\n", "", "duration_s", "the key is missing"),
    "unknown key": (JOINT, "duration_s = 20.0\n", "duration_s = 20.0\nspeed = 2\n", "speed",
                    "no such key here"),
    "quantity without unit": (JOINT, '["73 deg"', "[73", "unit[0].initial_joint[0]",
                              "'<formula in t> <unit>'"),
    "length where an angle belongs": (JOINT, '"83 deg"', '"0.083 m"',
                                      "unit[0].initial_joint[1]", "(an angle)"),
    "unknown function in a formula": (TASK, '"0.03*cos(a1) m"', '"0.03*cosh(a1) m"',
                                      "desired.leader[0]", "unknown function 'cosh'"),
    "unknown name in a formula": (TASK, '"0.03*sin(a1) m"', '"0.03*sin(b1) m"',
                                  "desired.leader[1]", "unknown name 'b1'"),
    "gain of wrong size": (JOINT, "alpha = [5.0, 4.0, 3.0]", "alpha = [5.0, 4.0]",
                           "unit[0].gains.alpha", "a list of 3 numbers"),
    "negative gain": (JOINT, "G_e = [0.05, 0.04, 0.003]", "G_e = [0.05, -0.04, 0.003]",
                      "unit[0].gains.G_e", "all positive"),
    "gain of the other controller": (JOINT, "alpha = [5.0, 4.0, 3.0]", "G_g = [5.0, 4.0, 3.0]",
                                     "unit[0].gains.alpha", "the key is missing"),
    "units out of order": (JOINT, 'name = "arm1"', 'name = "arm3"', "unit",
                           "units named, in order, 'arm1', 'arm2'"),
    "unknown variant": (JOINT, 'variant = "corrected"', 'variant = "best"', "control.variant",
                        "one of 'corrected', 'thesis'"),
    "both initial forms": (JOINT, 'initial_joint = ["73 deg", "83 deg", "110 deg"]',
                           'initial_joint = ["73 deg", "83 deg", "110 deg"]\n'
                           'initial_task = ["0.03 m", "0 m", "0 deg"]',
                           "unit[0].initial_joint", "exactly one of"),
    "time-varying initial state": (JOINT, '["73 deg"', '["73*t deg"', "unit[0].initial_joint",
                                   "must be a constant"),
    "encoder flag not a boolean": (JOINT, "[control]", "[plant]\nposition_encoder = 1\n\n"
                                   "[control]", "plant.position_encoder", "true or false"),
    # tomllib reads any integer whole; a check taking it as a float ended in an OverflowError
    # (found by putting 10**400 into every number of the shipped files: 308 of 528 crashed)
    "an integer beyond 64 bits": (JOINT, "duration_s = 20.0", "duration_s = 1" + "0" * 400,
                                  "duration_s", "an integer within 64 bits"),
    "an integer past Python's digits limit": (JOINT, "duration_s = 20.0",
                                              "duration_s = 1" + "0" * 5000, "(syntax)",
                                              "valid TOML"),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_scenario_names_the_key(tmp_path, case):
    text, old, new, key, expected = CASES[case]
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(DescriptionError) as info:
        load_scenario(path)
    assert str(info.value).startswith(f"{path}: {key}: expected"), str(info.value)
    assert expected in str(info.value)


@pytest.mark.parametrize("case", ["missing key", "unknown name in a formula",
                                  "encoder flag not a boolean"])
def test_a_scenario_read_from_its_text_is_refused_as_its_file(tmp_path, case):
    """A sweep's worker reads each sample's scenario from its text (no file written): the same
    refusal, naming the path it goes by; a good text gives the file's scenario."""
    text, old, new, key, expected = CASES[case]
    bad = text.replace(old, new, 1)
    path = tmp_path / "bad.toml"
    path.write_text(bad)
    with pytest.raises(DescriptionError) as from_file:
        load_scenario(path)
    with pytest.raises(DescriptionError) as from_text:
        load_scenario(tmp_path / "never_written.toml", text=bad)
    assert str(from_text.value) == str(from_file.value).replace("bad.toml", "never_written.toml")
    with pytest.raises(DescriptionError, match="valid TOML"):
        load_scenario("sample.toml", text="duration_s = [")
    good = load_scenario(tmp_path / "good.toml", text=JOINT)
    shipped = dataclasses.replace(load_scenario("serial_joint"), path=good.path, name=good.name)
    assert good.name == "good" and repr(good) == repr(shipped)


def test_unreachable_initial_pose_fails_before_the_run(tmp_path):
    path = tmp_path / "far.toml"
    path.write_text(TASK.replace('["0.028 m", "0.01 m", "-103 deg"]',
                                 '["0.4 m", "0.01 m", "-103 deg"]'))
    with pytest.raises(UnreachableTarget, match="out of reach"):
        unit_setups(load_scenario(path))


def test_unreachable_follower_trajectory_fails_before_the_run(tmp_path):
    """Arm 1 stretched out towards +x puts arm 2's mirrored target beyond arm 2's reach."""
    path = tmp_path / "wide.toml"
    leader = JOINT[JOINT.index("leader = ["):JOINT.index("]", JOINT.index("leader = [")) + 1]
    path.write_text(JOINT.replace(leader, 'leader = ["0 deg", "0 deg", "20*sin(t) deg"]'))
    with pytest.raises(UnreachableTarget, match=r"arm2's desired pose leaves the workspace at "
                                                r"t = \d+\.\d+ s"):
        unit_setups(load_scenario(path))


@pytest.mark.slow
def test_command_line_reports_unreachable_target_with_exit_2(tmp_path):
    path = tmp_path / "far.toml"
    path.write_text(TASK.replace('["0.028 m", "0.01 m", "-103 deg"]',
                                 '["0.4 m", "0.01 m", "-103 deg"]'))
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run",
         "--robot", "serial", "--space", "task", "--scenario", str(path), "--out", str(out)],
        capture_output=True, text=True)
    assert result.returncode == 2
    assert "out of reach" in result.stderr and "Traceback" not in result.stderr
    assert not out.exists()


def test_unreachable_is_a_user_error():
    assert issubclass(UnreachableTarget, CochleaError)


@pytest.mark.slow
def test_a_relative_description_is_relative_to_the_scenario(tmp_path, monkeypatch):
    """issue 25 papercut: a scenario's relative ``description`` names a file beside the
    scenario, whatever the working directory; an absolute path is unchanged."""
    from cochlea.resources import ROBOTS_DIR

    folder = tmp_path / "study"
    (folder / "robots").mkdir(parents=True)
    marked = (ROBOTS_DIR / "serial.toml").read_text().replace("keep_out_radius_m = 0.02",
                                                              "keep_out_radius_m = 0.017")
    (folder / "robots" / "mine.toml").write_text(marked)
    (folder / "s.toml").write_text(JOINT.replace('space = "joint"\n',
                                                 'space = "joint"\ndescription = '
                                                 '"robots/mine.toml"\n', 1))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    sc = load_scenario(folder / "s.toml")
    assert sc.system.keep_out_radius == 0.017
    assert sc.description == str(folder / "robots" / "mine.toml")
    assert len(unit_setups(sc)) == 2  # the setups load the same file again
    absolute = folder / "robots" / "mine.toml"
    (folder / "t.toml").write_text(JOINT.replace('space = "joint"\n',
                                                 f'space = "joint"\ndescription = "{absolute}"\n',
                                                 1))
    assert load_scenario(folder / "t.toml").description == str(absolute)
    # A bare name is still a shipped description.
    (folder / "u.toml").write_text(JOINT.replace('space = "joint"\n',
                                                 'space = "joint"\ndescription = "serial"\n', 1))
    assert load_scenario(folder / "u.toml").system.keep_out_radius == 0.02


@pytest.mark.slow
def test_the_estimate_bound_does_not_depend_on_the_machines_blas(monkeypatch):
    """The bound is written into the generated embedded C (``cochlea-codegen --check``
    compares it byte for byte): numpy's norm sums through the BLAS kernel of the CPU, and an
    AMD EPYC gave the realistic serial studies' bound another last bit than the machine that
    wrote generated_c/."""
    from cochlea.sim import setup as setup_mod

    sc = load_scenario("serial_joint_realistic")
    bounds = [u.bound for u in unit_setups(sc)]
    p = [float(v) for v in unit_setups(sc)[0].controller_model.p_nominal]
    total = 0.0
    for v in p:
        total += v * v
    assert bounds == [sc.estimate_bound * math.sqrt(total)] * 2
    assert abs(setup_mod.euclidean_norm(p) - math.hypot(*p)) <= 2 * math.ulp(math.hypot(*p))
    norm = np.linalg.norm  # another BLAS: numpy's norm one ulp off
    monkeypatch.setattr(np.linalg, "norm", lambda *a, **k: np.nextafter(norm(*a, **k), np.inf))
    assert [u.bound for u in setup_mod.unit_setups(load_scenario("serial_joint_realistic"),
                                                   cache=False)] == bounds
