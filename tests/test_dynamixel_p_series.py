"""Issue 27, items 3 and 4, for the DYNAMIXEL-P series: every Python program follows the data,
and a mixed chain (an X-series arm with a P-series joint) on one bus.

* the P layout's items against the e-Manual page its data cites (addresses, sizes, units of
  the items the toolkit uses) and the P models' limits and units;
* the emulator as a PH54-200-S500-R answering PING, READ, WRITE and REBOOT at the P series'
  addresses (its EEPROM area from the data: locked below 512 while the torque is on);
* ``cochlea-dxl scan`` naming an X and a P motor on one emulated bus;
* ``cochlea-run --backend dynamixel`` over the virtual chain of a 2-DoF planar arm with a
  PH42-020-S300-R shoulder and an XM430-W350 elbow (tests/data/planar2_xp*.toml): it converges,
  with BULK_READ / BULK_WRITE and the bus budget of those frames in its summary; Fast Sync
  Read is never chosen for such a chain;
* bad input: a P motor whose needed value is unsourced, one line.

The embedded drive tables and the C bridge on the same chain: tests/test_embedded_p_series.py.
"""

from __future__ import annotations

import csv
import dataclasses
import gc
import json
import math
import subprocess
import sys
import time
import tomllib
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from cochlea.apps.cochlea_dxl import main as dxl_main
from cochlea.dynamixel import drives as drives_module
from cochlea.dynamixel import protocol as proto
from cochlea.dynamixel.bridge import DynamixelBackend, choose_transfers
from cochlea.dynamixel.bringup.common import Bus
from cochlea.dynamixel.budget import bus_budget
from cochlea.dynamixel.control_table import (
    ACCESS,
    DATA_LIMIT,
    DATA_RANGE,
    MODELS,
    MODELS_BY_NUMBER,
    MODELS_PACKAGE,
)
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.emulator import Truth, VirtualChain
from cochlea.errors import CochleaError, DescriptionError
from cochlea.runtime.backend import BackendError
from cochlea.sim import load_scenario

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(__file__).resolve().parent / "data"
ARM = DATA / "planar2_xp.toml"
SCENARIO = DATA / "planar2_xp_joint.toml"
BAUD = 4_000_000


@pytest.fixture(autouse=True)
def no_gc():
    """The emulator is a thread of this process: a full collection can stall it (as in
    test_dynamixel_bridge.py)."""
    gc.collect()
    gc.disable()
    yield
    gc.enable()


# ---- the data against the e-Manual ---------------------------------------------------------

#: https://emanual.robotis.com/docs/en/dxl/p/ph54-200-s500-r/#control-table, the page
#: layout_p.toml cites (the PH42-020-S300-R's page has the same addresses, sizes and units):
#: name -> (address, size, access, unit as the page gives it) of every item the toolkit uses.
EMANUAL_P = {
    "Model Number": (0, 2, "R", "-"),
    "Firmware Version": (6, 1, "R", "-"),
    "ID": (7, 1, "RW", "-"),
    "Baud Rate": (8, 1, "RW", "-"),
    "Return Delay Time": (9, 1, "RW", "2 us"),
    "Drive Mode": (10, 1, "RW", "-"),
    "Operating Mode": (11, 1, "RW", "-"),
    "Homing Offset": (20, 4, "RW", "1 pulse"),
    "Current Limit": (38, 2, "RW", "1 mA"),
    "Velocity Limit": (44, 4, "RW", "0.01 rpm"),
    "Max Position Limit": (48, 4, "RW", "1 pulse"),
    "Min Position Limit": (52, 4, "RW", "1 pulse"),
    "Indirect Address 128": (422, 2, "RW", "-"),  # the EEPROM area's last item
    "Torque Enable": (512, 1, "RW", "-"),
    "Status Return Level": (516, 1, "RW", "-"),
    "Hardware Error Status": (518, 1, "R", "-"),
    "Feedforward 2nd Gain": (536, 2, "RW", "-"),
    "Bus Watchdog": (546, 1, "RW", "20 ms"),
    "Goal Current": (550, 2, "RW", "1 mA"),
    "Goal Velocity": (552, 4, "RW", "0.01 rpm"),
    "Goal Position": (564, 4, "RW", "1 pulse"),
    "Realtime Tick": (568, 2, "R", "1 ms"),
    "Present Current": (574, 2, "R", "1 mA"),
    "Present Velocity": (576, 4, "R", "0.01 rpm"),
    "Present Position": (580, 4, "R", "1 pulse"),
}
#: The same pages: Model Number, Current Limit (mA), Velocity Limit (0.01 rpm) and the Max
#: Position Limit's bound (pulses, half a turn: -N ~ N over -180 ~ 180 deg).
EMANUAL_MODELS = {"PH54-200-S500-R": (2020, 22740, 2900, 501923),
                  "PH42-020-S300-R": (2000, 4500, 2920, 303750)}
#: The data's unit texts the page's units are written as ("current_unit_mA" is 1 mA here).
UNIT_TEXT = {"1 mA": "current_unit_mA", "20 ms": "20 ms", "2 us": "2 us", "1 ms": "1 ms",
             "0.01 rpm": "0.01 rpm", "1 pulse": "1 pulse", "-": None}


def _layout_p() -> dict:
    text = resources.files(MODELS_PACKAGE).joinpath("layout_p.toml").read_bytes()
    return tomllib.loads(text.decode())


def test_the_p_layout_against_its_e_manual_page():
    layout = _layout_p()
    assert layout["url"] == "https://emanual.robotis.com/docs/en/dxl/p/ph54-200-s500-r/" \
                            "#control-table"
    assert layout["velocity_unit_rpm"] == 0.01
    # The EEPROM area ends with Indirect Address 128 (422..423); the RAM starts at 512.
    assert layout["ram_from"] == 512
    raw = {it["name"]: it for it in layout["item"]}
    for name, (address, size, access, unit) in EMANUAL_P.items():
        it = raw[name]
        assert (it["address"], it["size"], it["access"]) == (address, size, access), name
        if UNIT_TEXT[unit] is not None:
            assert it["unit"].startswith(UNIT_TEXT[unit]), (name, it["unit"])
    spec = MODELS["PH42-020-S300-R"]
    for name, (address, size, access, _) in EMANUAL_P.items():
        item = spec.item(name)
        assert (item.address, item.size, item.writable) == (address, size, access == "RW")
        assert item.eeprom == (address < 512), name
    # Signed where the page's range is: positions, velocities, currents.
    for name in ("Homing Offset", "Goal Current", "Goal Velocity", "Goal Position",
                 "Present Current", "Present Velocity", "Present Position"):
        assert spec.item(name).signed, name
    # The per-period block is the X series' one (same order and sizes), at 568..583.
    x = MODELS["XM430-W350"]
    for name in ("Present Current", "Present Velocity", "Present Position"):
        assert (spec.item(name).address - 568, spec.item(name).size) == \
            (x.item(name).address - 120, x.item(name).size)


@pytest.mark.parametrize("name", list(EMANUAL_MODELS))
def test_each_p_model_s_number_limits_and_units(name):
    number, current_limit, velocity_limit, half_turn = EMANUAL_MODELS[name]
    spec = MODELS[name]
    assert MODELS_BY_NUMBER[number] is spec and spec.layout == "p"
    assert spec.current_unit_mA == 1.0 and spec.current_limit_max == current_limit
    assert spec.item("Current Limit").hi == current_limit
    assert spec.item("Velocity Limit").hi == velocity_limit
    assert spec.item("Max Position Limit").hi == half_turn
    assert spec.counts_per_rev == 2 * half_turn
    assert spec.rad_per_count == pytest.approx(math.pi / half_turn, rel=1e-15)
    assert spec.rad_s_per_velocity_lsb == pytest.approx(0.01 * 2 * math.pi / 60, rel=1e-15)
    assert spec.units_problem() is None and spec.current_control_problem() is None


def test_a_p_joint_converts_in_its_own_units():
    """The PH42's joint: 607500 pulses a turn, 0.01 rpm, 1 mA (the XM430's: 4096, 0.229 rpm,
    2.69 mA); a count round-trips, a current is its mA."""
    shoulder, elbow = joint_drives("serial", ARM)
    assert (shoulder.spec.name, elbow.spec.name) == ("PH42-020-S300-R", "XM430-W350")
    assert shoulder.q_per_count == pytest.approx(2 * math.pi / 607500, rel=1e-15)
    assert elbow.q_per_count == pytest.approx(2 * math.pi / 4096, rel=1e-15)
    assert shoulder.qd_per_lsb == pytest.approx(0.01 * 2 * math.pi / 60, rel=1e-15)
    assert elbow.qd_per_lsb == pytest.approx(0.229 * 2 * math.pi / 60, rel=1e-15)
    for counts in (-303750, -1, 0, 1, 123456, 10 * 607500):  # multi-turn, signed
        assert shoulder.counts(shoulder.q(counts)) == counts
    assert shoulder.current_mA(1234) == 1234.0
    # 4 N m through the placeholder fit (1 N m/A): 4 A, 4000 LSB of 1 mA.
    assert shoulder.current_limit_lsb == 4000


# ---- the emulator as a PH54 ----------------------------------------------------------------


def _ph54_scenario(tmp_path: Path) -> Path:
    """planar2_xp with a PH54-200-S500-R at the shoulder instead of the PH42."""
    (tmp_path / "planar2_xp.toml").write_text(
        ARM.read_text().replace('model = "PH42-020-S300-R"', 'model = "PH54-200-S500-R"'))
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(SCENARIO.read_text())
    return scenario


def _reply(bus: Bus, frame: bytes, motor_id: int):
    reply = bus.request(frame, motor_id)
    assert reply is not None
    return reply


@pytest.mark.hil
def test_the_emulator_answers_as_a_ph54_at_the_p_addresses(tmp_path):
    spec = MODELS["PH54-200-S500-R"]
    with VirtualChain("serial", _ph54_scenario(tmp_path)) as chain, Bus(chain.path, BAUD) as bus:
        assert [m.spec.name for m in chain.motors] == ["PH54-200-S500-R", "XM430-W350"]
        assert bus.ping(1) == (2020, spec.firmware) and bus.ping(2) == (1020, 46)
        item = spec.item
        assert bus.read(1, item("Current Limit")) == 22740  # its default: the model's limit
        assert bus.read(1, item("Torque Enable")) == 0
        assert bus.read(1, item("Status Return Level")) == 2
        # Present Position at 580: the plant's angle in the PH54's pulses (1003846 a turn).
        d = chain.motors[0].drive
        counts = bus.read(1, item("Present Position"))
        assert abs(d.q(counts) - chain.joint_state()[0]) <= 2 * abs(d.q_per_count)
        assert d.q(counts) == pytest.approx(math.radians(33.0), abs=1e-4)
        # The Realtime Tick at 568 moves.
        t0 = bus.read(1, item("Realtime Tick"))
        time.sleep(0.02)
        assert bus.read(1, item("Realtime Tick")) != t0
        # Nothing at the X series' addresses: 64 (Torque Enable there) is no P item.
        assert _reply(bus, proto.write(1, 64, b"\x01"), 1).error == ACCESS
        # EEPROM (below 512, the data's area) writable with the torque off, locked with it on.
        bus.write(1, item("Current Limit"), 3000)
        bus.write(1, item("Indirect Address 128"), 600)  # EEPROM (422), the torque still off
        # The P series has no current-based position mode (5): refused, as by the X motor
        # beside it a mode no model has (2); the X motor takes 5.
        assert _reply(bus, proto.write(1, 11, b"\x05"), 1).error == DATA_RANGE
        assert _reply(bus, proto.write(2, 11, b"\x02"), 2).error == DATA_RANGE
        bus.write(2, MODELS["XM430-W350"].item("Operating Mode"), 5)
        bus.write(2, MODELS["XM430-W350"].item("Operating Mode"), 3)
        bus.write(1, item("Operating Mode"), 16)
        bus.write(1, item("Operating Mode"), 0)
        bus.write(1, item("Bus Watchdog"), 10)
        bus.write(1, item("Torque Enable"), 1)
        assert _reply(bus, proto.write(1, 38, proto.le(2000, 2)), 1).error == ACCESS
        assert _reply(bus, proto.write(1, 20, proto.le(5, 4)), 1).error == ACCESS
        assert _reply(bus, proto.write(1, 422, proto.le(700, 2)), 1).error == ACCESS
        bus.write(1, item("Feedforward 2nd Gain"), 1234)  # RAM (536): free with the torque on
        # Goal Current (550) within the Current Limit, refused beyond it.
        assert _reply(bus, proto.write(1, 550, proto.le(3001, 2)), 1).error == DATA_LIMIT
        bus.write(1, item("Goal Current"), -2500)
        assert bus.read(1, item("Goal Current")) == -2500
        assert chain.motors[0].applied_current == -2500
        # The X motor beside it keeps its own table: its EEPROM (38) is free, torque off.
        bus.write(2, MODELS["XM430-W350"].item("Current Limit"), 600)
        # A REBOOT restores the RAM from 512 and keeps the EEPROM.
        assert _reply(bus, proto.reboot(1), 1).error == 0
        assert bus.read(1, item("Torque Enable")) == 0
        assert bus.read(1, item("Bus Watchdog")) == 0
        assert bus.read(1, item("Current Limit")) == 3000
        assert bus.read(1, item("Indirect Address 128")) == 600  # EEPROM kept
        assert bus.read(1, item("Feedforward 2nd Gain")) == 0  # RAM restored
        assert bus.read(1, item("Operating Mode")) == 0
        assert bus.read(1, item("Goal Current")) == 3000  # reset to the Current Limit
        assert bus.read(2, MODELS["XM430-W350"].item("Current Limit")) == 600


@pytest.mark.hil
def test_the_bridge_drives_the_mixed_chain_by_bulk_frames():
    """In process: the bridge over the emulated PH42 + XM430 chain reads each motor's block at
    its address (BULK_READ) and writes each Goal Current at its address (BULK_WRITE); the
    joints read what the plant says, and the currents reach each motor."""
    with VirtualChain("serial", SCENARIO) as chain:
        backend = DynamixelBackend("serial", chain.path, description=ARM, timeout_s=0.05,
                                   realtime_tick=True)
        assert (backend.read_instruction, backend.write_instruction) == ("bulk", "bulk")
        backend.enable()
        try:
            x = np.zeros(4)
            good = sum(backend.read(x) for _ in range(20))
            assert good >= 18
            quantum = np.abs(backend.position_quantum())
            assert quantum[0] < quantum[1] / 100  # the PH42's pulses are 148x finer
            assert np.allclose(x[:2], chain.joint_state()[:2], atol=2 * quantum.max())
            tau = np.array([0.5, -0.3])
            assert backend.write(tau)
            time.sleep(0.01)
            assert [m.table[m.a_torque] for m in chain.motors] == [1, 1]
            sent = backend.goal_current_lsb.copy()
            assert [m.applied_current for m in chain.motors] == [int(v) for v in sent]
            assert sent[0] == pytest.approx(500, abs=1) and sent[1] < 0  # 0.5 N m: 500 mA
        finally:
            backend.disable()
    assert "torque off confirmed by all 2" in backend.shutdown_report
    bulk = [e for e in chain.events if e[1] == "bulk-read"]
    assert bulk and not [e for e in chain.events if e[1] in ("sync-read", "fast-sync-read")]


def test_fast_sync_read_is_never_chosen_for_a_mixed_chain():
    """Even with both models answering FAST_SYNC_READ (a firmware the data does not describe),
    a chain whose blocks lie at different addresses is read by BULK_READ; asking for the
    Fast Sync Read is refused in one line."""
    specs = [dataclasses.replace(MODELS[n], fast_sync_read=True)
             for n in ("PH42-020-S300-R", "XM430-W350")]
    read, write, why = choose_transfers(specs)
    assert (read, write) == ("bulk", "bulk") and "BULK_READ" in why
    with pytest.raises(BackendError) as info:
        DynamixelBackend("serial", "/dev/null", description=ARM, read_instruction="fast")
    assert "\n" not in str(info.value) and "FAST_SYNC_READ cannot read this chain" \
        in str(info.value)
    with pytest.raises(BackendError, match="SYNC_WRITE cannot write"):
        DynamixelBackend("serial", "/dev/null", description=ARM, write_instruction="sync")


def test_the_bus_budget_is_the_bulk_frames_sent():
    """The budget counts the frames the mixed chain sends: BULK_WRITE (10 + 7 per motor),
    BULK_READ (10 + 5 per motor) and a status packet of 11 + 16 bytes per motor."""
    backend = DynamixelBackend("serial", "/dev/null", description=ARM, realtime_tick=True)
    b = backend.budget
    assert (b.read_instruction, b.write_instruction) == ("bulk", "bulk")
    assert len(backend._read_frame) == 10 + 5 * 2 == b.sync_read_bytes
    assert backend._write_frame.encode() == 10 + 7 * 2 == b.sync_write_bytes  # its length
    assert b.reply_bytes == 11 + 16
    sync = bus_budget(2, BAUD, adapter_latency_s=0.0, read_length=16)
    assert b.total_bytes == 24 + 20 + 2 * 27 != sync.total_bytes


# ---- cochlea-dxl and cochlea-run over the virtual mixed chain -------------------------------


@pytest.mark.hil
def test_scan_names_an_x_and_a_p_motor_on_one_bus(capsys):
    with VirtualChain("serial", SCENARIO) as chain:
        code = dxl_main(["scan", "--port", chain.path, "--baud", str(BAUD), "--ids", "0-5"])
    out = capsys.readouterr().out
    rows = [line.split() for line in out.splitlines() if line[:1].isdigit()]
    assert code == 0
    assert [(r[1], r[2]) for r in rows] == [("1", "PH42-020-S300-R"), ("2", "XM430-W350")]
    # Each read at its model's address: position mode, torque off, no error, on both.
    for r in rows:
        assert " ".join(r[4:]) == "3 (position) 0 (off) 0 (none)", r
    assert "not read" not in out


@pytest.mark.hil
def test_configure_info_and_reboot_on_the_mixed_chain(capsys):
    """``cochlea-dxl info`` finds the factory registers that differ (at each model's address:
    Bus Watchdog 546 and 98, ...), ``configure`` writes them (the PH42's Current Limit 4000 mA,
    the XM430's in its 2.69 mA LSB), ``info`` then agrees, ``reboot`` brings both back."""
    common = ["--port", None, "--baud", str(BAUD), "--robot", "serial", "--description",
              str(ARM)]
    with VirtualChain("serial", SCENARIO) as chain:
        common[1] = chain.path
        assert dxl_main(["info", *common]) != 0
        out = capsys.readouterr().out
        assert "Bus Watchdog           546" in out and "Bus Watchdog           98" in out
        assert "Current Limit          38       4500 (4500 mA)" in out
        assert dxl_main(["configure", *common]) == 0
        assert chain.motors[0].get(38) == 4000 and chain.motors[0].get(11) == 0
        assert chain.motors[1].get(38) == joint_drives("serial", ARM)[1].current_limit_lsb
        capsys.readouterr()
        assert dxl_main(["info", *common]) == 0
        assert "all 2 motors as the description and the runtime expect" in capsys.readouterr().out
        chain.motors[0].latch_hardware_error(5)  # overload on the PH42 (518)
        assert dxl_main(["reboot", "--port", chain.path, "--baud", str(BAUD), "--ids",
                         "1,2"]) == 0
        out = capsys.readouterr().out
        assert "ID 1: rebooted, back without alert (was 32 (overload))" in out
        assert chain.motors[0].hardware_error == 0


@pytest.mark.slow
@pytest.mark.hil
def test_cochlea_run_converges_over_the_mixed_chain(tmp_path):
    """The emulator as a command (the PH42 and the XM430 answering as themselves), then
    ``cochlea-run --backend dynamixel``: it converges, says BULK_READ + BULK_WRITE, and its
    summary's bus budget is those frames'."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "cochlea.dynamixel.emulator", "--robot", "serial", "--scenario",
         str(SCENARIO)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/"), proc.stderr.read() if proc.poll() is not None else port
        assert "PH42-020-S300-R" in proc.stdout.readline()
        out = tmp_path / "run"
        done = subprocess.run(
            [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
             "joint", "--scenario", str(SCENARIO), "--backend", "dynamixel", "--port", port,
             "--out", str(out), "--watchdog-misses", "300"],
            capture_output=True, text=True, timeout=240, cwd=tmp_path)
    finally:
        proc.terminate()
        proc.communicate(timeout=20)
    assert done.returncode == 0, done.stderr
    assert "cochlea-run: bus: BULK_READ + BULK_WRITE per period" in done.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["converged"] is True, done.stdout
    bus = summary["timing"]["bus"]["bus_budget"]
    assert (bus["read_instruction"], bus["write_instruction"]) == ("BULK_READ", "BULK_WRITE")
    assert "different addresses" in bus["read_choice"]
    assert bus["bytes_per_period"] == (10 + 7 * 2) + (10 + 5 * 2) + 2 * (11 + 16)
    # The current columns (what identification reads) in each motor's own unit: whole mA on
    # the PH42, whole 2.69 mA LSBs on the XM430, and not all zero.
    with open(out / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    shoulder = np.array([float(r["arm.current.shoulder_A"]) for r in rows])
    elbow = np.array([float(r["arm.current.elbow_A"]) for r in rows])
    assert np.count_nonzero(shoulder) > len(rows) / 2 and np.count_nonzero(elbow) > 10
    assert np.allclose(shoulder * 1000.0, np.rint(shoulder * 1000.0), atol=1e-6)
    assert np.allclose(elbow / 2.69e-3, np.rint(elbow / 2.69e-3), atol=1e-3)


@pytest.mark.hil
def test_calibration_recovers_the_p_and_the_x_motor_s_mounting(tmp_path, monkeypatch):
    """``cochlea-dxl calibrate`` on the mixed chain mounted otherwise than its description
    says: each motor's offset comes back within one of its own counts (the PH42's 607500 a
    turn, the XM430's 4096), each direction exactly."""
    import argparse

    from cochlea.dynamixel.bringup import calibrate

    offsets, directions = {1: 100.0, 2: 37.3}, {1: -1}
    description = tmp_path / "planar2_xp.toml"
    description.write_text(ARM.read_text())
    refs = {d.name: q for d, q in zip(joint_drives("serial", ARM),
                                      (math.radians(30.0), math.radians(60.0)))}

    def ask(prompt):
        name = prompt.split(" ")[0].rstrip(":")
        chain.move_joint(name, refs[name] + (0.0 if "reference pose" in prompt else 0.2))
        return ""

    monkeypatch.setattr(calibrate, "ask", ask)
    parser = argparse.ArgumentParser()
    calibrate.add_arguments(parser)
    out = tmp_path / "calibrated.toml"
    with VirtualChain("serial", SCENARIO, truth=Truth(offsets, directions)) as chain:
        code = calibrate.run(parser.parse_args([
            "--robot", "serial", "--port", chain.path, "--description", str(description),
            "--out", str(out), "--reference", "arm.upper=30", "--reference", "arm.forearm=60"]))
        assert not any(m.torque_on for m in chain.motors)
    assert code == 0
    for d in joint_drives("serial", out):
        assert d.direction == directions.get(d.id, 1), d.name
        error = (math.degrees(d.zero_offset) - offsets[d.id] + 180.0) % 360.0 - 180.0
        assert abs(error) <= 360.0 / d.spec.counts_per_rev, (d.name, d.spec.name, error)


def _p_carriage(tmp_path: Path) -> tuple[Path, Path]:
    """tests/data/prismatic3 (a lead-screw carriage between two revolute joints, XM430-W350s)
    with a PH42-020-S300-R on the carriage (the placeholder fit of planar2_xp.toml's)."""
    text = (DATA / "prismatic3.toml").read_text()
    head, sep, tail = text.partition('model = "XM430-W350"')
    head2, sep2, tail2 = tail.partition('model = "XM430-W350"')
    tail2 = tail2.replace('fit = { a = 178.3,', 'fit = { a = 100.0,', 1)
    description = tmp_path / "prismatic3.toml"
    description.write_text(head + sep + head2 + 'model = "PH42-020-S300-R"' + tail2)
    scenario = tmp_path / "prismatic3_joint.toml"
    scenario.write_text((DATA / "prismatic3_joint.toml").read_text())
    return description, scenario


@pytest.mark.hil
def test_home_finds_a_p_carriage_s_stop_and_the_bridge_counts_from_it(tmp_path):
    """``cochlea-dxl home`` drives the PH42 carriage onto its hard stop (its Goal Current at
    550, its present state at 568..583, its homing token at 536), records it, and the bridge
    then counts the carriage from the stop in the PH42's pulses."""
    import argparse

    from cochlea.dynamixel.bringup import home

    description, scenario = _p_carriage(tmp_path)
    drives = joint_drives("serial", description)
    assert [d.spec.name for d in drives] == ["XM430-W350", "PH42-020-S300-R", "XM430-W350"]
    stop, record = 0.03, tmp_path / "homing.json"
    parser = argparse.ArgumentParser()
    home.add_arguments(parser)
    with VirtualChain("serial", scenario, truth=Truth(offset_deg={2: 500.0},
                                                      hard_stop_m=stop)) as chain:
        code = home.run(parser.parse_args([
            "--robot", "serial", "--description", str(description), "--port", chain.path,
            "--record", str(record), "--stop-m", str(stop), "--speed-mm-s", "10",
            "--force-N", "20"]))
        assert code == 0 and not any(m.torque_on for m in chain.motors)
        (entry,) = json.loads(record.read_text())["joints"]
        assert (entry["joint"], entry["motor_id"], entry["marker_address"]) == \
            ("arm.carriage", 2, 536)
        bridge = DynamixelBackend("serial", chain.path, description=description,
                                  timeout_s=0.05, homing="required", homing_record=record)
        assert (bridge.read_instruction, bridge.write_instruction) == ("bulk", "bulk")
        bridge.enable()
        try:
            x = np.zeros(6)
            assert bridge.read(x)
            assert abs(x[1] - chain.joint_state()[1]) <= 3 * abs(drives[1].q_per_count)
            assert abs(x[1] - stop) < 1e-3
        finally:
            bridge.disable()


# ---- bad input and what still refuses ------------------------------------------------------


def test_a_p_motor_whose_limits_are_unsourced_is_refused_in_one_line(tmp_path):
    """The PH54-100-S500-R's Current Limit and counts per turn are unsourced: its description
    is refused in one line naming what to add."""
    (tmp_path / "planar2_xp.toml").write_text(
        ARM.read_text().replace('model = "PH42-020-S300-R"', 'model = "PH54-100-S500-R"'))
    (tmp_path / "scenario.toml").write_text(SCENARIO.read_text())
    with pytest.raises(DescriptionError) as info:
        load_scenario(tmp_path / "scenario.toml")
    message = str(info.value)
    assert "\n" not in message and "PH54-100-S500-R" in message and "not sourced" in message


def test_a_p_motor_whose_counts_per_turn_are_unsourced_is_refused_in_one_line(monkeypatch):
    """Its current sourced but not its pulses per turn: the bridge, the emulator and
    cochlea-dxl (all through joint_drives) refuse it, never guess 4096."""
    spec = MODELS["PH42-020-S300-R"]
    monkeypatch.setitem(drives_module.MODELS, spec.name, dataclasses.replace(
        spec, counts_per_rev=None, unsourced=spec.unsourced + ("counts_per_rev",)))
    with pytest.raises(BackendError) as info:
        joint_drives("serial", ARM)
    assert str(info.value) == (
        "joint arm.upper: the PH42-020-S300-R's counts_per_rev is not sourced yet "
        "(cochlea/dynamixel/models/p.toml): add it from "
        "https://emanual.robotis.com/docs/en/dxl/p/ph42-020-s300-r/")


def test_a_simulated_encoder_of_unsourced_counts_is_refused_not_guessed(tmp_path, monkeypatch):
    """A simulated plant that reports what the motor measures (its encoder's counts) needs
    the model's counts per turn: unsourced, the simulation refuses in one line as the bridge
    does, where it once quantised the P motor's position with the X series' 4096 counts."""
    from cochlea.sim.setup import unit_setups

    spec = MODELS["PH42-020-S300-R"]
    monkeypatch.setitem(drives_module.MODELS, spec.name, dataclasses.replace(
        spec, counts_per_rev=None, unsourced=spec.unsourced + ("counts_per_rev",)))
    (tmp_path / "planar2_xp.toml").write_text(ARM.read_text())
    (tmp_path / "scenario.toml").write_text(
        SCENARIO.read_text() + '\n[plant]\nplant = "ideal"\nposition_encoder = true\n')
    sc = load_scenario(tmp_path / "scenario.toml")
    with pytest.raises(CochleaError) as info:
        unit_setups(sc, cache=False)
    message = str(info.value)
    assert "\n" not in message and message.startswith("joint arm.upper: ")
    assert "PH42-020-S300-R's counts_per_rev is not sourced" in message
    # Without the encoder's grid the plant's position is continuous: nothing to refuse.
    (tmp_path / "scenario.toml").write_text(SCENARIO.read_text())
    assert unit_setups(load_scenario(tmp_path / "scenario.toml"), cache=False)


@pytest.mark.slow
def test_cochlea_run_on_an_unsourced_p_motor_says_one_line(tmp_path):
    (tmp_path / "planar2_xp.toml").write_text(
        ARM.read_text().replace('model = "PH42-020-S300-R"', 'model = "PM54-040-S250-R"'))
    (tmp_path / "scenario.toml").write_text(SCENARIO.read_text())
    done = subprocess.run(
        [sys.executable, "-m", "cochlea.apps.cochlea_run", "--robot", "serial", "--space",
         "joint", "--scenario", str(tmp_path / "scenario.toml"), "--backend", "dynamixel",
         "--port", str(tmp_path / "no-port"), "--out", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode != 0 and "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "PM54-040-S250-R" in lines[0] and "not sourced" in lines[0]

