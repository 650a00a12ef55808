"""``cochlea-urdf``: URDF import against Pinocchio's own URDF parser, the snaps, the round trip
through export, every class of file that cannot be a serial chain, and the starter scenario."""

from __future__ import annotations

import math
import re
from importlib import metadata
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import cochlea
from cochlea.apps.cochlea_urdf import main
from cochlea.errors import EXIT_USER_ERROR
from cochlea.robots.serial import load_serial
from cochlea.robots.serial.description import rpy_matrix
from cochlea.robots.serial.urdf import UrdfError, export_urdf, import_urdf, rpy_of

from .conftest import DATA, ev

ARM4 = DATA / "arm4.urdf"


def _example_robot(relative: str) -> Path | None:
    """A URDF of the example-robot-data package (a test dependency), or None without it."""
    try:
        dist = metadata.distribution("example-robot-data")
    except metadata.PackageNotFoundError:
        return None
    path = Path(str(dist.locate_file(
        f"cmeel.prefix/share/example-robot-data/robots/{relative}")))
    return path if path.is_file() else None


UR5 = _example_robot("ur_description/urdf/ur5_robot.urdf")
SO101 = _example_robot("so_arm_description/urdf/so101.urdf")
needs_erd = pytest.mark.skipif(UR5 is None or SO101 is None,
                               reason="example-robot-data is not installed")


def _imported(tmp_path: Path, urdf: Path, name: str = "robot.toml", **kw) -> Path:
    out = tmp_path / name
    out.write_text(import_urdf(urdf, **kw).text, encoding="utf-8")
    return out


def _pin_snapped(tmp_path: Path, text: str) -> Path:
    """The fixture as Pinocchio should read it: the angles cochlea snaps written exactly, the
    continuous joint as a revolute one with the limits the import gives it (Pinocchio's
    continuous joint has two configuration coordinates)."""
    text = (text.replace('"1.5708', f'"{math.pi / 2!r}').replace(" 1.5708 ", f" {math.pi / 2!r} ")
            .replace("1.57079632679", repr(math.pi / 2)).replace("3.14159", repr(math.pi))
            .replace('type="continuous"', 'type="revolute"')
            .replace('<limit velocity="4.0"', '<limit lower="-6.3" upper="6.3" velocity="4.0"'))
    path = tmp_path / "pin.urdf"
    path.write_text(text, encoding="utf-8")
    return path


def _relative(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def _against_pinocchio(ours, urdf: Path, rng, n: int = 50) -> float:
    """The worst relative difference of M, C qd + G and G between our model and Pinocchio's
    model of ``urdf`` on random states."""
    theirs = pin.buildModelFromUrdf(str(urdf))
    assert theirs.nq == theirs.nv == ours.nq
    data = theirs.createData()
    worst = 0.0
    for _ in range(n):
        q = rng.uniform(-np.pi, np.pi, ours.nq)
        qd = rng.uniform(-2.0, 2.0, ours.nq)
        M_pin = pin.crba(theirs, data, q)
        M_pin = np.triu(M_pin) + np.triu(M_pin, 1).T
        G_ours = ev(ours.G, q)
        worst = max(
            worst,
            _relative(ev(ours.M, q), M_pin),
            _relative(ev(ours.C, q, qd) @ qd + G_ours, pin.nonLinearEffects(theirs, data, q, qd)),
            _relative(G_ours, pin.computeGeneralizedGravity(theirs, data, q)),
        )
    return worst


# --------------------------------------------------------------------------------------------
# Against Pinocchio
# --------------------------------------------------------------------------------------------


@needs_erd
def test_ur5_matches_pinocchios_urdf_parser(tmp_path, rng):
    """example-robot-data's UR5 (6 DoF, pi/2 written to 1e-11): M, C qd + G and G to 1e-9."""
    ours = cochlea.model("serial", description=_imported(tmp_path, UR5))
    assert [j.name for j in ours.joints] == [
        "shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
        "wrist_2_joint", "wrist_3_joint"]
    assert _against_pinocchio(ours, UR5, rng) <= 1e-9


def test_fixture_matches_pinocchio(tmp_path, rng):
    """The hand-written 4-DoF arm: fixed joints before, inside and after the chain, a side
    body, rotated inertial frames, a tilted axis, a prismatic joint."""
    ours = cochlea.model("serial", description=_imported(tmp_path, ARM4))
    assert ours.nq == 4
    assert [j.type for j in ours.joints] == ["revolute", "revolute", "prismatic", "revolute"]
    pin_file = _pin_snapped(tmp_path, ARM4.read_text(encoding="utf-8"))
    assert _against_pinocchio(ours, pin_file, rng) <= 1e-9
    # Guard: the comparison is not vacuous (gravity on every tilted joint, coupling everywhere).
    q = rng.uniform(-1, 1, 4)
    assert np.abs(ev(ours.G, q))[1:].min() > 1e-3  # the first axis is vertical
    assert np.abs(ev(ours.M, q)).min() > 1e-6


def test_limits_names_and_friction_carry_over(tmp_path):
    system = load_serial(_imported(tmp_path, ARM4))
    pan, lift, extend, roll = (link.joint for link in system.arms[0].links)
    assert pan.name == "pan" and pan.position_limits == (-2.5, 2.5)
    assert pan.velocity_limit == 3.0 and pan.effort_limit == 8.0
    assert pan.actuator.viscous == 0.05 and pan.actuator.coulomb == 0.1
    assert extend.type == "prismatic" and extend.position_limits == (-0.05, 0.1)
    assert extend.effort_limit == 40.0 and extend.velocity_limit == 0.2
    assert roll.position_limits == pytest.approx((-2 * math.pi, 2 * math.pi))
    np.testing.assert_allclose(lift.axis, [0.0, 0.6, 0.8])
    assert [link.name for link in system.arms[0].links] == ["shoulder", "upper", "slider",
                                                             "wrist"]


def test_an_effort_limit_above_the_motors_stall_torque_is_noted(tmp_path):
    """arm4's pan and lift allow 8 N m, above the XM430-W350's 4.1 N m stall torque: kept as
    the URDF says (a limit the drive reaches first), and each said in the import's notes and
    the description's header; the 3 N m roll joint is not."""
    imported = import_urdf(ARM4, motors=["XM430-W350"])
    said = [n for n in imported.notes if "stall torque" in n]
    assert [n.split("'")[1] for n in said] == ["pan", "lift"]
    assert said[0] == ("joint 'pan': the URDF's effort limit 8 N m is above the XM430-W350's "
                       "stall torque 4.1 N m (the drive saturates first): consider "
                       "torque_limit_Nm <= 4.1")
    assert f"# * {said[1]}" in imported.text
    assert load_serial(_imported(tmp_path, ARM4)).arms[0].links[0].joint.effort_limit == 8.0


def test_rpy_of_inverts_the_rotation(rng):
    for _ in range(200):
        rpy = rng.uniform(-np.pi, np.pi, 3)
        if rng.random() < 0.2:
            rpy[1] = rng.choice([-1, 1]) * np.pi / 2  # gimbal lock
        np.testing.assert_allclose(rpy_matrix(rpy_of(rpy_matrix(rpy))), rpy_matrix(rpy),
                                   atol=1e-12)


# --------------------------------------------------------------------------------------------
# Snaps
# --------------------------------------------------------------------------------------------


def test_snaps_are_reported_and_exact(tmp_path, capsys):
    out = tmp_path / "arm4.toml"
    assert main(["import", str(ARM4), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    snaps = [line for line in printed.splitlines() if line.startswith("snapped: ")]
    assert len(snaps) == 4
    assert "joint 'lift' origin rpy[2]: 3.14159 rad snapped to 180 deg" in printed
    assert "link 'upper' inertial origin rpy[1]: 1.5708 rad snapped to 90 deg" in printed
    text = out.read_text(encoding="utf-8")
    assert "origin_rpy_deg = [90.0, 0.0, 180.0]" in text  # exact, not 179.99984...
    assert "3.14159 rad snapped" in text  # the header keeps the record


def test_an_angle_beyond_the_tolerance_is_not_snapped(tmp_path):
    text = ARM4.read_text(encoding="utf-8").replace('rpy="1.57079632679 0 3.14159"',
                                                    'rpy="1.5707 0 3.1415"')
    bad = tmp_path / "a.urdf"
    bad.write_text(text, encoding="utf-8")
    result = import_urdf(bad)
    assert not any("'lift'" in s for s in result.snaps)
    lift = result.system.arms[0].links[1].joint
    assert lift.origin_rpy[0] == pytest.approx(1.5707, abs=1e-12)


@needs_erd
@pytest.mark.slow
def test_so101_is_snapped_then_exported_exactly(tmp_path, rng):
    """SO-101 writes pi/2 as 1.5708 (3.7e-6 rad off): snapped and reported; the snapped model
    agrees with Pinocchio reading our export of it."""
    result = import_urdf(SO101, motors=["MX-64"])
    assert sum("1.5708 rad snapped to" in s for s in result.snaps) >= 4
    description = tmp_path / "so101.toml"
    description.write_text(result.text, encoding="utf-8")
    exported = tmp_path / "so101_out.urdf"
    exported.write_text(export_urdf(load_serial(description)), encoding="utf-8")
    ours = cochlea.model("serial", description=description)
    assert _against_pinocchio(ours, exported, rng, n=20) <= 1e-9
    # the unsnapped file differs by about the snaps' size, no more
    assert 1e-7 < _against_pinocchio(ours, SO101, rng, n=5) < 1e-4


@needs_erd
@pytest.mark.slow
def test_snapping_keeps_the_base_parameters_of_the_true_arm(tmp_path, monkeypatch):
    """Why snap: SO-101's 1.5708 for pi/2 adds two base parameters (36 -> 38), which
    identification would refuse as rank-deficient; snapped, the count is the UR5's 36."""
    import cochlea.robots.serial.urdf as urdf

    def count() -> int:
        path = _imported(tmp_path, SO101)
        return len(cochlea.model("serial", description=path, parameterisation="base")
                   .param_names)

    assert count() == 36
    monkeypatch.setattr(urdf, "SNAP_TOLERANCE_RAD", 0.0)
    assert count() == 38


# --------------------------------------------------------------------------------------------
# Round trip
# --------------------------------------------------------------------------------------------


def _same_dynamics(a, b, rng, n=30):
    for _ in range(n):
        q = rng.uniform(-np.pi, np.pi, a.nq)
        qd = rng.uniform(-2.0, 2.0, a.nq)
        assert _relative(ev(a.M, q), ev(b.M, q)) <= 1e-9
        assert _relative(ev(a.C, q, qd), ev(b.C, q, qd)) <= 1e-9
        Ga, Gb = ev(a.G, q), ev(b.G, q)
        assert np.abs(Ga - Gb).max() <= 1e-9 * max(1.0, np.abs(Gb).max())


@pytest.mark.parametrize("source", ["fixture", "ur5", "shipped"])
@pytest.mark.slow
def test_import_of_export_round_trips(tmp_path, rng, source):
    if source == "ur5" and UR5 is None:
        pytest.skip("example-robot-data is not installed")
    first = {"fixture": lambda: _imported(tmp_path, ARM4, "first.toml"),
             "ur5": lambda: _imported(tmp_path, UR5, "first.toml"),
             "shipped": lambda: "serial"}[source]()
    exported = tmp_path / "out.urdf"
    assert main(["export", str(first), "--out", str(exported)]) == 0
    second = tmp_path / "second.toml"
    assert main(["import", str(exported), "--out", str(second),
                 "--motor", "MX-64"]) == 0
    a = cochlea.model("serial", description=first)
    b = cochlea.model("serial", description=second)
    assert [j.name for j in a.joints] == [j.name for j in b.joints]
    limits = [(*j.position_limits, j.velocity_limit, j.effort_limit) for j in a.joints]
    assert np.allclose(limits, [(*j.position_limits, j.velocity_limit, j.effort_limit)
                                for j in b.joints], rtol=0, atol=1e-12)
    _same_dynamics(a, b, rng)


# --------------------------------------------------------------------------------------------
# What cannot be a serial chain: one line, exit 2
# --------------------------------------------------------------------------------------------


def _edit(old: str, new: str, count: int = 1):
    def edit(text: str) -> str:
        assert old in text, old
        return text.replace(old, new, count)
    return edit


_ROLL_LIMIT = '<limit velocity="4.0" effort="3.0"/>'
_SLIDER = '<link name="slider">'
BAD = {
    "floating": (_edit('name="extend" type="prismatic"', 'name="extend" type="floating"'),
                 "floating"),
    "planar": (_edit('name="pan" type="revolute"', 'name="pan" type="planar"'), "planar"),
    "unknown type": (_edit('name="pan" type="revolute"', 'name="pan" type="ball"'), "'ball'"),
    "branch": (_edit("</robot>", '<link name="side"><inertial><mass value="0.1"/><inertia '
                     'ixx="1e-4" iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial>'
                     '</link><joint name="side_j" type="revolute"><parent link="upper"/>'
                     '<child link="side"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" '
                     'velocity="1" effort="1"/></joint></robot>'), "branches at link 'upper'"),
    "two parents": (_edit("</robot>", '<joint name="loop" type="fixed"><parent link="wrist"/>'
                          '<child link="upper"/></joint></robot>'), "two parents"),
    "self loop": (_edit("</robot>", '<joint name="loop" type="fixed"><parent link="wrist"/>'
                        '<child link="wrist"/></joint></robot>'), "closed loop"),
    "mimic": (_edit(_ROLL_LIMIT, _ROLL_LIMIT + '<mimic joint="pan"/>'), "mimics"),
    "zero mass": (_edit('<mass value="0.2"/>', '<mass value="0"/>'), "positive mass"),
    "negative mass": (_edit('<mass value="0.2"/>', '<mass value="-0.2"/>'), "positive mass"),
    "not positive definite": (_edit('ixx="0.00015" iyy="0.0002" izz="0.00018"',
                                    'ixx="-0.00015" iyy="0.0002" izz="0.00018"'),
                              "not positive definite"),
    "triangle": (_edit('ixx="0.00015" iyy="0.0002" izz="0.00018"',
                       'ixx="0.00005" iyy="0.00005" izz="0.00018"'), "triangle inequality"),
    "no limit": (_edit('<limit lower="-2.5" upper="2.5" velocity="3.0" effort="8.0"/>', ""),
                 "<limit> is missing"),
    "no velocity": (_edit('velocity="3.0" effort="8.0"', 'effort="8.0"'), "velocity"),
    "no position limits": (_edit('lower="-1.8" upper="1.8" ', ""), "position limits"),
    "inverted limits": (_edit('lower="-1.8" upper="1.8"', 'lower="1.8" upper="-1.8"'),
                        "lower < upper"),
    "zero axis": (_edit('<axis xyz="0 0.6 0.8"/>', '<axis xyz="0 0 0"/>'), "not a direction"),
    "nan": (_edit('xyz="0.02 0.03 0.06"', 'xyz="0.02 nan 0.06"'), "finite"),
    "bad number": (_edit('xyz="0.02 0.03 0.06"', 'xyz="0.02 0.03"'), "3 finite numbers"),
    # float() reads each of these as a number: 0_2 is 2 (a tenfold mass), the others 0.2 or 2
    "underscore": (_edit('<mass value="0.2"/>', '<mass value="0_2"/>'), "'0_2'"),
    "arabic digits": (_edit('<mass value="0.2"/>', '<mass value="\u0660.\u0662"/>'),
                      "finite number"),
    "full-width digits": (_edit('<mass value="0.2"/>', '<mass value="\uff10.\uff12"/>'),
                          "finite number"),
    "infinity word": (_edit('velocity="3.0" effort="8.0"', 'velocity="Infinity" effort="8.0"'),
                      "finite number"),
    "underscore reduction": (_edit("<mechanicalReduction>", "<mechanicalReduction>1_"),
                             "mechanicalReduction"),
    "undefined link": (_edit('<child link="wrist"/>', '<child link="hand"/>'), "not defined"),
    "duplicate link": (_edit("</robot>", '<link name="wrist"/></robot>'), "two links"),
    "two roots": (_edit("</robot>", '<link name="island"/></robot>'), "not one tree"),
    "malformed": (_edit("</robot>", "</robto>"), "not well-formed XML"),
    "not a robot": (lambda t: "<sdf version='1.6'/>", "<robot>"),
    "empty": (lambda t: "", "not well-formed XML"),
    "doctype": (lambda t: t.replace("<robot", '<!DOCTYPE r [<!ENTITY a "aaaa">]><robot', 1),
                "document type"),
    "nothing moves": (lambda t: re.sub(r'type="(revolute|prismatic|continuous)"', 'type="fixed"',
                                       t), "nothing to move"),
    "huge mass": (_edit('<mass value="0.2"/>', '<mass value="5000"/>'), "mass_kg"),
}
BAD["no inertial"] = (lambda t: re.sub(r'(<link name="wrist">)\s*<inertial>.*?</inertial>',
                                       r"\1", t, flags=re.S)
                      .replace('<inertial><origin xyz="0.01 0 0"/><mass value="0.1"/>\n      '
                               '<inertia ixx="0.00002" iyy="0.00002" izz="0.00003" ixy="0" '
                               'ixz="0" iyz="0"/></inertial>', ""), "no inertial")


def _run_bad(tmp_path: Path, capsys, args: list[str]) -> str:
    out = tmp_path / "out.toml"
    code = main(["import", *args, "--out", str(out)])
    captured = capsys.readouterr()
    assert code == EXIT_USER_ERROR, captured
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("cochlea-urdf: "), captured.err
    assert not out.exists()
    return lines[0]


def main_line(tmp_path: Path, capsys, args: list[str]) -> str:
    code = main(["import", *args])
    captured = capsys.readouterr()
    assert code == EXIT_USER_ERROR, captured
    assert len(captured.err.strip().splitlines()) == 1
    return captured.err


@pytest.mark.parametrize("case", list(BAD))
def test_what_cannot_be_a_serial_chain_is_one_line(tmp_path, capsys, case):
    edit, expected = BAD[case]
    bad = tmp_path / "bad.urdf"
    bad.write_text(edit(ARM4.read_text(encoding="utf-8")), encoding="utf-8")
    assert expected in _run_bad(tmp_path, capsys, [str(bad)])


def test_names_casadi_cannot_take_become_names_it_can(tmp_path):
    """URDF names with a hyphen, a space, an accent, a doubled or trailing underscore (all
    legal in URDF) become description names the model builds with: they name CasADi and C
    functions (``robot_arm_M_p``). Before, a hyphen reached CasADi and stopped the build with
    its own traceback."""
    text = ARM4.read_text(encoding="utf-8")
    for old, new in [('"arm4"', '"so-101 bras articul\u00e9"'), ('"shoulder"', '"shoulder-link"'),
                     ('"upper"', '"upper__arm_"'), ('"pan"', '"pan joint"'),
                     ('"lift"', '"_lift-2"')]:
        assert old in text
        text = text.replace(old, new)
    urdf = tmp_path / "names.urdf"
    urdf.write_text(text, encoding="utf-8")
    ours = cochlea.model("serial", description=_imported(tmp_path, urdf))
    system = load_serial(tmp_path / "robot.toml")
    assert system.name == "so_101_bras_articul"
    links = system.arms[0].links
    assert [link.name for link in links] == ["shoulder_link", "upper_arm", "slider", "wrist"]
    assert [link.joint.name for link in links] == ["pan_joint", "lift_2", "extend", "roll"]
    assert np.linalg.eigvalsh(ev(ours.M, np.zeros(4))).min() > 0


@pytest.mark.parametrize("name", ["my-arm", "arm__1", "arm_", "1arm", "a" * 65])
def test_a_description_name_casadi_cannot_take_is_one_line(tmp_path, name):
    """Written by hand, such a name is refused when the description loads, naming the key and
    the rule, before any model is built."""
    text = _imported(tmp_path, ARM4).read_text(encoding="utf-8")
    assert '\nname = "arm4"' in text
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace('\nname = "arm4"', f'\nname = "{name}"'), encoding="utf-8")
    with pytest.raises(cochlea.errors.DescriptionError) as err:
        load_serial(bad)
    assert "system.name" in str(err.value) and "single underscores" in str(err.value)
    assert "\n" not in str(err.value)


def _chain_urdf(n: int, name: str = "j") -> str:
    body = ['<robot name="long"><link name="l0"/>']
    for i in range(1, n + 1):
        body.append(f'<link name="l{i}"><inertial><mass value="0.1"/><inertia ixx="1e-4" '
                    'iyy="1e-4" izz="1e-4" ixy="0" ixz="0" iyz="0"/></inertial></link>'
                    f'<joint name="{name}{i}" type="revolute"><parent link="l{i - 1}"/>'
                    f'<child link="l{i}"/><origin xyz="0.05 0 0"/><axis xyz="0 0 1"/>'
                    '<limit lower="-1" upper="1" velocity="1" effort="1"/></joint>')
    return "".join(body) + "</robot>"


def test_a_chain_longer_than_an_arm_is_refused_in_a_short_line(tmp_path, capsys):
    """A 17-joint chain: before, imported (and cochlea-model ran for seconds to minutes as the
    chain grew); a 5000-joint one was refused with a 29 KB line about --ids the user never
    gave. Now a short line about the chain's length; other lists of names stay bounded."""
    long = tmp_path / "long.urdf"
    long.write_text(_chain_urdf(17), encoding="utf-8")
    line = _run_bad(tmp_path, capsys, [str(long)])
    assert "the chain has 17 moving joints" in line and "at most 16" in line
    assert "--ids" not in line
    long.write_text(_chain_urdf(5000), encoding="utf-8")
    assert len(_run_bad(tmp_path, capsys, [str(long)])) < 300
    named = tmp_path / "named.urdf"
    named.write_text(_chain_urdf(3, "j" + "x" * 5000), encoding="utf-8")
    assert len(_run_bad(tmp_path, capsys, [str(named), "--ids", "1,2"])) < 400
    assert len(_run_bad(tmp_path, capsys, [str(named), "--motor", "nope=MX-64"])) < 400


def test_file_level_mistakes_are_one_line(tmp_path, capsys):
    assert "no such file" in _run_bad(tmp_path, capsys, [str(tmp_path / "missing.urdf")])
    assert "a folder" in _run_bad(tmp_path, capsys, [str(tmp_path)])
    latin = tmp_path / "latin.urdf"
    latin.write_bytes(ARM4.read_bytes().replace(b"hand-written", b"hand-\xe9crit"))
    assert "not UTF-8" in _run_bad(tmp_path, capsys, [str(latin)])


def test_option_mistakes_are_one_line(tmp_path, capsys):
    arm4 = str(ARM4)
    assert "unknown motor model 'XL-320'" in _run_bad(tmp_path, capsys,
                                                      [arm4, "--motor", "XL-320"])
    assert "no joint 'elbow'" in _run_bad(tmp_path, capsys, [arm4, "--motor", "elbow=MX-64"])
    assert "4 joints" in _run_bad(tmp_path, capsys, [arm4, "--ids", "1,2,3"])
    assert "distinct" in _run_bad(tmp_path, capsys, [arm4, "--ids", "1,1,2,3"])
    # An empty item (was read as 1,2,3,4); int() and float() take "1_0" (10), "nan" and other
    # scripts' digits: each refused in one line, nothing written.
    for option, value in [("--ids", "1,,2,3,4"), ("--ids", "1,2,3,1_0"), ("--ids", "1,2,3,\u0664"),
                          ("--keep-out-radius-m", "1_0"), ("--keep-out-radius-m", "nan")]:
        assert repr(value) in _run_bad(tmp_path, capsys, [arm4, option, value])
    assert "[0.0001, 1]" in _run_bad(tmp_path, capsys, [arm4, "--transmission",
                                                      "extend=lead_screw:0_1"])
    assert "ending in .toml" in main_line(tmp_path, capsys, [arm4, "--out", "robot"])
    assert "no such link" in _run_bad(tmp_path, capsys, [arm4, "--tip", "hand"])
    assert "not below" in _run_bad(tmp_path, capsys, [arm4, "--base", "slider", "--tip",
                                                      "upper"])


def test_export_names_its_fixed_joints_apart_from_the_arms(tmp_path, capsys):
    """A description joint called base_link_fixed or tool_fixed: export wrote two joints of
    that name (which its own import refused); the fixed joints now take other names."""
    text = _imported(tmp_path, ARM4).read_text(encoding="utf-8")
    for old, new in [('name = "pan"', 'name = "base_link_fixed"'),
                     ('name = "roll"', 'name = "tool_fixed"'),
                     ("base_xyz_m = ", "tool_xyz_m = [0.05, 0.0, 0.0]\nbase_xyz_m = ")]:
        assert old in text
        text = text.replace(old, new)
    first = tmp_path / "named.toml"
    first.write_text(text, encoding="utf-8")
    exported, second = tmp_path / "named.urdf", tmp_path / "again.toml"
    assert main(["export", str(first), "--out", str(exported)]) == 0
    joints = re.findall(r'<joint name="([^"]+)" type=', exported.read_text(encoding="utf-8"))
    assert len(joints) == len(set(joints)) == 6, joints
    assert main(["import", str(exported), "--out", str(second)]) == 0, capsys.readouterr().err
    arm = load_serial(second).arms[0]
    assert [link.joint.name for link in arm.links] == [
        "base_link_fixed", "lift", "extend", "tool_fixed"]
    assert np.allclose(arm.tool_xyz, [0.05, 0.0, 0.0])


def test_an_output_that_is_an_input_or_another_output_is_refused(tmp_path, capsys):
    """Before anything is written: ``export in.toml --out in.toml`` overwrote the description
    with URDF XML, and ``import --out same.toml --scenario-out same.toml`` left a scenario
    naming itself (both exit 0). A hard link and a spelling through ``..`` are the same file."""
    description = _imported(tmp_path, ARM4)
    before = description.read_bytes()
    (tmp_path / "sub").mkdir()
    linked = tmp_path / "linked.toml"
    linked.hardlink_to(description)
    for out in (description, tmp_path / "sub" / ".." / "robot.toml", linked):
        assert main(["export", str(description), "--out", str(out)]) == EXIT_USER_ERROR
        err = capsys.readouterr().err
        assert "is the input description" in err and len(err.strip().splitlines()) == 1
    assert description.read_bytes() == before
    same = tmp_path / "same.toml"
    assert "are the same file" in _run_bad(tmp_path, capsys, [
        str(ARM4), "--scenario-out", str(tmp_path / "sub" / ".." / "out.toml")])
    assert main(["import", str(ARM4), "--out", str(same), "--scenario-out",
                 str(same)]) == EXIT_USER_ERROR
    assert "are the same file" in capsys.readouterr().err and not same.exists()
    urdf_named_toml = tmp_path / "arm.toml"
    urdf_named_toml.write_bytes(ARM4.read_bytes())
    assert main(["import", str(urdf_named_toml), "--out", str(urdf_named_toml)]) \
        == EXIT_USER_ERROR
    assert "is the input URDF" in capsys.readouterr().err
    assert urdf_named_toml.read_bytes() == ARM4.read_bytes()


@pytest.mark.parametrize("name", ["it's", 'say "hi"', "back\\slash", "del\x7f", "esc\x1b[1m",
                                  "new\nline", "smile\U0001F600", "bras articul\u00e9"])
def test_any_file_name_gives_valid_toml_and_urdf(tmp_path, capsys, name):
    """The starter names its description in a TOML string: written as '{x!r}', a quote or a
    control character in --out's name made it invalid TOML (exit 0). The URDF's own name goes
    into the description's header comment: a DEL, newline or ESC there made the import refuse
    a valid URDF ("not a valid cochlea description: (syntax)"). Export's XML comment names
    the description: '--' or a control character there is no XML."""
    from cochlea.sim import load_scenario

    folder = tmp_path / "r"
    folder.mkdir()
    urdf = folder / f"{name}.urdf"
    urdf.write_bytes(ARM4.read_bytes())
    out, starter = folder / f"{name}.toml", folder / "s.toml"
    assert main(["import", str(urdf), "--out", str(out), "--scenario-out", str(starter)]) == 0, \
        capsys.readouterr().err
    assert load_scenario(starter).system.path == out
    exported = folder / "x.urdf"
    weird = folder / f"a--{name}-.toml"
    weird.write_bytes(out.read_bytes())
    assert main(["export", str(weird), "--out", str(exported)]) == 0
    assert main(["import", str(exported), "--out", str(folder / "back.toml")]) == 0


def test_the_starter_stays_inside_a_tiny_joint_range(tmp_path, capsys):
    """A joint whose range is 5.7e-6 deg wide around 57.29578 deg: the centre written with
    .6g (57.2958) lay outside it, and the starter was refused when loaded."""
    from cochlea.sim import load_scenario, unit_setups

    urdf = tmp_path / "tiny.urdf"
    urdf.write_text(_edit('lower="-1.8" upper="1.8"', 'lower="1.0" upper="1.0000001"')(
        ARM4.read_text(encoding="utf-8")), encoding="utf-8")
    out, starter = tmp_path / "robot.toml", tmp_path / "s.toml"
    assert main(["import", str(urdf), "--out", str(out), "--scenario-out", str(starter)]) == 0
    (setup,) = unit_setups(load_scenario(starter))
    lo, hi = load_serial(out).arms[0].links[1].joint.position_limits
    assert lo <= setup.x0[1] <= hi


def test_a_starter_scenario_drives_a_prismatic_joint(tmp_path, capsys):
    """The fixture's prismatic joint has a <transmission>: the starter is written, moves it in
    metres, and its plan has a motor on every joint (the carriage's m/rad from the URDF)."""
    from cochlea.dynamixel.drives import joint_drives
    from cochlea.sim import load_scenario

    out, starter = tmp_path / "robot.toml", tmp_path / "s.toml"
    assert main(["import", str(ARM4), "--out", str(out), "--scenario-out", str(starter)]) == 0
    scenario = load_scenario(starter)
    assert scenario.system.path == out
    assert "0.01*sin" in starter.read_text() and " m\"" in starter.read_text()
    drives = {d.name: d for d in joint_drives("serial", out)}
    assert drives["arm.slider"].type == "prismatic"
    assert drives["arm.slider"].ratio == pytest.approx(0.01, rel=1e-15)


def test_tip_picks_one_path_through_a_branch(tmp_path, capsys):
    edit, _ = BAD["branch"]
    branched = tmp_path / "branched.urdf"
    branched.write_text(edit(ARM4.read_text(encoding="utf-8")), encoding="utf-8")
    out = tmp_path / "tip.toml"
    assert main(["import", str(branched), "--out", str(out), "--tip", "wrist",
                 "--motor", "MX-64", "--motor", "extend=XM540-W270", "--ids", "5,6,7,8"]) == 0
    printed = capsys.readouterr().out
    assert "left out: joint 'side_j'" in printed
    arm = load_serial(out).arms[0]
    assert [link.joint.name for link in arm.links] == ["pan", "lift", "extend", "roll"]
    assert [link.motor.model for link in arm.links] == ["MX-64", "MX-64", "XM540-W270", "MX-64"]
    assert [link.motor.id for link in arm.links] == [5, 6, 7, 8]
    assert all(link.motor.fit.placeholder for link in arm.links)
    # a shorter chain: base and tip inside the arm
    assert main(["import", str(branched), "--out", str(out), "--base", "upper", "--tip",
                 "slider"]) == 0
    assert [link.joint.name for link in load_serial(out).arms[0].links] == ["extend"]


def test_the_header_says_what_is_an_estimate(tmp_path):
    text = _imported(tmp_path, ARM4).read_text(encoding="utf-8")
    header = text.split('format = "cochlea-robot/1"')[0]
    assert "imported from the URDF arm4.urdf" in header
    assert "PLACEHOLDER" in header and "calibrate" in header
    assert "10.6 N m / 4.4 A" in header  # the XM540-W270's datasheet stall figures


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.data())
@pytest.mark.slow
def test_fuzzed_urdfs_give_a_description_or_a_clear_error(tmp_path, data):
    """Random cuts, insertions and replacements of the fixture, and random bytes: a
    description or a UrdfError, never a traceback."""
    text = ARM4.read_bytes()
    kind = data.draw(st.sampled_from(["cut", "insert", "replace", "number", "bytes"]))
    if kind == "bytes":
        mutated = data.draw(st.binary(max_size=400))
    else:
        i = data.draw(st.integers(0, len(text)))
        j = data.draw(st.integers(i, min(len(text), i + 40)))
        piece = data.draw(st.binary(max_size=20) | st.sampled_from(
            [b"<", b">", b"/>", b'"', b"<joint", b"</link>", b"nan", b"-1e308", b"1e999",
             b'type="planar"', b"<mimic/>", b"\xff", b"&amp;", b"<![CDATA[", b"\x00"]))
        if kind == "cut":
            mutated = text[:i] + text[j:]
        elif kind == "insert":
            mutated = text[:i] + piece + text[i:]
        elif kind == "replace":
            mutated = text[:i] + piece + text[j:]
        else:
            numbers = list(re.finditer(rb"-?\d+\.?\d*(e-?\d+)?", text))
            m = numbers[data.draw(st.integers(0, len(numbers) - 1))]
            value = data.draw(st.sampled_from([b"0", b"-0.0", b"1e300", b"-1", b"inf", b"1e-30",
                                               b"3.14159", b"", b"x"]))
            mutated = text[:m.start()] + value + text[m.end():]
    path = tmp_path / "fuzz.urdf"
    path.write_bytes(mutated)
    try:
        result = import_urdf(path)
    except UrdfError as exc:
        assert "\n" not in str(exc)
    else:
        assert 1 <= len(result.system.arms[0].links) <= 4


# --------------------------------------------------------------------------------------------
# The starter scenario
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("source", ["fixture", "ur5"])
@pytest.mark.slow
def test_the_starter_scenario_converges(tmp_path, source, monkeypatch):
    """import -> the starter scenario -> a short simulation that converges, the description
    found beside the scenario from another working directory."""
    from cochlea.apps import report
    from cochlea.sim import load_scenario, simulate

    if source == "fixture":  # the slider made revolute: a run of the revolute joints' starter
        urdf = tmp_path / "arm4r.urdf"
        urdf.write_text(ARM4.read_text(encoding="utf-8").replace(
            'name="extend" type="prismatic"', 'name="extend" type="revolute"'), encoding="utf-8")
    elif UR5 is None:
        pytest.skip("example-robot-data is not installed")
    else:
        urdf = UR5
    folder = tmp_path / "robot"
    folder.mkdir()
    assert main(["import", str(urdf), "--out", str(folder / "robot.toml"),
                 "--scenario-out", str(folder / "starter.toml")]) == 0
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    scenario = load_scenario(folder / "starter.toml")
    result = simulate(scenario, duration=4.0, kernels="casadi")
    summary = report.summary(result)
    assert summary["converged"] and not summary["diverged"], summary
    for unit in summary["units"].values():
        for c in unit["tracked"].values():
            assert c["initial_abs_error"] > 1e-3
            assert c["converged"]
