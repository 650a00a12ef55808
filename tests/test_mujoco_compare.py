"""bench/mujoco_compare.py's MJCF (issue 30): written from the description as cochlea loads it.

MuJoCo is a bench-only dependency, so these tests do not import it: they read the XML with the
standard library. Whether MuJoCo's dynamics of that XML equal cochlea's is checked where it is
used, in the bench, and gates the ratio it reports (accelerations and one RK4 step to 1e-9).
"""

from __future__ import annotations

import dataclasses
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from cochlea.robots.serial import load_serial
from cochlea.robots.serial.description import joint_rotation, rpy_matrix

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "bench"))

import mujoco_compare  # noqa: E402  (bench/, as bench/run.py imports it)


def numbers(element, key):
    return np.array([float(v) for v in element.get(key).split()])


def rotation(quat):
    """The rotation matrix of a unit quaternion ``[w, x, y, z]``."""
    w, x, y, z = quat
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


@pytest.fixture(scope="module")
def serial():
    return load_serial("serial")


def chain(root):
    """The nested bodies below the base body, outermost first."""
    base = root.find("worldbody/body")
    bodies, body = [], base
    while (body := body.find("body")) is not None:
        bodies.append(body)
    return base, bodies


def test_the_mjcf_is_the_loaded_arm(serial):
    arm = serial.arms[0]
    root = ET.fromstring(mujoco_compare.mjcf(serial, arm, 1e-3))
    option = root.find("option")
    assert option.get("integrator") == "RK4"
    assert float(option.get("timestep")) == 1e-3
    assert np.array_equal(numbers(option, "gravity"), serial.gravity)
    assert option.find("flag").get("contact") == "disable"
    assert root.find(".//geom") is None  # nothing to collide, no inertia from geometry
    assert root.find("compiler").get("inertiafromgeom") == "false"
    base, bodies = chain(root)
    assert np.array_equal(numbers(base, "pos"), arm.base_xyz)
    assert np.allclose(rotation(numbers(base, "quat")), arm.base_rotation, atol=1e-15)
    assert base.find("joint") is None and base.find("inertial") is None  # welded, massless
    assert [b.get("name") for b in bodies] == [link.name for link in arm.links]
    for body, link in zip(bodies, arm.links):
        (joint,) = body.findall("joint")
        assert joint.get("type") == "hinge"
        assert np.array_equal(numbers(joint, "axis"), link.joint.axis)
        assert joint.get("limited") == "false"
        # The ideal plant: no armature, damping or friction on the joint.
        assert {"armature", "damping", "frictionloss"}.isdisjoint(joint.attrib)
        assert np.array_equal(numbers(body, "pos"), link.joint.origin_xyz)
        inertial = body.find("inertial")
        assert float(inertial.get("mass")) == link.mass
        assert np.array_equal(numbers(inertial, "pos"), link.com)
        I = link.inertia_com
        assert np.array_equal(numbers(inertial, "fullinertia"),
                              [I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])
    # The second link sits at the first's length: the description's default joint origin.
    assert numbers(bodies[1], "pos")[0] == arm.links[0].length == 0.105


def test_turned_frames_off_diagonal_inertia_armature_and_damping(serial):
    """What the shipped arm 1 leaves at zero still reaches the XML: a rolled base, a turned
    and offset joint, a prismatic joint, products of inertia, armature and damping."""
    arm = serial.arms[0]
    links = list(arm.links)
    turned = dataclasses.replace(links[1].joint, origin_xyz=np.array([0.1, 0.02, -0.01]),
                                 origin_rpy=np.array([0.3, -0.2, 2.9]))
    slider = dataclasses.replace(links[2].joint, type="prismatic",
                                 axis=np.array([1.0, 0.0, 0.0]))
    inertia = links[0].inertia_com + np.array([[0, 1e-7, -2e-7], [1e-7, 0, 3e-7],
                                               [-2e-7, 3e-7, 0]])
    links[0] = dataclasses.replace(links[0], inertia_com=inertia)
    links[1] = dataclasses.replace(links[1], joint=turned)
    links[2] = dataclasses.replace(links[2], joint=slider)
    arm = dataclasses.replace(arm, links=tuple(links), base_roll=0.4, base_pitch=-1.2,
                              base_yaw=3.1)
    root = ET.fromstring(mujoco_compare.mjcf(serial, arm, 5e-4, armature=True,
                                             damping=np.array([0.0, 0.01, 0.0])))
    base, bodies = chain(root)
    assert np.allclose(rotation(numbers(base, "quat")), arm.base_rotation, atol=1e-15)
    assert np.allclose(rotation(numbers(bodies[1], "quat")), joint_rotation(turned),
                       atol=1e-15)
    assert np.array_equal(numbers(bodies[1], "pos"), [0.1, 0.02, -0.01])
    assert np.array_equal(numbers(bodies[0].find("inertial"), "fullinertia")[3:],
                          [1e-7, -2e-7, 3e-7])
    joints = [b.find("joint") for b in bodies]
    assert [j.get("type") for j in joints] == ["hinge", "hinge", "slide"]
    assert [float(j.get("armature")) for j in joints] == [
        link.joint.actuator.armature for link in arm.links]
    assert [j.get("damping") for j in joints] == [None, "0.01", None]
    assert float(root.find("option").get("timestep")) == 5e-4


@pytest.mark.parametrize("rpy", [(0, 0, 0), (0, 0, np.pi), (np.pi, 0, 0), (0, np.pi, 0),
                                 (np.pi / 2, 0.1, -3.0), (3.1, -1.5, 0.2), (-2.0, 1.0, 2.5)])
def test_the_quaternion_is_the_rotation(rpy):
    """Every branch of the conversion (trace or each diagonal element largest)."""
    R = rpy_matrix(np.array(rpy, float))
    q = mujoco_compare.quaternion(R)
    assert abs(np.linalg.norm(q) - 1) < 1e-15 and q[0] >= 0
    assert np.allclose(rotation(q), R, atol=1e-15)


def test_a_bad_timestep_is_refused(serial):
    with pytest.raises(ValueError, match="timestep must be a positive number of seconds"):
        mujoco_compare.mjcf(serial, serial.arms[0], 0.0)


def test_the_section_without_mujoco_says_how_to_install_it(monkeypatch):
    """The bench extra missing: one line naming it, raised so the section says why."""
    monkeypatch.setitem(sys.modules, "mujoco", None)  # import mujoco now raises ImportError
    with pytest.raises(RuntimeError, match=r"pip install -e '\.\[bench\]'"):
        mujoco_compare.bench(None, None)


def test_the_relative_difference_is_against_the_largest_value():
    assert mujoco_compare.relative([1.0, 2.0], [1.0, 4.0]) == 0.5
    assert mujoco_compare.relative([1.0, 2.0], [1.0, 4.0], scale=[0.0, 20.0]) == 0.1


@pytest.mark.slow  # the scenario's set-ups: about 0.3 s of CPU
def test_a_different_arm_gets_no_time_and_no_ratio(monkeypatch, tmp_path):
    """Above the tolerance nothing is timed, and the section says the arms differ."""
    import types

    from cochlea.kernels import library as ckernels

    fake = types.SimpleNamespace(__version__="0.0",
                                 MjModel=types.SimpleNamespace(from_xml_path=lambda path: path))
    monkeypatch.setitem(sys.modules, "mujoco", fake)
    monkeypatch.setattr(mujoco_compare, "WORK", tmp_path)
    monkeypatch.setattr(mujoco_compare, "ROOT", tmp_path.parent)
    monkeypatch.setattr(mujoco_compare, "check",
                        lambda *_: {"qacc_max_rel": 2e-9, "step_max_rel": 1e-14})

    def never(*_):
        raise AssertionError("timed although the arms differ")

    monkeypatch.setattr(mujoco_compare, "build_harness", never)
    row = mujoco_compare.bench(ckernels.load(), never)
    assert row["same_arm"] is False and "ratio" not in row
    text = "\n".join(mujoco_compare.markdown(row))
    assert "**Not the same arm**" in text and "2.0e-09" in text
    assert "mj_step / plant step" not in text and "| 0." not in text
    # The arm the XML was written for: the scenario's unit, its period.
    root = ET.parse(tmp_path / "serial_joint_arm1.xml").getroot()
    assert root.find("option").get("timestep") == "0.001"


def test_the_section_reports_both_times_and_their_ratio():
    row = {"scenario": "serial_joint", "unit": "arm1", "period_s": 1e-3, "plant_substeps": 1,
           "plant_kernel": "serial_arm1_plant_step", "plant_operations": 840,
           "mujoco": "4.0.0", "states": 50, "tolerance": 1e-9, "xml": "x.xml",
           "qacc_max_rel": 1.8e-14, "step_max_rel": 1.5e-14, "same_arm": True,
           "plant_c_s": 2.87e-7, "mujoco_c_s": 3.981e-6, "mujoco_rollout_s": 6.569e-6,
           "mujoco_python_s": 7.5e-6, "ratio": 3.981e-6 / 2.87e-7, "load_before": 1.99,
           "load_after": 2.01}
    text = "\n".join(mujoco_compare.markdown(row))
    assert "| 0.287 | 3.981 | 6.569 | 7.50 | 13.9x |" in text
    assert "worst 1.8e-14" in text and "Load average (1 min) 1.99 before and 2.01" in text
    assert "parallel mechanism" in text
