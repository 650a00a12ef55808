"""Homing records per robot description, and more than one prismatic joint (issue 25's
leftovers): ``cochlea-dxl home`` homes every prismatic joint of a user arm in turn over the
virtual chain (a hard stop under each), writes one record holding an entry per joint at a path
of that description's own, and the bridge counts each joint from its stop; a record of another
description, and a joint whose motor lost its marker, are refused in one line."""

from __future__ import annotations

import argparse
import csv
import gc
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from cochlea.dynamixel import homing
from cochlea.dynamixel.bridge import DynamixelBackend
from cochlea.dynamixel.bringup import home
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.emulator import Faults, Truth, VirtualChain
from cochlea.resources import ROBOTS_DIR
from cochlea.runtime.backend import BackendError

from .conftest import DATA

ONE = DATA / "prismatic3.toml"  # one prismatic joint: the carriage (ID 2)
ONE_STUDY = DATA / "prismatic3_joint.toml"
TWO = DATA / "prismatic3_two.toml"  # two: the carriage (ID 2) and the forearm (ID 3)
TWO_STUDY = DATA / "prismatic3_two_joint.toml"
STOP_M = 0.03  # the emulator's hard stop, under every prismatic joint
RUN = [sys.executable, "-m", "cochlea.apps.cochlea_run"]
#: The homing options of these tests: quicker than the defaults, within both joints' limits.
FAST = ("--speed-mm-s", "8", "--force-N", "20")


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="cochlea-dxl home")
    home.add_arguments(parser)
    return parser.parse_args(list(argv))


@pytest.fixture
def no_gc():
    """The emulator is a thread of this process: no collector pause may stall it."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


@pytest.fixture
def home_dir(tmp_path, monkeypatch) -> Path:
    """A home of the test's own: the default records land in HOME/.cochlea/homing."""
    folder = tmp_path / "home"
    folder.mkdir()
    monkeypatch.setenv("HOME", str(folder))
    return folder


def _bridge(chain: VirtualChain, description: Path, **options) -> DynamixelBackend:
    return DynamixelBackend("serial", chain.path, description=description, timeout_s=0.05,
                            homing="required", **options)


def _refused(bridge: DynamixelBackend) -> str:
    with pytest.raises(BackendError) as caught:
        bridge.enable()
    assert not bridge.enabled
    text = str(caught.value)
    assert "\n" not in text and "Traceback" not in text
    return text


# ---- where the records go ----------------------------------------------------------------------


def test_each_description_has_its_own_default_record(home_dir, tmp_path):
    """The shipped descriptions keep ~/.cochlea/homing/ROBOT.json (the lab's records still
    count); a user's description gets ROBOT-STEM-HASH.json, the hash of its resolved path: two
    descriptions, or one copied elsewhere, never share a record."""
    folder = home_dir / ".cochlea" / "homing"
    assert homing.default_record("parallel") == folder / "parallel.json"
    assert homing.default_record("serial", "serial") == folder / "serial.json"
    assert homing.default_record("parallel", ROBOTS_DIR / "parallel.toml") == \
        folder / "parallel.json"
    copy = tmp_path / "elsewhere" / TWO.name
    copy.parent.mkdir()
    copy.write_bytes(TWO.read_bytes())
    paths = [homing.default_record("serial", p) for p in (ONE, TWO, copy)]
    assert len(set(paths)) == 3
    assert all(p.parent == folder and p.name.startswith("serial-") for p in paths)
    assert paths[0].name.startswith("serial-prismatic3-")
    assert paths[1].name.startswith("serial-prismatic3_two-")
    assert paths[2].name.startswith("serial-prismatic3_two-")
    # The same file named otherwise (relative, absolute) is the same description.
    relative = Path(__import__("os").path.relpath(TWO))
    assert homing.default_record("serial", relative) == paths[1]
    assert homing.description_id("serial", relative) == str(TWO.resolve())
    assert homing.description_id("parallel", None) == homing.SHIPPED


# ---- two prismatic joints, end to end over the virtual chain ---------------------------------


@pytest.mark.hil
def test_two_prismatic_joints_are_homed_in_turn_and_each_is_counted_from_its_stop(
        home_dir, no_gc):
    """Both joints' motors are mounted far from what the description says (their zero_offset
    wrong by hundreds of degrees): home drives the carriage, then the forearm, onto their stops,
    writes one record with an entry each at the description's default path; the bridge then
    starts with each joint at its stop. A motor rebooted since (its marker gone) is refused by
    name, the other's entry valid or not."""
    chain = VirtualChain("serial", TWO_STUDY, truth=Truth(offset_deg={2: 500.0, 3: -700.0},
                                                          hard_stop_m=STOP_M)).start()
    try:
        chain.move_joint("arm.forearm", 0.04)  # 10 mm above its stop; the carriage 9.5 mm
        code = home.run(parse("--robot", "serial", "--description", str(TWO), "--port",
                              chain.path, "--stop-m", str(STOP_M), "--stop-m", str(STOP_M),
                              *FAST))
        assert code == 0 and not any(m.torque_on for m in chain.motors)
        path = homing.default_record("serial", TWO)
        assert [p.name for p in path.parent.iterdir()] == [path.name]
        saved = json.loads(path.read_text())
        assert saved["format"] == "cochlea-homing/2"
        assert saved["description"] == str(TWO.resolve())
        assert [e["joint"] for e in saved["joints"]] == ["arm.carriage", "arm.forearm"]
        motors = {m.id: m for m in chain.motors}
        for entry in saved["joints"]:
            true = motors[entry["motor_id"]].drive  # as the motor is truly mounted
            assert abs(entry["raw_counts"] - float(true.counts(STOP_M))) <= 2, entry
            assert entry["stop_m"] == STOP_M
        assert len({e["marker"] for e in saved["joints"]}) == 2  # a token each
        assert chain.joint_state()[1] == pytest.approx(STOP_M, abs=1e-4)
        assert chain.joint_state()[2] == pytest.approx(STOP_M, abs=1e-4)

        # The bridge finds the record by the description alone, and counts each joint from
        # its stop whatever the description's zero_offset_deg says (500 and -700 deg off).
        chain.move_joint("arm.forearm", 0.035)  # a hand moves it, torque off: still counted
        bridge = _bridge(chain, TWO)
        bridge.enable()
        try:
            x = np.zeros(6)
            assert bridge.read(x)
            truth = chain.joint_state()
            for j, d in ((1, "arm.carriage"), (2, "arm.forearm")):
                drive = next(x for x in bridge.drives if x.name == d)
                assert abs(x[j] - truth[j]) <= 3 * drive.ratio * 2 * np.pi / 4096, d
            assert abs(x[1] - STOP_M) < 1e-3 and abs(x[2] - 0.035) < 1e-3
            assert bridge.summary()["homing"] == f"homed {saved['date']} ({path})"
        finally:
            bridge.disable()

        # The forearm's motor rebooted alone: its entry no longer counts, the start is refused
        # naming it, before any write.
        motors[3].reboot()
        text = _refused(_bridge(chain, TWO))
        assert text.startswith("arm.forearm (ID 3) was power-cycled or rebooted")
        assert f"cochlea-dxl home --robot serial --description {TWO.resolve()}" in text
        assert not any(m.torque_on for m in chain.motors)
    finally:
        chain.close()


@pytest.mark.hil
def test_a_record_of_another_description_is_refused_naming_both(home_dir, tmp_path, no_gc):
    """The same arm homed under two descriptions (the shipped-like file and a copy of it
    elsewhere) gets two records, the first untouched by the second; the runtime refuses the
    copy's record for the original in one line naming both descriptions, even when it is
    given by path, and the original's own record no longer holds: the second homing left its
    own token in the motor."""
    copy = tmp_path / "copy" / ONE.name
    copy.parent.mkdir()
    copy.write_bytes(ONE.read_bytes())
    chain = VirtualChain("serial", ONE_STUDY, truth=Truth(offset_deg={2: 500.0},
                                                          hard_stop_m=STOP_M)).start()
    try:
        assert home.run(parse("--robot", "serial", "--description", str(ONE), "--port",
                              chain.path, "--stop-m", str(STOP_M), *FAST)) == 0
        first = homing.default_record("serial", ONE)
        before = first.read_text()
        chain.move_joint("arm.carriage", 0.04)
        assert home.run(parse("--robot", "serial", "--description", str(copy), "--port",
                              chain.path, "--stop-m", str(STOP_M), *FAST)) == 0
        second = homing.default_record("serial", copy)
        assert first != second and first.read_text() == before
        assert sorted(p.name for p in first.parent.iterdir()) == sorted([first.name,
                                                                         second.name])

        text = _refused(_bridge(chain, ONE, homing_record=second))
        assert text == (f"homing record {second} was made for the description "
                        f"{copy.resolve()}, not {ONE.resolve()}: run cochlea-dxl home --robot "
                        f"serial --description {ONE.resolve()} --port PORT again")
        text = _refused(_bridge(chain, ONE))  # its own record: the token is the copy's now
        assert text.startswith("arm.carriage (ID 2) was power-cycled or rebooted")
        bridge = _bridge(chain, copy)  # the copy's own: valid
        bridge.enable()
        try:
            x = np.zeros(6)
            assert bridge.read(x) and abs(x[1] - STOP_M) < 1e-3
        finally:
            bridge.disable()
    finally:
        chain.close()


@pytest.mark.hil
def test_a_fault_on_the_second_joint_stops_everything_and_records_nothing(home_dir, capsys,
                                                                          no_gc):
    """The carriage homed, then the forearm's motor goes into hardware alert while it is being
    homed: the move stops at once with the torque off on every motor, the command says so in
    one line (exit 6), and no record is written, not even the carriage's entry."""
    from cochlea.apps import cochlea_dxl

    # Overload (bit 5) on the forearm's motor 3 s after the first torque on: after the
    # carriage's homing (9.5 mm at 8 mm/s, then the dwell), within the forearm's (20 mm).
    chain = VirtualChain("serial", TWO_STUDY, truth=Truth(hard_stop_m=STOP_M),
                         faults=Faults(hardware_error=(3, 5), delay_s=3.0)).start()
    try:
        chain.move_joint("arm.forearm", 0.05)
        code = cochlea_dxl.main(["home", "--robot", "serial", "--description", str(TWO),
                                 "--port", chain.path, "--stop-m", str(STOP_M), "--stop-m",
                                 str(STOP_M), *FAST])
        out, err = capsys.readouterr()
        assert not any(m.torque_on for m in chain.motors)
    finally:
        chain.close()
    assert code == 6, err
    assert out.count("arm.carriage (ID 2) on its stop") == 1 and "homed" not in out
    assert err.count("\n") == 1
    assert err.startswith("cochlea-dxl home: hardware alert during the homing of arm.forearm: "
                          "ID 3 (arm.forearm, XM430-W350): 32 (overload); stopped: goal current "
                          "0 and torque off on every motor;"), err
    assert not homing.default_record("serial", TWO).exists()


# ---- the records' rules, without a chain ----------------------------------------------------


def _entry(d, **changes) -> dict:
    entry = {"joint": d.name, "motor_id": d.id, "model": d.spec.name, "raw_counts": 100,
             "stop_m": 0.0, "direction": d.direction, "ratio_m_per_rad": d.ratio,
             "marker_address": 88, "marker": 4321}
    entry.update(changes)
    return entry


def _write(path: Path, record: dict) -> Path:
    path.write_text(json.dumps(record))
    return path


def test_an_old_single_joint_record_still_counts_for_the_shipped_parallel_robot(tmp_path):
    """A cochlea-homing/1 record (flat, one joint) of the shipped parallel robot is read as
    before; its offset is the one the old rule gives."""
    (slider,) = [d for d in joint_drives("parallel") if d.type == "prismatic"]
    old = {"format": "cochlea-homing/1", "robot": "parallel", **_entry(slider),
           "description": "shipped", "date": "2026-11-20T09:00:00"}
    path = _write(tmp_path / "parallel.json", old)
    record = homing.load_record(path)
    (entry,) = homing.check_record(record, path, "parallel", None, [slider])
    offset = homing.reference_offset(entry, record, path, slider, 4321)
    assert offset == pytest.approx(0.0 - slider.q_per_count * 100, rel=1e-15)
    with pytest.raises(BackendError, match=r"^slider\.d1 \(ID \d+\) was power-cycled"):
        homing.reference_offset(entry, record, path, slider, 0)  # a fresh power-on's 0


def test_an_old_record_of_a_user_description_is_refused_in_one_line(tmp_path):
    """A cochlea-homing/1 record does not identify a user's description: homing again is the
    only safe answer."""
    carriage = next(d for d in joint_drives("serial", ONE) if d.type == "prismatic")
    path = _write(tmp_path / "old.json", {"format": "cochlea-homing/1", "robot": "serial",
                                          **_entry(carriage), "description": str(ONE)})
    with pytest.raises(BackendError) as caught:
        homing.check_record(homing.load_record(path), path, "serial", ONE, [carriage])
    assert str(caught.value) == (
        f"homing record {path} is a cochlea-homing/1 record (from an older cochlea) of a "
        "user's description, which it does not identify: run cochlea-dxl home --robot serial "
        f"--description {ONE.resolve()} --port PORT again")


@pytest.mark.parametrize("case, message", [
    ("missing joint", "holds the joints arm.carriage; the description's prismatic joints are "
                      "arm.carriage, arm.forearm"),
    ("other robot", "was made for the parallel robot, not the serial one"),
    ("wrong motor", "was made for arm.forearm on motor ID 9, direction +1"),
])
def test_a_record_that_does_not_fit_the_description_is_refused(tmp_path, case, message):
    drives = [d for d in joint_drives("serial", TWO) if d.type == "prismatic"]
    entries = [_entry(d) for d in drives]
    record = {"format": "cochlea-homing/2", "robot": "serial",
              "description": str(TWO.resolve()), "date": "2026-11-26T05:00:00",
              "joints": entries}
    if case == "missing joint":
        record["joints"] = entries[:1]
    elif case == "other robot":
        record["robot"] = "parallel"
    else:
        entries[1]["motor_id"] = 9
    path = _write(tmp_path / "r.json", record)
    with pytest.raises(BackendError) as caught:
        loaded = homing.load_record(path)
        for d, entry in zip(drives, homing.check_record(loaded, path, "serial", TWO, drives)):
            homing.reference_offset(entry, loaded, path, d, 4321)
    assert message in str(caught.value) and "cochlea-dxl home" in str(caught.value)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize("key, value", [("raw_counts", 10**320), ("raw_counts", 2**31),
                                        ("marker", 70000), ("motor_id", 300), ("marker", -1),
                                        ("ratio_m_per_rad", 10**400), ("stop_m", -10**400)])
def test_an_entry_no_home_could_write_is_refused_in_one_line(tmp_path, key, value):
    """Integers out of what the bus carries (a 4-byte position, a 2-byte token, an ID up to
    252), or a length no float holds: one line, never an OverflowError at the start-up (10**320
    counts, or a ratio of 10**400, did that; found by fuzzing 4500 mutated records)."""
    (slider,) = [d for d in joint_drives("parallel") if d.type == "prismatic"]
    path = _write(tmp_path / "r.json", {"format": "cochlea-homing/2", "robot": "parallel",
                                        "description": "shipped", "date": "2026-11-26",
                                        "joints": [_entry(slider, **{key: value})]})
    with pytest.raises(BackendError) as caught:
        homing.load_record(path)
    assert "not a cochlea-homing/2 record" in str(caught.value)
    assert "\n" not in str(caught.value)


# ---- cochlea-run finds the description's record ------------------------------------------------


@pytest.mark.hil
def test_cochlea_run_starts_the_homed_arm_from_the_scenarios_description(home_dir, tmp_path,
                                                                        no_gc):
    """cochlea-run --backend dynamixel --homing required, no --homing-record: the record is
    looked up from the scenario's description (the user's, not serial.json), both joints are
    counted from their stops (their motors 500 and -700 deg off the description's zero), and
    the study runs from the pose a hand put the arm in."""
    chain = VirtualChain("serial", TWO_STUDY, truth=Truth(offset_deg={2: 500.0, 3: -700.0},
                                                          hard_stop_m=STOP_M)).start()
    out = tmp_path / "run"
    try:
        # Not homed yet: refused, naming the command for this description.
        text = _refused(_bridge(chain, TWO))
        assert text == ("the robot's prismatic joints are not homed: no homing record "
                        f"{homing.default_record('serial', TWO)}; run cochlea-dxl home --robot "
                        f"serial --description {TWO.resolve()} --port PORT first")
        # Without --stop-m each joint's stop is its lower limit (0 m for both); these stops
        # are at 30 mm, so home again with their true coordinates, once per joint.
        assert home.run(parse("--robot", "serial", "--description", str(TWO), "--port",
                              chain.path, *FAST)) == 0
        saved = json.loads(homing.default_record("serial", TWO).read_text())
        assert [e["stop_m"] for e in saved["joints"]] == [0.0, 0.0]
        chain.move_joint("arm.carriage", 0.04)
        assert home.run(parse("--robot", "serial", "--description", str(TWO), "--port",
                              chain.path, "--stop-m", str(STOP_M), "--stop-m", str(STOP_M),
                              *FAST)) == 0
        chain.move_joint("arm.carriage", 0.0395)  # the scenario's initial pose, by hand
        chain.move_joint("arm.forearm", 0.0355)
        done = subprocess.run(RUN + ["--robot", "serial", "--space", "joint", "--scenario",
                                     str(TWO_STUDY), "--backend", "dynamixel", "--port",
                                     chain.path, "--duration", "1", "--out", str(out),
                                     "--homing", "required", "--watchdog-misses", "300"],
                              capture_output=True, text=True, timeout=180, cwd=tmp_path,
                              env={**os.environ, "HOME": str(home_dir)})
    finally:
        chain.close()
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["bus"]["homing"].endswith(
        f"({homing.default_record('serial', TWO)})")
    assert summary["timing"]["bus"]["homing"].startswith("homed ")
    with open(out / "log.csv", newline="") as f:
        first = next(csv.DictReader(f))
    assert abs(float(first["arm.q.carriage_joint_m"]) - 0.0395) < 1e-3
    assert abs(float(first["arm.q.forearm_joint_m"]) - 0.0355) < 1e-3


# ---- the embedded C program (cochlea-codegen --embedded of a user's scenario) -------------------


def _embedded_program(tmp: Path, scenario: Path) -> Path:
    """``build/cochlea-embedded`` of a user's scenario, as a user builds it."""
    from tests.test_embedded_program import ROOT

    gen, build = tmp / "gen", tmp / "build"
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_codegen", "--scenario",
                           str(scenario), "--embedded", "--no-build", "--out", str(gen)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    program = build / "cochlea-embedded"
    done = subprocess.run(["make", "-s", f"GEN={gen}", f"BUILD={build}", str(program)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    return program


@pytest.mark.slow
def test_the_embedded_program_refuses_two_prismatic_joints_on_a_checked_start(tmp_path):
    """Its bridge counts one joint from a homing: a robot with two is refused in one line,
    before the port opens, naming cochlea-run (the other joint would otherwise run on the
    description's zero_offset_deg)."""
    program = _embedded_program(tmp_path, TWO_STUDY)
    done = subprocess.run([str(program), "--scenario", "prismatic3_two_joint", "--port",
                           "/dev/ttyUSB-none", "--out", str(tmp_path / "run"), "--homing",
                           "required"], capture_output=True, text=True, timeout=60)
    errors = [line for line in done.stderr.splitlines() if ": warning: " not in line]
    assert done.returncode == 5 and errors == [
        "cochlea-embedded: the backend could not start, nothing moved: the robot has 2 "
        "prismatic joints and this program checks the homing of one: run it with cochlea-run "
        "--backend dynamixel, which checks each"], done.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
@pytest.mark.hil
def test_the_embedded_program_counts_a_user_joint_from_the_record_home_writes(
        home_dir, tmp_path, no_gc):
    """The one-carriage arm's embedded program reads the cochlea-homing/2 record
    cochlea-dxl home wrote for its description (given by path: the program does not know its
    description) and starts with the carriage counted from its stop, its motor 500 deg off."""
    from tests.test_embedded_program import EMULATOR_SETTLE_S, PATIENT

    program = _embedded_program(tmp_path, ONE_STUDY)
    chain = VirtualChain("serial", ONE_STUDY, truth=Truth(offset_deg={2: 500.0},
                                                          hard_stop_m=STOP_M)).start()
    out = tmp_path / "run"
    try:
        assert home.run(parse("--robot", "serial", "--description", str(ONE), "--port",
                              chain.path, "--stop-m", str(STOP_M), *FAST)) == 0
        record = homing.default_record("serial", ONE)
        chain.move_joint("arm.carriage", 0.0395)  # the scenario's initial pose, by hand
        time.sleep(min(EMULATOR_SETTLE_S, 0.5))
        done = subprocess.run([str(program), "--scenario", "prismatic3_joint", "--port",
                               chain.path, "--duration", "0.3", "--out", str(out), *PATIENT,
                               "--homing", "required", "--homing-record", str(record)],
                              capture_output=True, text=True, timeout=120)
    finally:
        chain.close()
    assert done.returncode == 0, done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"]["bus"]["homing"].startswith("homed ")
    assert summary["timing"]["bus"]["homing"].endswith(f"({record})")
    with open(out / "log.csv", newline="") as f:
        first = next(csv.DictReader(f))
    assert abs(float(first["arm.q.carriage_joint_m"]) - 0.0395) < 1e-3


# ---- the token's register, from the models' data ---------------------------------------------


def test_the_tokens_register_is_each_models_own(tmp_path):
    """The homing token lives in each model's Feedforward 2nd Gain, at the address its data
    gives (88 on the X series and MX(2.0), 536 on the P series), not at a constant; a model
    whose register cannot hold a token, and a record that kept the token at another address,
    are refused in one line."""
    from dataclasses import replace
    from types import SimpleNamespace

    from cochlea.dynamixel.control_table import MODELS

    for model, address in [("XM430-W350", 88), ("MX-64", 88), ("PH54-200-S500-R", 536)]:
        drive = SimpleNamespace(name="arm.carriage", spec=MODELS[model])
        assert homing.marker_item(drive).address == address
    narrow = replace(MODELS["XM430-W350"].item("Feedforward 2nd Gain"), size=1, hi=255)
    spec = SimpleNamespace(name="XM430-W350", item=lambda name: narrow)
    with pytest.raises(BackendError, match=r"^joint arm\.carriage: the XM430-W350's "
                       r"Feedforward 2nd Gain \(address 88, 1 bytes, 0\.\.255\) cannot hold"):
        homing.marker_item(SimpleNamespace(name="arm.carriage", spec=spec))

    carriage = next(d for d in joint_drives("serial", ONE) if d.type == "prismatic")
    path = _write(tmp_path / "moved.json", {
        "format": homing.FORMAT, "robot": "serial", "description": str(ONE.resolve()),
        "joints": [_entry(carriage, marker_address=536)]})
    record = homing.load_record(path)
    (entry,) = homing.check_record(record, path, "serial", ONE, [carriage])
    with pytest.raises(BackendError) as caught:
        homing.reference_offset(entry, record, path, carriage, 4321)
    assert str(caught.value) == (
        f"homing record {path} keeps arm.carriage's token at address 536; the XM430-W350 "
        "keeps it at 88 (Feedforward 2nd Gain): run cochlea-dxl home again")
