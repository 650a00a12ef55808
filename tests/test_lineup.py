"""The Dynamixel lineup as data (issue 27, items 1-3): every model of
``cochlea/dynamixel/models`` at its e-Manual addresses, descriptions on other models than the
robots' two, what a model cannot do refused up front in one line, a broken data file one line.

The expected addresses and sizes below are written from the ROBOTIS e-Manual control tables,
not from the data files:

* X series and MX(2.0) (one layout): XM430-W350
  https://emanual.robotis.com/docs/en/dxl/x/xm430-w350/#control-table, XL330-M288
  https://emanual.robotis.com/docs/en/dxl/x/xl330-m288/#control-table, XC330-T288
  https://emanual.robotis.com/docs/en/dxl/x/xc330-t288/#control-table, XH430-V350
  https://emanual.robotis.com/docs/en/dxl/x/xh430-v350/#control-table, XM430-W210, XH430-W210,
  XH430-W350, XM540-W150, XH540-W270, XH540-V270, XL330-M077, XC330-M181, XC330-M288,
  XC330-T181, XW540-T140, MX-106(2.0) (the same addresses and sizes on all these pages),
  MX-64(2.0) (/work/shared/reference/dynamixel.md).
* P series: PH54-200-S500-R https://emanual.robotis.com/docs/en/dxl/p/ph54-200-s500-r/,
  PH42-020-S300-R https://emanual.robotis.com/docs/en/dxl/p/ph42-020-s300-r/, PM54-060-S250-R
  https://emanual.robotis.com/docs/en/dxl/p/pm54-060-s250-r/ (the same addresses).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel import control_table as ct
from cochlea.dynamixel.drives import check_baud, joint_drives
from cochlea.errors import CochleaError, DescriptionError
from cochlea.robots import robot
from cochlea.runtime.backend import BackendError
from cochlea.sim import load_scenario, simulate

DATA = Path(__file__).parent / "data"

#: The items the toolkit uses: (address, size in bytes) per layout, from the e-Manual pages.
EMANUAL_ITEMS = {
    "x": {"Model Number": (0, 2), "Firmware Version": (6, 1), "ID": (7, 1),
          "Baud Rate": (8, 1), "Return Delay Time": (9, 1), "Operating Mode": (11, 1),
          "Current Limit": (38, 2), "Velocity Limit": (44, 4), "Shutdown": (63, 1),
          "Torque Enable": (64, 1), "Hardware Error Status": (70, 1), "Bus Watchdog": (98, 1),
          "Goal Current": (102, 2), "Present Current": (126, 2), "Present Velocity": (128, 4),
          "Present Position": (132, 4)},
    "p": {"Model Number": (0, 2), "Firmware Version": (6, 1), "ID": (7, 1),
          "Baud Rate": (8, 1), "Return Delay Time": (9, 1), "Operating Mode": (11, 1),
          "Current Limit": (38, 2), "Velocity Limit": (44, 4), "Shutdown": (63, 1),
          "Torque Enable": (512, 1), "Hardware Error Status": (518, 1),
          "Bus Watchdog": (546, 1), "Goal Current": (550, 2), "Present Current": (574, 2),
          "Present Velocity": (576, 4), "Present Position": (580, 4)},
    # XL320: https://emanual.robotis.com/docs/en/dxl/x/xl320/#control-table
    "xl320": {"Model Number": (0, 2), "Firmware Version": (2, 1), "ID": (3, 1),
              "Baud Rate": (4, 1), "Return Delay Time": (5, 1)},
}

#: Per model, what its e-Manual page (or ROBOTIS Dynamixel2Arduino src/actuator.h for the model
#: number) says: (model number, current unit mA/LSB, largest Current Limit LSB), None where the
#: data leaves the value unsourced.
EMANUAL_MODELS = {
    "MX-64": (311, 3.36, 1941), "XM540-W270": (1120, 2.69, 2047),
    "XM430-W350": (1020, 2.69, 1193), "XH430-V350": (1040, 1.34, 689),
    "XL330-M288": (1200, 1.0, 1750), "XC330-T288": (1220, 1.0, 910),
    "PH54-200-S500-R": (2020, 1.0, 22740), "PH42-020-S300-R": (2000, 1.0, 4500),
    "PM54-060-S250-R": (2120, 1.0, 7980),
    "XL330-M077": (1190, 1.0, 1750), "XC330-M181": (1230, 1.0, 2352),
    "XC330-M288": (1240, 1.0, 2352), "XC330-T181": (1210, 1.0, 910),
    "XM430-W210": (1030, 2.69, 1193), "XH430-W350": (1000, 2.69, 648),
    "XM540-W150": (1130, 2.69, 2047), "XH540-W270": (1100, 2.69, 2047),
    "XH540-V270": (1140, 2.69, 2047),
    "XH430-W210": (1010, None, 648), "XH430-V210": (1050, None, None),
    "XH540-W150": (1110, None, None), "XH540-V150": (1150, None, None),
    "XW430-T200": (1280, None, None),
    "XW430-T333": (1270, None, None), "XW540-T140": (1180, 2.69, 2047),
    "XW540-T260": (1170, None, None), "MX-106": (321, 3.36, 2047),
    "PH54-100-S500-R": (2010, 1.0, None), "PM54-040-S250-R": (2110, 1.0, None),
    "PM42-010-S260-R": (2100, 1.0, None),
    # Without Current Control mode (item 2 refuses them in a description).
    "XL430-W250": (1060, None, None), "XC430-W150": (1070, None, None),
    "XC430-W240": (1080, None, None), "2XL430-W250": (1090, None, None),
    "MX-28": (30, None, None), "XL320": (350, None, None),
}
NO_CURRENT_CONTROL = ("XL430-W250", "XC430-W150", "XC430-W240", "2XL430-W250", "MX-28", "XL320")


def test_the_lineup_is_the_brief_s():
    assert set(ct.MODELS) == set(EMANUAL_MODELS)
    assert list(ct.MODELS)[:2] == ["MX-64", "XM540-W270"]  # every "one of" list starts so
    assert {n for n, m in ct.MODELS.items() if not m.current_control} == set(NO_CURRENT_CONTROL)


@pytest.mark.parametrize("name", list(EMANUAL_MODELS))
def test_every_model_at_its_e_manual_addresses(name):
    spec = ct.MODELS[name]
    number, unit, limit = EMANUAL_MODELS[name]
    assert (spec.number, spec.current_unit_mA, spec.current_limit_max) == (number, unit, limit)
    assert ct.MODELS_BY_NUMBER[number] is spec
    for item, (address, size) in EMANUAL_ITEMS[spec.layout].items():
        assert (spec.item(item).address, spec.item(item).size) == (address, size), item
    if spec.current_limit_max is not None:  # the current items bounded by the model's limit
        assert spec.item("Current Limit").hi == spec.current_limit_max
        assert spec.item("Goal Current").lo == -spec.current_limit_max
    assert spec.url.startswith("https://emanual.robotis.com/docs/en/dxl/")
    # Unsourced values are None and named, never filled in.
    for field in ct.SOURCED_FIELDS:
        assert (getattr(spec, field) is None) == (field in spec.unsourced), field


def test_units_per_layout():
    """X: 4096 counts per turn and 0.229 rpm; P: 0.01 rpm and the model's own resolution."""
    xm = ct.MODELS["XM430-W350"]
    assert (xm.counts_per_rev, xm.velocity_unit_rpm) == (4096, 0.229)
    ph = ct.MODELS["PH54-200-S500-R"]
    assert (ph.counts_per_rev, ph.velocity_unit_rpm) == (1_003_846, 0.01)
    assert ct.MODELS["XL330-M288"].baud_rates[-1] == 4_000_000  # codes 0..6 only
    assert ct.MX64.fast_sync_read is False


# --------------------------------------------------------------------------------------------
# Descriptions on other motors
# --------------------------------------------------------------------------------------------

#: (model, fit slope in N cm/A from the e-Manual stall figures at the nominal voltage).
OTHER_MOTORS = {"XM430-W350": 4.1 / 2.3 * 100, "XL330-M288": 0.52 / 1.47 * 100}


def _user_robot(folder: Path, model: str, slope: float | None = None, extra: str = "") -> Path:
    """tests/data/planar2.toml and its joint scenario with ``model`` at both joints."""
    text = (DATA / "planar2.toml").read_text().replace('model = "XM540-W270"',
                                                       f'model = "{model}"')
    if slope is not None:
        text = text.replace("a = 240.9", f"a = {slope:.4f}")
    text = text.replace("  id = 1\n", f"  id = 1\n{extra}")
    (folder / "planar2.toml").write_text(text)
    scenario = folder / "planar2_joint.toml"
    scenario.write_text((DATA / "planar2_joint.toml").read_text())
    return scenario


@pytest.mark.parametrize("model", list(OTHER_MOTORS))
def test_a_description_on_other_motors_loads_and_simulates(tmp_path, model):
    sc = load_scenario(_user_robot(tmp_path, model, OTHER_MOTORS[model]))
    joints = robot("serial").actuated_joints(sc.system)
    assert [j.motor.model for j in joints] == [model, model]
    result = simulate(sc, duration=0.2, kernels="casadi")
    assert not result.diverged and result.periods == 200  # 0.2 s at 1 kHz
    arm = result.unit("arm")
    assert np.all(np.isfinite(arm.q)) and np.all(np.isfinite(arm.tau))
    drives = joint_drives("serial", system=sc.system)
    spec = ct.MODELS[model]
    assert all(d.spec is spec and 0 < d.current_limit_lsb <= spec.current_limit_max
               for d in drives)


def test_the_emulator_answers_with_each_model_s_number(tmp_path):
    from cochlea.dynamixel.emulator import VirtualChain
    chain = VirtualChain("serial", _user_robot(tmp_path, "XL330-M288", 35.37))
    try:
        for m in chain.motors:
            assert int.from_bytes(m.table[0:2], "little") == 1200  # Model Number (0)
            assert int.from_bytes(m.table[38:40], "little") == 1750  # Current Limit (38)
    finally:
        chain.close()


# --------------------------------------------------------------------------------------------
# Item 2: refused up front, one line naming the model and the reason
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model", NO_CURRENT_CONTROL)
def test_a_model_without_current_control_is_refused(tmp_path, model):
    with pytest.raises(DescriptionError) as info:
        load_scenario(_user_robot(tmp_path, model))
    message = str(info.value)
    assert "arm[0].link[0].motor.model" in message and "\n" not in message
    assert f"the {model} has no Current Control mode" in message


def test_a_model_whose_current_data_is_unsourced_is_refused(tmp_path):
    with pytest.raises(DescriptionError, match=r"the XH430-V210's current_unit_mA and "
                       r"current_limit_max are not sourced yet"):
        load_scenario(_user_robot(tmp_path, "XH430-V210"))
    with pytest.raises(DescriptionError, match=r"the XH430-W210's current_unit_mA is not "
                       r"sourced yet \(cochlea/dynamixel/models/x430.toml\): add it from "
                       r"https://emanual.robotis.com/docs/en/dxl/x/xh430-w210/"):
        load_scenario(_user_robot(tmp_path, "XH430-W210"))


def test_a_current_limit_above_the_model_s_is_refused(tmp_path):
    with pytest.raises(DescriptionError) as info:
        load_scenario(_user_robot(tmp_path, "XL330-M288", 35.37,
                                  "  current_limit_mA = 1800.0\n"))
    assert "motor.current_limit_mA: expected a positive number (mA) up to the XL330-M288's " \
           "1750 mA, got 1800.0" in str(info.value)


def test_a_baud_rate_the_model_does_not_take_is_refused(tmp_path):
    sc = load_scenario(_user_robot(tmp_path, "XL330-M288", 35.37))
    drives = joint_drives("serial", system=sc.system)
    check_baud(drives, 4_000_000)  # the XL330's fastest
    with pytest.raises(BackendError) as info:
        check_baud(drives, 4_500_000)
    assert str(info.value) == ("ID 1 (arm.upper, XL330-M288): the XL330-M288 does not support "
                               "4500000 baud (it takes 9600, 57600, 115200, 1000000, 2000000, "
                               "3000000, 4000000)")
    from cochlea.dynamixel.bridge import DynamixelBackend
    from cochlea.dynamixel.emulator import VirtualChain
    with pytest.raises(CochleaError, match="does not support 4500000 baud"):
        VirtualChain("serial", tmp_path / "planar2_joint.toml", baud=4_500_000)
    # The bridge refuses before it opens the port (this path does not exist).
    with pytest.raises(BackendError, match="ID 1 .*does not support 4500000 baud"):
        DynamixelBackend("serial", str(tmp_path / "no-port"), baud=4_500_000,
                         description=str(tmp_path / "planar2.toml"))


def test_a_p_series_motor_drives_in_python_and_in_the_embedded_tables(tmp_path):
    """The P series' addresses differ: the description, the simulation and the Python bridge
    and emulator (joint_drives, each item from the data) take it, and so do the embedded drive
    tables and the C bridge (issue 27 items 3, 4): a chain of P motors alone places every item
    alike, so its transfers are the plain SYNC ones (its Fast Sync Read support unsourced),
    each item at the P series' address."""
    from cochlea.dynamixel.embedded_drives import bus_choice, drives_header

    sc = load_scenario(_user_robot(tmp_path, "PH54-200-S500-R", 2000.0))
    result = simulate(sc, duration=0.05, kernels="casadi")
    assert not result.diverged and np.all(np.isfinite(result.unit("arm").q))
    drives = joint_drives("serial", system=sc.system)
    assert [d.spec.name for d in drives][0] == "PH54-200-S500-R"
    assert bus_choice(drives[:1]) == (
        "SYNC_READ", "SYNC_WRITE", "SYNC_READ (PH54-200-S500-R: FAST_SYNC_READ support not "
        "sourced)")
    header = drives_header("serial", system=sc.system, drives=drives)
    assert '{"PH54-200-S500-R", {{9, 1}, {11, 1}, {38, 2}, {512, 1}, {518, 1}, {546, 1}, ' \
        '{550, 2}, {536, 2}, {568, 2}, {574, 2}, {576, 4}, {580, 4}}, 0}' in header


# --------------------------------------------------------------------------------------------
# A broken data file: one line naming the file and the entry
# --------------------------------------------------------------------------------------------


def _files() -> dict[str, bytes]:
    folder = resources.files(ct.MODELS_PACKAGE)
    return {p.name: p.read_bytes() for p in folder.iterdir() if p.name.endswith(".toml")}


CORRUPTIONS = {
    "not TOML": ("x430.toml", b"number = 1020", b"number = = 1020",
                 "x430.toml: not a valid UTF-8 TOML file"),
    "not UTF-8": ("x430.toml", b'family = "X430"', b'family = "X430\xff"',
                  "x430.toml: not a valid UTF-8 TOML file"),
    "address of the wrong type": ("layout_x.toml", b"address = 102", b'address = "102"',
                                  "layout_x.toml: item Goal Current.address: expected an "
                                  "integer in 0..1023, got '102'"),
    "size that is not 1, 2 or 4": ("layout_x.toml", b"address = 126\nsize = 2",
                                   b"address = 126\nsize = 3",
                                   "item Present Current.size: expected 1, 2 or 4 (bytes)"),
    "a value neither given nor unsourced": (
        "x430.toml", b"current_limit_max = 1193\n", b"",
        "x430.toml: model XM430-W350.current_limit_max: expected a value (or the name in "
        "unsourced: no source found)"),
    "a negative current unit": ("x540.toml", b"current_unit_mA = 2.69", b"current_unit_mA = -2.69",
                                "model XM540-W270.current_unit_mA: expected a positive number"),
    "a rate no Dynamixel has": ("x330.toml", b"baud_rates = [9600,", b"baud_rates = [9601,",
                                "x330.toml: model XL330-M077.baud_rates: expected a list of "
                                "Dynamixel baud rates"),
    "a duplicate model number": ("x430.toml", b"number = 1030", b"number = 1020",
                                 "model XM430-W210.number: expected a number no other model "
                                 "uses (also XM430-W350)"),
    "an unknown layout": ("p.toml", b'layout = "p"', b'layout = "q"',
                          "p.toml: layout: expected one of p, x, xl320, got 'q'"),
    "an unknown key": ("mx2.toml", b"number = 311", b"numbr = 311",
                       "mx2.toml: model[0].numbr: expected no such key"),
    "an Operating Mode outside its range": (
        "layout_p.toml", b"values = [0, 1, 3, 4, 16]", b"values = [0, 1, 3, 4, 17]",
        "layout_p.toml: item Operating Mode.values: expected distinct integers within min..max"),
    "Operating Modes that are not integers": (
        "layout_x.toml", b"values = [0, 1, 3, 4, 5, 16]", b'values = ["current"]',
        "layout_x.toml: item Operating Mode.values: expected distinct integers"),
}


@pytest.mark.parametrize("case", list(CORRUPTIONS))
def test_a_corrupted_data_file_is_one_line(case):
    fname, old, new, expected = CORRUPTIONS[case]
    files = _files()
    assert old in files[fname], case  # the corruption applies to today's file
    files[fname] = files[fname].replace(old, new, 1)
    with pytest.raises(ct.ModelDataError) as info:
        ct.load_models(files)
    message = str(info.value)
    assert expected in message and "\n" not in message, message


def test_the_shipped_data_loads_the_same_as_the_package(tmp_path):
    assert ct.load_models(_files()).keys() == ct.MODELS.keys()


@pytest.mark.slow
def test_an_installation_with_a_broken_data_file_exits_with_one_line(tmp_path):
    """The package copied, one data file corrupted: any program that imports the control
    tables prints one line and exits EXIT_MODEL_DATA, no traceback."""
    package = Path(ct.__file__).parents[2] / "cochlea"
    shutil.copytree(package, tmp_path / "cochlea",
                    ignore=shutil.ignore_patterns("__pycache__", "*.so", "data", "lib"))
    broken = tmp_path / "cochlea" / "dynamixel" / "models" / "x540.toml"
    broken.write_text(broken.read_text().replace("number = 1120", "number = -1120"))
    done = subprocess.run([sys.executable, "-c", "import cochlea.dynamixel.control_table"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120,
                          env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"})
    assert done.returncode == ct.EXIT_MODEL_DATA, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert "x540.toml: model XM540-W270.number: expected a Model Number (0..65535), got " \
           "-1120" in done.stderr
