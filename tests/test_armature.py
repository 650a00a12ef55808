"""Actuator armature (reflected rotor inertia) in the descriptions and the models (issue 11,
item 1, first part): ``Ia`` on the diagonal of ``M`` and nothing else, in both derivations and
both robots; an identifiable parameter of every parameterisation; the shipped descriptions,
which declare none, keep the thesis's rigid-link model exactly."""

from __future__ import annotations

import re

import numpy as np
import pytest

import cochlea
from cochlea.resources import ROBOTS_DIR
from cochlea.robots.parallel import SCENARIO_START
from cochlea.sim.scenario import Plant
from cochlea.sim.setup import INERTIAL_NAMES, perturbed_parameters

SERIAL_ARMATURE = (4e-3, 3e-3, 2e-3)  # kg m^2 per joint: the MX-64's order of magnitude at 200:1
#: The shipped descriptions declare their own armatures: these tests set theirs.
WITHOUT_ARMATURE = re.compile(r"(?m)^\s*armature_kg(m2)? = .*\n")
PARALLEL_ARMATURE = {"left.th1": 4e-3, "left.th2": 3e-3, "slider.d1": 18.0,  # kg at the slider
                     "right.th1": 4e-3, "right.th2": 3e-3}


@pytest.fixture(scope="module")
def serial_with_armature(tmp_path_factory):
    text = WITHOUT_ARMATURE.sub("", (ROBOTS_DIR / "serial.toml").read_text())
    count = iter(range(100))
    text = re.sub(r"(?m)^(\s*velocity_limit_rad_s = .*)$",
                  lambda m: f"{m.group(1)}\n  armature_kgm2 = {SERIAL_ARMATURE[next(count) % 3]}",
                  text)
    path = tmp_path_factory.mktemp("armature") / "serial_armature.toml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def parallel_with_armature(tmp_path_factory):
    text = WITHOUT_ARMATURE.sub("", (ROBOTS_DIR / "parallel.toml").read_text())
    for joint, value in PARALLEL_ARMATURE.items():
        side, name = joint.split(".")
        key = "armature_kg" if name == "d1" else "armature_kgm2"
        text = re.sub(rf"(?m)^(\s*\[{re.escape(side)}\.{name}\]\n)", rf"\g<1>  {key} = {value}\n",
                      text)
    path = tmp_path_factory.mktemp("armature") / "parallel_armature.toml"
    path.write_text(text)
    return path


def _random_states(rng, n, count=5):
    return [(rng.uniform(-2, 2, n), rng.uniform(-1, 1, n), rng.uniform(-1, 1, n))
            for _ in range(count)]


@pytest.mark.parametrize("method", ["newton-euler", "lagrange"])
def test_serial_armature_is_inertia_on_the_diagonal_only(serial_with_armature, method, rng):
    plain = cochlea.model("serial", method=method)
    geared = cochlea.model("serial", method=method, description=serial_with_armature,
                      actuators="armature")
    for q, qd, _ in _random_states(rng, 3):
        assert np.allclose(np.array(geared.M(q)) - np.array(plain.M(q)),
                           np.diag(SERIAL_ARMATURE), rtol=0, atol=1e-15)
        assert np.allclose(np.array(geared.C(q, qd)), np.array(plain.C(q, qd)), rtol=0, atol=1e-15)
        assert np.allclose(np.array(geared.G(q)), np.array(plain.G(q)), rtol=0, atol=1e-15)


def test_newton_euler_equals_lagrange_with_armature(serial_with_armature, rng):
    ne = cochlea.model("serial", arm="arm2", description=serial_with_armature,
                      actuators="armature")
    la = cochlea.model("serial", arm="arm2", method="lagrange", description=serial_with_armature,
                      actuators="armature")
    for q, qd, qdd in _random_states(rng, 3):
        for f in ("M", "G"):
            assert np.allclose(np.array(getattr(ne, f)(q)), np.array(getattr(la, f)(q)), rtol=0,
                               atol=1e-12)
        assert np.allclose(np.array(ne.C(q, qd)), np.array(la.C(q, qd)), rtol=0, atol=1e-12)
        assert np.allclose(np.array(ne.inverse_dynamics(q, qd, qdd)),
                           np.array(la.inverse_dynamics(q, qd, qdd)), rtol=0, atol=1e-12)


@pytest.mark.parametrize("parameterisation", ["inertial", "base", "mass"])
def test_regressor_identity_with_armature(serial_with_armature, parallel_with_armature,
                                          parameterisation, rng):
    for robot, path, n in (("serial", serial_with_armature, 3),
                           ("parallel", parallel_with_armature, 5)):
        m = cochlea.model(robot, parameterisation=parameterisation, description=path,
                      actuators="armature")
        for _ in range(3):
            q = SCENARIO_START + rng.uniform(-0.05, 0.05, 5) if robot == "parallel" else \
                rng.uniform(-2, 2, n)
            qd, qd_r, qdd_r = (rng.uniform(-1, 1, n) for _ in range(3))
            lhs = np.array(m.Y(q, qd, qd_r, qdd_r)) @ m.p_nominal
            rhs = (np.array(m.M(q)) @ qdd_r + np.array(m.C(q, qd)) @ qd_r
                   + np.array(m.G(q)).ravel())
            assert np.allclose(lhs, rhs, rtol=1e-10, atol=1e-12), (robot, parameterisation)


def test_armature_parameters_in_every_parameterisation(serial_with_armature):
    full = cochlea.model("serial", description=serial_with_armature,
                      actuators="armature").parameters
    assert full.names[-3:] == ("joint1.Ia", "joint2.Ia", "joint3.Ia")
    assert full.si_units[-3:] == ("kg m^2",) * 3
    assert np.allclose(full.nominal[-3:], SERIAL_ARMATURE)
    mass = cochlea.model("serial", parameterisation="mass",
                         description=serial_with_armature,
                      actuators="armature").parameters
    assert mass.names == ("link1.m", "link2.m", "link3.m", "joint1.Ia", "joint2.Ia", "joint3.Ia")
    # In the base set, joint 1's armature only adds to the constant part of M11, exactly as
    # link 1's Izz does, so the two merge; joints 2 and 3 add parameters of their own.
    plain = cochlea.model("serial", parameterisation="base").parameters
    base = cochlea.model("serial", parameterisation="base",
                         description=serial_with_armature,
                      actuators="armature").parameters
    assert len(base.names) == len(plain.names) + 2
    assert any("joint1.Ia" in meaning and "link1.Izz" in meaning for meaning in base.meanings)


def test_parallel_armature_is_inertia_on_the_diagonal_only(parallel_with_armature, rng):
    plain = cochlea.model("parallel")
    geared = cochlea.model("parallel", description=parallel_with_armature,
                      actuators="armature")
    assert geared.parameters.names[-5:] == tuple(f"{j}.Ia" for j in PARALLEL_ARMATURE)
    assert geared.parameters.si_units[-5:] == ("kg m^2", "kg m^2", "kg", "kg m^2", "kg m^2")
    for _ in range(3):
        q = SCENARIO_START + rng.uniform(-0.05, 0.05, 5)
        qd = rng.uniform(-1, 1, 5)
        assert np.allclose(np.array(geared.M(q)) - np.array(plain.M(q)),
                           np.diag(list(PARALLEL_ARMATURE.values())), rtol=0, atol=1e-12)
        assert np.allclose(np.array(geared.C(q, qd)), np.array(plain.C(q, qd)), rtol=0, atol=1e-12)
        assert np.allclose(np.array(geared.G(q)), np.array(plain.G(q)), rtol=0, atol=1e-12)


def test_the_thesis_models_have_no_actuator_terms():
    """actuators="none" (the default): the thesis's rigid links, no parameter beyond the bodies'."""
    for robot in ("serial", "parallel"):
        assert not any(n.endswith(".Ia") for n in cochlea.model(robot).parameters.names)


@pytest.mark.parametrize("edit, key", [
    ("  armature_kgm2 = -1e-3\n", "armature_kgm2"),   # negative inertia
    ("  armature_kg = 1e-3\n", "armature_kg"),         # the prismatic key on a revolute joint
    ('  armature_kgm2 = "4e-3"\n', "armature_kgm2"),  # a string
])
def test_bad_armature_names_the_key(tmp_path, edit, key):
    text = WITHOUT_ARMATURE.sub("", (ROBOTS_DIR / "serial.toml").read_text()).replace(
        "  velocity_limit_rad_s = 6.0\n", "  velocity_limit_rad_s = 6.0\n" + edit, 1)
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(cochlea.DescriptionError, match=key):
        cochlea.load_serial(path)


def test_scaled_masses_and_payload_leave_the_armature_alone(serial_with_armature):
    m = cochlea.model("serial", description=serial_with_armature,
                      actuators="armature")
    full = m.parameters
    plant = Plant(mass_scale=np.array([1.3, 1.3, 1.3]), payload_kg=0.05)
    p = perturbed_parameters(full, plant, {"link3": np.array([0.08, 0.0, 0.0])})
    assert np.array_equal(p[-3:], full.nominal[-3:])
    assert p[full.names.index("link1.m")] == pytest.approx(1.3 * full.nominal[0])
    assert p[full.names.index("link3.m")] == pytest.approx(
        1.3 * full.nominal[full.names.index("link3.m")] + 0.05)


def test_the_perturbed_parameters_are_the_name_by_name_ones(serial_with_armature):
    """The parameters' owners are read once per name list: every parameter of a scaled body
    (its armature too, as it always was) and every payload term, the same numbers bit for bit
    as reading each name again."""
    full = cochlea.model("serial", description=serial_with_armature, actuators="armature"
                         ).parameters
    plant = Plant(mass_scale=np.array([0.83, 1.21, 1.07]), payload_kg=0.037)
    points = {"link3": np.array([0.08, 0.01, -0.02]), "link2": np.array([0.03])}
    expected = np.asarray(full.nominal, float).copy()
    bodies = list(dict.fromkeys(n.rsplit(".", 1)[0] for n in full.names
                                if n.rsplit(".", 1)[1] in INERTIAL_NAMES))
    for body, scale in zip(bodies, plant.mass_scale, strict=True):
        for i, name in enumerate(full.names):
            if name.rsplit(".", 1)[0] == body:
                expected[i] *= scale
    for body, point in points.items():
        x, y, z = (list(point) + [0.0, 0.0])[:3]
        m = plant.payload_kg
        added = {"m": m, "mx": m * x, "my": m * y, "mz": m * z, "Ixx": m * (y * y + z * z),
                 "Iyy": m * (x * x + z * z), "Izz": m * (x * x + y * y), "Ixy": -m * x * y,
                 "Ixz": -m * x * z, "Iyz": -m * y * z}
        for i, name in enumerate(full.names):
            owner, kind = name.rsplit(".", 1)
            if owner == body and kind in added:
                expected[i] += added[kind]
    for _ in range(2):  # the second through the owners read the first time
        assert perturbed_parameters(full, plant, points).tobytes() == expected.tobytes()
