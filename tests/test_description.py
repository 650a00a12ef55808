"""Loading robot descriptions: the shipped file is right, every kind of mistake is reported
with one clear error naming the file, the key and what was expected."""

from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest

from cochlea import DescriptionError, load_serial
from cochlea.resources import ROBOTS_DIR

SERIAL = (ROBOTS_DIR / "serial.toml").read_text()


def test_shipped_serial_description_holds_the_thesis_numbers():
    system = load_serial("serial")
    assert [a.name for a in system.arms] == ["arm1", "arm2"]
    assert np.allclose(system.arm("arm1").base_xyz, [0.101, -0.128, 0.0])
    assert np.allclose(system.arm("arm2").base_xyz, [-0.105, -0.105, 0.0])
    for arm in system.arms:
        assert [l.length for l in arm.links] == [0.105, 0.105, 0.04]
        assert [l.mass for l in arm.links] == [0.09518, 0.07878, 0.01119]
        for link in arm.links:
            assert np.allclose(link.com, [link.length / 2, 0, 0])
            assert link.inertia_com[2, 2] == pytest.approx(link.mass * link.length**2 / 12,
                                                           rel=1e-12)
            assert link.joint.type == "revolute"
            assert link.motor.model == "MX-64"
    ids = [l.motor.id for a in system.arms for l in a.links]
    assert ids == [1, 2, 3, 4, 5, 6]
    fit = system.arm("arm1").links[0].motor.fit
    assert (fit.a, fit.b, fit.x, fit.y) == (108.2, -15.47, "current_A", "torque_Ncm")
    # Degrees in the file, radians inside.
    assert system.arm("arm1").links[0].joint.position_limits[1] == pytest.approx(np.radians(170))


def _broken(tmp_path, old, new, count=1):
    assert old in SERIAL, old
    path = tmp_path / "broken.toml"
    path.write_text(SERIAL.replace(old, new, count))
    return path


CASES = {
    "missing key": ("mass_kg = 0.09518\n", "", "arm[0].link[0].mass_kg",
                    "positive number (kg) (the key is missing)"),
    "unknown key": ("mass_kg = 0.09518\n", "mass_kg = 0.09518\n  colour = \"red\"\n",
                    "arm[0].link[0].colour", "no such key here"),
    "wrong type": ("mass_kg = 0.07878", "mass_kg = \"heavy\"", "arm[0].link[1].mass_kg",
                   "a positive number (kg), got 'heavy'"),
    "boolean is not a number": ("length_m = 0.04", "length_m = true", "arm[0].link[2].length_m",
                                "a non-negative number (m)"),
    "negative mass": ("mass_kg = 0.01119", "mass_kg = -0.01119", "arm[0].link[2].mass_kg",
                      "positive number (kg), got -0.01119"),
    "inertia not positive definite": (
        "[1.18975e-06, 8.7446625e-05, 8.7446625e-05", "[1.18975e-06, 8.7446625e-05, -8.7e-05",
        "arm[0].link[0].inertia_com_kgm2", "positive definite"),
    "inertia breaks the triangle inequality": (
        "[1.18975e-06, 8.7446625e-05, 8.7446625e-05", "[1.0e-06, 1.0e-06, 8.7446625e-05",
        "arm[0].link[0].inertia_com_kgm2", "triangle inequality"),
    "unknown joint type": ('type = "revolute"', 'type = "spherical"', "arm[0].link[0].joint.type",
                           "one of 'revolute', 'prismatic'"),
    "zero axis": ("axis = [0.0, 0.0, 1.0]", "axis = [0.0, 0.0, 0.0]", "arm[0].link[0].joint.axis",
                  "non-zero direction"),
    "reversed limits": ("position_limits_deg = [-170.0, 170.0]",
                        "position_limits_deg = [170.0, -170.0]",
                        "arm[0].link[0].joint.position_limits_deg", "lower < upper"),
    "unit of another joint type": ("torque_limit_Nm = 2.5", "force_limit_N = 2.5",
                                   "arm[0].link[0].joint.torque_limit_Nm", "the key is missing"),
    "duplicate motor id": ("id = 4", "id = 1", "arm[1].link[0].motor.id",
                           "a motor ID not already used (by arm1.link1)"),
    "motor id out of range": ("id = 2", "id = 300", "arm[0].link[1].motor.id", "0..252"),
    "unknown motor": ('model = "MX-64"', 'model = "AX-12"', "arm[0].link[0].motor.model",
                      "one of 'MX-64', 'XM540-W270'"),
    "fit without units": ('x = "current_A"', 'x = "current"', "arm[0].link[0].motor.fit.x",
                          "'current_A'"),
    "wrong format": ('format = "cochlea-robot/1"', 'format = "urdf"', "format",
                     "the string 'cochlea-robot/1'"),
    "vector of wrong size": ("base_xyz_m = [0.101, -0.128, 0.0]", "base_xyz_m = [0.101, -0.128]",
                             "arm[0].base_xyz_m", "a list of 3 numbers in m"),
    "syntax error": ("name = \"arm1\"", "name = arm1", "(syntax)", "valid TOML"),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_description_names_file_key_and_expectation(tmp_path, case):
    old, new, key, expected = CASES[case]
    path = _broken(tmp_path, old, new)
    with pytest.raises(DescriptionError) as info:
        load_serial(path)
    message = str(info.value)
    assert message.startswith(f"{path}: {key}: expected "), message
    assert expected in message, message
    assert info.value.key == key


def _joint_names(names: list[str | None]) -> str:
    """The shipped description with arm1's joints named ``names`` (None: no name key, the
    default: jointK for linkK)."""
    head, *joints = SERIAL.split("  [arm.link.joint]\n")
    out = head
    for i, rest in enumerate(joints):
        name = names[i] if i < len(names) else None
        out += "  [arm.link.joint]\n" + (f'  name = "{name}"\n' if name else "") + rest
    return out


@pytest.mark.parametrize("names, key, expected", [
    ([None, "joint1"], "arm[0].link[1].joint.name", "link 0's joint is already called 'joint1'"),
    (["joint2", None], "arm[0].link[1]", "this link's joint is 'joint2' by default"),
    (["j", "j"], "arm[0].link[1].joint.name", "a joint name unique within the arm"),
], ids=["given-as-a-default", "default-as-given", "given-twice"])
def test_two_joints_of_an_arm_with_one_name_are_refused(tmp_path, names, key, expected):
    """Joint names, given or by default, name the model's joints and parameters and an exported
    URDF's joints. Before, two alike loaded (cochlea-model exit 0, 'joint1.Ia' twice among the
    parameters, an export that its own import refused). The other arm's are its own."""
    path = tmp_path / "dup.toml"
    path.write_text(_joint_names(names))
    with pytest.raises(DescriptionError) as info:
        load_serial(path)
    assert str(info.value).startswith(f"{path}: {key}: expected "), str(info.value)
    assert expected in str(info.value)
    path.write_text(_joint_names(["a", "b", "c", "a", "b", "c"]))  # per arm: allowed
    assert [link.joint.name for link in load_serial(path).arm("arm2").links] == ["a", "b", "c"]


def test_an_arm_of_more_than_16_joints_is_refused(tmp_path):
    """The model's cost grows with the cube of the joints: 30 took cochlea-model 11 s and
    0.4 GB, 60 over two minutes and 3.3 GB. 16 load; 17 are refused, naming the limit."""
    head, *links = SERIAL.split("  [[arm.link]]\n")
    arm1 = links[:3]
    last = arm1[2].split("[[arm]]")[0]  # link3 of arm1, without arm2 after it
    text = head + "".join("  [[arm.link]]\n" + l.replace('name = "link', f'name = "k{i}_')
                          .replace("id = ", f"id = {10 * i + 10} + 0 * ") for i, l in
                          enumerate([arm1[0], arm1[1]] * 8 + [last]))
    text = re.sub(r"id = (\d+) \+ 0 \* \d+", lambda m: f"id = {m.group(1)}", text)
    path = tmp_path / "long.toml"
    path.write_text(text)
    with pytest.raises(DescriptionError) as info:
        load_serial(path)
    assert "arm[0].link: expected at most 16 [[arm.link]] tables" in str(info.value)
    assert "not 17" in str(info.value)


def test_a_bare_name_that_is_also_a_local_file_or_folder_is_refused(tmp_path, monkeypatch,
                                                                     capsys):
    """`--description serial` with a folder ./serial loaded the shipped arms; a local file
    `myarm` was reported as models/robots/myarm.toml. Now the bare name is refused, naming
    both; `./myarm` is the local file; no option (the default) is the shipped one."""
    from cochlea.apps.cochlea_model import main as model_main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "serial").mkdir()
    (tmp_path / "myarm").write_text(SERIAL)
    assert model_main(["serial", "--description", "serial"]) == 2
    err = capsys.readouterr().err
    assert "names both the shipped" in err and str(tmp_path / "serial") in err
    assert model_main(["serial", "--description", "myarm"]) == 2
    err = capsys.readouterr().err
    assert "(there is none)" in err and str(tmp_path / "myarm") in err and "./myarm" in err
    assert model_main(["serial", "--description", "./myarm"]) == 0
    assert "description: myarm" in capsys.readouterr().out
    assert model_main(["serial"]) == 0  # the default: the shipped file
    assert load_serial("./myarm").path.name == "myarm"


def test_missing_file(tmp_path):
    with pytest.raises(DescriptionError, match="expected an existing robot description file"):
        load_serial(tmp_path / "nowhere.toml")


def test_command_line_reports_a_bad_description_without_traceback(tmp_path):
    path = _broken(tmp_path, "mass_kg = 0.07878", "mass_kg = -1")
    result = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_model", "--description", str(path)],
        capture_output=True, text=True)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.strip() == (f"cochlea-model: {path}: arm[0].link[1].mass_kg: expected a "
                                     "positive number (kg), got -1")
