"""The motor keys the bridge needs: direction, zero_offset_deg, current_limit_mA. Defaults,
validation with the loader's usual errors, and their effect on the conversions."""

from __future__ import annotations

import math

import pytest

from cochlea import DescriptionError, load_serial
from cochlea.dynamixel.drives import joint_drives
from cochlea.resources import ROBOTS_DIR
from cochlea.robots.parallel import load_parallel

SERIAL = (ROBOTS_DIR / "serial.toml").read_text()
PARALLEL = (ROBOTS_DIR / "parallel.toml").read_text()
FIRST_MOTOR = 'id = 1\n  fit = { a = 108.2, b = -15.47, x = "current_A", y = "torque_Ncm" }\n'


def _variant(tmp_path, old, new, text=SERIAL, name="serial.toml"):
    assert old in text, old
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


def test_shipped_descriptions_state_the_mapping():
    for motor in [link.motor for arm in load_serial().arms for link in arm.links] + \
            [j.motor for j in load_parallel().joints]:
        assert (motor.direction, motor.zero_offset, motor.current_limit_mA) == (1, 0.0, None)
    assert SERIAL.count("zero_offset_deg = ") == 6 and PARALLEL.count("zero_offset_deg = ") == 5


def test_the_keys_default_when_absent(tmp_path):
    text = SERIAL.replace("  direction = 1", "  # no direction").replace(
        "  zero_offset_deg = 0.0", "  # no offset")
    path = tmp_path / "bare.toml"
    path.write_text(text)
    motor = load_serial(path).arms[0].links[0].motor
    assert (motor.direction, motor.zero_offset, motor.current_limit_mA) == (1, 0.0, None)


def test_values_are_read_in_si(tmp_path):
    assert SERIAL.index(FIRST_MOTOR) < SERIAL.index("direction = 1")  # arm1.link1's keys
    text = SERIAL.replace("direction = 1", "direction = -1", 1).replace(
        "zero_offset_deg = 0.0", "zero_offset_deg = 180.0\n  current_limit_mA = 1500.0", 1)
    path = tmp_path / "serial.toml"
    path.write_text(text)
    motor = load_serial(path).arms[0].links[0].motor
    assert motor.direction == -1
    assert motor.zero_offset == pytest.approx(math.pi)
    assert motor.current_limit_mA == 1500.0
    drive = joint_drives("serial", path)[0]
    assert drive.current_limit_lsb == math.ceil(1500.0 / 3.36)
    # q = direction * (theta - zero): the motor at 180 deg is joint zero, at 270 deg joint -90.
    assert drive.q(2048) == pytest.approx(0.0)
    assert drive.q(3072) == pytest.approx(-math.pi / 2)
    assert float(drive.effort(drive.goal_current_lsb(0.5))) == pytest.approx(0.5, abs=0.004)
    assert drive.goal_current_lsb(0.5) < 0  # the motor turns the other way


CASES = {
    "direction not +-1": ("direction = 1", "direction = 2", "arm[0].link[0].motor.direction",
                          "1 or -1"),
    "direction a boolean": ("direction = 1", "direction = true",
                            "arm[0].link[0].motor.direction", "1 or -1"),
    "direction a float": ("direction = 1", "direction = 1.0",
                          "arm[0].link[0].motor.direction", "1 or -1"),
    "offset not a number": ("zero_offset_deg = 0.0", 'zero_offset_deg = "zero"',
                            "arm[0].link[0].motor.zero_offset_deg", "a number (deg)"),
    "current limit negative": ("zero_offset_deg = 0.0",
                               "zero_offset_deg = 0.0\n  current_limit_mA = -5.0",
                               "arm[0].link[0].motor.current_limit_mA", "a positive number"),
    "current limit above the model's": ("zero_offset_deg = 0.0",
                                        "zero_offset_deg = 0.0\n  current_limit_mA = 7000",
                                        "arm[0].link[0].motor.current_limit_mA",
                                        "up to the MX-64's 6521.76 mA"),
    "unknown key": ("zero_offset_deg = 0.0", "zero_offset_deg = 0.0\n  offset_deg = 3.0",
                    "arm[0].link[0].motor.offset_deg", "current_limit_mA, direction, fit, id, "
                                                      "model, zero_offset_deg"),
}


@pytest.mark.parametrize("case", CASES)
def test_mistakes_are_reported(tmp_path, case):
    old, new, key, expected = CASES[case]
    with pytest.raises(DescriptionError) as info:
        load_serial(_variant(tmp_path, old, new))
    message = str(info.value)
    assert f": {key}: expected" in message and expected in message, message


def test_the_parallel_loader_reads_the_same_keys(tmp_path):
    old = 'id = 1\n  fit = { a = 97.2, b = -0.567, x = "current_A", y = "torque_Ncm" }\n' \
          '  direction = 1'  # the slider's motor, the first in the file
    path = _variant(tmp_path, old, old.replace("direction = 1", "direction = -1"), PARALLEL,
                    "parallel.toml")
    assert load_parallel(path).d1.motor.direction == -1
    path = _variant(tmp_path, "direction = 1", "direction = 0", PARALLEL, "parallel.toml")
    with pytest.raises(DescriptionError, match=r"slider\.d1\.motor\.direction: expected 1 or -1"):
        load_parallel(path)
    largest = "current_limit_mA = 5600"  # above the XM540-W270's 5506.43 mA
    path = _variant(tmp_path, old, old + "\n  " + largest, PARALLEL, "parallel.toml")
    with pytest.raises(DescriptionError, match="up to the XM540-W270's 5506.43 mA"):
        load_parallel(path)
