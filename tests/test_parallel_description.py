"""Loading the parallel mechanism's description: the shipped file holds the thesis's numbers and
the stated assumptions; every kind of mistake is one clear error naming file, key, expectation."""

from __future__ import annotations

import numpy as np
import pytest

from cochlea import DescriptionError, load_serial
from cochlea.resources import ROBOTS_DIR
from cochlea.robots.parallel.description import SIDE_BODIES, load_parallel

PARALLEL = (ROBOTS_DIR / "parallel.toml").read_text()


def test_shipped_description_holds_the_thesis_numbers():
    """Thesis (3.66), the same on both sides; rods m l^2 / 12; SI inside."""
    system = load_parallel("parallel")
    assert (system.link_length, system.base_offset, system.rod_length) == (0.1, 0.12, 0.19)
    assert np.array_equal(system.gravity, [0.0, -9.81])
    assert system.slider_mass == 0.136
    for side in system.sides:
        for name in ("link1", "link2", "link3", "link4"):
            body = side.body(name)
            assert body.mass == 0.25
            assert np.allclose(body.com, [0.05, 0.0])
            assert body.inertia_com == pytest.approx(0.25 * 0.1**2 / 12, rel=1e-12)
        assert side.body("link5").mass == 1.0
        assert np.array_equal(side.body("link5").com, [0.0, 0.0])
        assert side.body("link5").inertia_com == 5.416e-4  # the stated choice
        rod = side.body("link7")
        assert rod.mass == 0.364 and np.allclose(rod.com, [0.095, 0.0])
        assert rod.inertia_com == pytest.approx(0.364 * 0.19**2 / 12, rel=1e-12)
        assert [b.name for b in side.bodies] == [f"{side.name}.{b}" for b in SIDE_BODIES]
    assert [j.name for j in system.joints] == ["left.th1", "left.th2", "slider.d1", "right.th1",
                                               "right.th2"]
    assert [j.type for j in system.joints] == ["revolute"] * 2 + ["prismatic"] + ["revolute"] * 2
    # Degrees in the file, radians inside; the right side's limits mirror the left's.
    left, right = system.left, system.right
    assert left.th1.position_limits == pytest.approx(np.radians([45.0, 180.0]))
    assert right.th2.position_limits == pytest.approx(np.pi - np.array(
        left.th2.position_limits)[::-1])
    assert system.d1.position_limits == (0.0, 0.15)
    # Motors: four MX-64 and the XM540 of Table C.1 on the slider, with its pinion.
    assert [j.motor.model for j in system.joints] == ["MX-64"] * 2 + ["XM540-W270"] + \
        ["MX-64"] * 2
    assert [j.motor.id for j in system.joints] == [2, 3, 1, 4, 5]
    fit = system.d1.motor.fit
    assert (fit.a, fit.b, fit.x, fit.y) == (97.2, -0.567, "current_A", "torque_Ncm")
    t = system.d1.transmission
    assert (t.kind, t.size, t.ratio) == ("pinion", 0.02, 0.02)
    assert t.motor_torque(10.0) == pytest.approx(0.2)  # N m for 10 N
    assert all(j.transmission is None for j in system.joints if j.type == "revolute")


def test_lead_screw_transmission(tmp_path):
    path = tmp_path / "screw.toml"
    path.write_text(PARALLEL.replace('kind = "pinion"\n  radius_m = 0.02',
                                     'kind = "lead_screw"\n  lead_m = 0.008'))
    t = load_parallel(path).d1.transmission
    assert t.ratio == pytest.approx(0.008 / (2 * np.pi))
    assert t.motor_angle(0.008) == pytest.approx(2 * np.pi)  # one revolution per lead


def _broken(tmp_path, old, new):
    assert old in PARALLEL, old
    path = tmp_path / "broken.toml"
    path.write_text(PARALLEL.replace(old, new, 1))
    return path


CASES = {
    "missing key": ("link_length_m = 0.1 ", "", "geometry.link_length_m",
                    "a positive number (m) (the key is missing)"),
    "unknown key": ("mass_kg = 0.136\n", "mass_kg = 0.136\ncolour = \"red\"\n", "slider.colour",
                    "no such key here"),
    "wrong type": ("mass_kg = 0.364", "mass_kg = \"heavy\"", "left.link7.mass_kg",
                   "a positive number (kg), got 'heavy'"),
    "negative mass": ("mass_kg = 1.0", "mass_kg = -1.0", "left.link5.mass_kg",
                      "a positive number (kg), got -1.0"),
    "non-positive inertia": ("inertia_com_kgm2 = 5.416e-4", "inertia_com_kgm2 = 0.0",
                             "left.link5.inertia_com_kgm2", "a positive number (kg m^2"),
    "com of wrong size": ("com_m = [0.095, 0.0]", "com_m = [0.095, 0.0, 0.0]",
                          "left.link7.com_m", "a list of 2 numbers in m"),
    "reversed limits": ("position_limits_deg = [45.0, 180.0]",
                        "position_limits_deg = [180.0, 45.0]", "left.th1.position_limits_deg",
                        "lower < upper"),
    "reversed stroke": ("position_limits_m = [0.0, 0.15]", "position_limits_m = [0.15, 0.0]",
                        "slider.d1.position_limits_m", "lower < upper"),
    "revolute unit on the slider": ("force_limit_N = 100.0", "torque_limit_Nm = 100.0",
                                    "slider.d1.force_limit_N", "the key is missing"),
    "missing motor": ("[right.th2.motor]", "[right.th2.engine]", "right.th2.motor",
                      "a table (the key is missing)"),
    "duplicate motor id": ("id = 5", "id = 1", "right.th2.motor.id",
                           "a motor ID not already used (by slider.d1)"),
    "unknown motor": ('model = "XM540-W270"', 'model = "XM-540"', "slider.d1.motor.model",
                      "one of 'MX-64', 'XM540-W270'"),
    "missing transmission": ("[slider.d1.transmission]", "[slider.d1.gearbox]",
                             "slider.d1.transmission", "a table (the key is missing)"),
    "unknown transmission": ('kind = "pinion"', 'kind = "belt"', "slider.d1.transmission.kind",
                             "one of 'pinion', 'lead_screw'"),
    "non-positive pinion": ("radius_m = 0.02", "radius_m = 0.0",
                            "slider.d1.transmission.radius_m", "a positive number (m"),
    "rod shorter than the sleeve clearance": (
        "min_pivot_distance_m = 0.03", "min_pivot_distance_m = 0.3",
        "geometry.min_pivot_distance_m", "below rod_length_m = 0.19"),
    "gravity in 3-D": ("gravity_m_s2 = [0.0, -9.81]", "gravity_m_s2 = [0.0, -9.81, 0.0]",
                       "system.gravity_m_s2", "a list of 2 numbers in m/s^2"),
    "wrong kind": ('kind = "parallel"', 'kind = "serial"', "system.kind", "one of 'parallel'"),
    "missing body": ("[right.link3]", "[right.link8]", "right.link3", "the key is missing"),
    "wrong format": ('format = "cochlea-robot/1"', 'format = "cochlea-robot/2"', "format",
                     "the string 'cochlea-robot/1'"),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_bad_description_names_file_key_and_expectation(tmp_path, case):
    old, new, key, expected = CASES[case]
    path = _broken(tmp_path, old, new)
    with pytest.raises(DescriptionError) as info:
        load_parallel(path)
    message = str(info.value)
    assert message.startswith(f"{path}: {key}: expected "), message
    assert expected in message, message
    assert info.value.key == key


def test_missing_file(tmp_path):
    with pytest.raises(DescriptionError, match="expected an existing robot description file"):
        load_parallel(tmp_path / "nowhere.toml")


def test_each_loader_refuses_the_other_kind():
    with pytest.raises(DescriptionError, match=r"system\.kind: expected one of 'serial'"):
        load_serial("parallel")
    with pytest.raises(DescriptionError, match=r"system\.kind: expected one of 'parallel'"):
        load_parallel("serial")
