"""``cochlea-dxl`` when something goes wrong while it moves or configures motors (issue 26),
against ``cochlea-emulator`` on a pseudo-terminal (the fixtures of ``test_dxl_bringup``).

One test per class of defect:

* a hardware alert mid-move (``home``, ``calibrate --torque-fit``): the move stops at once
  (goal current 0, torque off on every motor), nothing is reported as done, nothing written,
  exit 6, one line naming the motor, its error bits in words and the reboot of that motor only;
* a motor that stops answering, answers garbled packets or stale ones (its Realtime Tick
  frozen) mid-move: the same, exit 7;
* an output path that cannot be written (missing folder, a folder that is a file, a read-only
  folder, a FIFO, a device, a folder, a symbolic link): refused before the port is even opened
  (exit 2), never replaced, nothing left behind;
* SIGINT, SIGTERM, SIGHUP during a move: torque off, no record, exit 128 + the signal;
* the reboot advice for a motor already in alert names that motor only.
"""

from __future__ import annotations

import os
import signal
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from cochlea.apps import cochlea_dxl
from cochlea.dynamixel.bringup import calibrate, common
from cochlea.dynamixel.drives import joint_drives
from cochlea.dynamixel.emulator import Faults, check_faults
from cochlea.errors import CochleaError
from cochlea.resources import ROBOTS_DIR
from tests.test_dxl_bringup import dxl, emulator, scanned, wait_for_alert

hil = pytest.mark.hil

SLIDER = next(d for d in joint_drives("parallel") if d.type == "prismatic")
LEFT = next(d for d in joint_drives("parallel") if d.type == "revolute")
PARALLEL_IDS = [d.id for d in joint_drives("parallel")]
#: How soon after the fault the tool must have turned the torque off (s): one loop period
#: (10 ms) and a few failed transactions, with room for a loaded machine.
STOP_WITHIN_S = 1.0


def timeline(log: Path) -> list[tuple[float, str, int, int, str]]:
    """``(t, kind, id, address, value)`` of every event in the emulator's log."""
    rows = []
    for line in log.read_text().splitlines():
        t, kind, motor, address, value = line.split(" ", 4)
        rows.append((float(t), kind, int(motor.split("=")[1]), int(address.split("=")[1]),
                     value.split("=", 1)[1]))
    return rows


def assert_stopped_after_fault(log: Path, moved: int) -> None:
    """After the emulator's fault: nothing turned on, at most the one goal already on its way
    when the fault came (before the first torque off), every motor of the chain sent Torque
    Enable 0 (the moved one within STOP_WITHIN_S)."""
    rows = timeline(log)
    fault = next(t for t, kind, *_ in rows if kind == "fault")
    after = [(t, i, a, v) for t, kind, i, a, v in rows if kind == "write" and t >= fault]
    assert not any(a == 64 and v != "0" for _, _, a, v in after), after
    torque_off = {i for _, i, a, v in after if a == 64 and v == "0"}
    silent = {i for t, kind, i, _, v in rows if kind == "fault" and "stops answering" in v}
    assert torque_off | silent == set(PARALLEL_IDS)
    first_off = min(t for t, _, a, v in after if a == 64 and v == "0")
    goals = [t for t, _, a, v in after if a == 102 and v != "0"]
    assert len(goals) <= 1 and all(t < first_off for t in goals), after
    first = min((t for t, i, a, _ in after if a == 64 and i == moved), default=None)
    if moved not in silent:
        assert first is not None and first - fault < STOP_WITHIN_S, (fault, first)


def only(tmp_path: Path, *names: str) -> None:
    """Nothing in ``tmp_path`` but ``names``: no record, no CSV, no temporary file."""
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names)


# ---- a hardware alert mid-move ---------------------------------------------------------------


@hil
def test_an_alert_mid_move_stops_home_without_a_record(tmp_path, capsys):
    log, record = tmp_path / "emu.log", tmp_path / "r.json"
    # Overload (bit 5) half a second after the homing turned the slider's torque on: the
    # motor's torque goes off and the slider rests, which the old loop took for the stop.
    with emulator("parallel", log, "--hardware-error", f"{SLIDER.id}:5", "--fault-delay",
                  "0.5") as port:
        code, out, err = dxl(capsys, "home", "--robot", "parallel", "--port", port, "--record",
                             str(record), "--timeout-s", "30")
    assert code == common.EXIT_ALERT == 6, err
    assert err.count("\n") == 1 and "homed" not in out
    assert err.startswith("cochlea-dxl home: hardware alert during the homing of slider.d1: "
                          f"ID {SLIDER.id} (slider.d1, {SLIDER.spec.name}): 32 (overload); "
                          "stopped: goal current 0 and torque off on every motor;")
    assert err.rstrip().endswith(f"cochlea-dxl reboot --ids {SLIDER.id} --port {port} --baud "
                                 "4000000")
    only(tmp_path, "emu.log")
    assert_stopped_after_fault(log, SLIDER.id)


@hil
def test_an_alert_mid_move_stops_the_torque_fit_without_a_csv(tmp_path, capsys, monkeypatch):
    log, samples = tmp_path / "emu.log", tmp_path / "fit.csv"

    def ask(prompt):  # the user reads the scale: the overheating comes meanwhile
        if "force on the scale" in prompt:
            time.sleep(0.4)
            return "2.5"
        return ""

    monkeypatch.setattr(calibrate, "ask", ask)
    with emulator("parallel", log, "--hardware-error", f"{LEFT.id}:2", "--fault-delay",
                  "0.2") as port:
        code, out, err = dxl(capsys, "calibrate", "--torque-fit", "--robot", "parallel",
                             "--port", port, "--joint", LEFT.name, "--lever-m", "0.1",
                             "--csv", str(samples))
    assert code == common.EXIT_ALERT, err
    assert err.count("\n") == 1 and "fit =" not in out
    assert (f"hardware alert during the torque fit of {LEFT.name}: ID {LEFT.id} ({LEFT.name}, "
            f"{LEFT.spec.name}): 4 (overheating); stopped") in err
    assert f"reboot --ids {LEFT.id} --port" in err
    only(tmp_path, "emu.log")
    assert_stopped_after_fault(log, LEFT.id)


# ---- a motor lost mid-move ---------------------------------------------------------------------


@hil
@pytest.mark.parametrize("fault, says", [
    (["--silent-motor", str(SLIDER.id)], "stopped answering"),
    (["--corrupt-crc", "1", "--fault-ids", str(SLIDER.id)], "a garbled packet (CRC)"),
    # Its last answer again and again: the slider looks still, which the old loop took for
    # the stop; its Realtime Tick does not move.
    (["--stale-replies", str(SLIDER.id), "--stale-unicast"], "answered a stale packet"),
], ids=["silent", "garbled", "stale"])
def test_a_motor_lost_mid_move_stops_home_without_a_record(tmp_path, capsys, fault, says):
    log, record = tmp_path / "emu.log", tmp_path / "r.json"
    with emulator("parallel", log, *fault, "--fault-delay", "0.5") as port:
        code, out, err = dxl(capsys, "home", "--robot", "parallel", "--port", port, "--record",
                             str(record), "--timeout-s", "30")
    assert code == common.EXIT_LOST == 7, err
    assert err.count("\n") == 1 and "homed" not in out
    assert f"ID {SLIDER.id} (slider.d1, {SLIDER.spec.name})" in err and says in err
    assert "during the homing of slider.d1: stopped" in err and "nothing written" in err
    if "silent" in fault[0]:  # it cannot confirm its torque off, and the line says so
        assert f"NOT confirmed by ID {SLIDER.id}" in err
    only(tmp_path, "emu.log")
    assert_stopped_after_fault(log, SLIDER.id)


def test_stale_unicast_needs_the_stale_fault_it_extends():
    with pytest.raises(CochleaError, match="--stale-unicast: expected --stale-replies"):
        check_faults(Faults(stale_unicast=True), PARALLEL_IDS)
    check_faults(Faults(stale=(SLIDER.id, -1), stale_unicast=True), PARALLEL_IDS)


# ---- outputs checked before anything moves ---------------------------------------------------


def _read_only_folder(tmp_path: Path) -> Path:
    """A folder this process cannot create a file in: a mode 555 one, or (root ignores modes)
    /sys, which takes no new file whoever asks."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    if os.access(folder, os.W_OK):
        folder.chmod(0o755)
        folder.rmdir()
        return Path("/sys")
    return folder


@pytest.mark.parametrize("case", ["missing folder", "folder is a file", "read-only folder",
                                  "FIFO", "device", "folder", "symbolic link"])
@pytest.mark.parametrize("command", ["home", "calibrate", "torque-fit"])
def test_an_unwritable_output_is_refused_before_the_port_opens(tmp_path, capsys, case,
                                                                command):
    """Checked before the port is opened (a missing port would be exit 5): nothing can have
    moved. The path is never replaced and nothing is left behind."""
    made = {"file": tmp_path / "file", "fifo": tmp_path / "fifo", "dir": tmp_path / "dir",
            "target": tmp_path / "target.json"}
    made["file"].write_text("x")
    os.mkfifo(made["fifo"])
    made["dir"].mkdir()
    made["target"].write_text("keep")
    path = {"missing folder": tmp_path / "none" / "out",
            "folder is a file": made["file"] / "out",
            "read-only folder": _read_only_folder(tmp_path) / "out",
            "FIFO": made["fifo"], "device": Path("/dev/null"), "folder": made["dir"],
            "symbolic link": tmp_path / "link"}[case]
    if case == "symbolic link":
        path.symlink_to(made["target"])
    before = sorted(p.name for p in tmp_path.iterdir())
    port = str(tmp_path / "ttyUSB9")  # never opened
    argv, option = {
        "home": (["home", "--robot", "parallel", "--record", str(path)], "--record"),
        "calibrate": (["calibrate", "--robot", "parallel", "--out", str(path)], "--out"),
        "torque-fit": (["calibrate", "--torque-fit", "--robot", "parallel", "--joint",
                        LEFT.name, "--lever-m", "0.1", "--csv", str(path)], "--csv"),
    }[command]
    code, out, err = dxl(capsys, *argv, "--port", port)
    assert code == 2, err
    assert out == "" and err.count("\n") == 1 and f"{option} {path}" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert stat.S_ISFIFO(os.lstat(made["fifo"]).st_mode)
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)
    assert made["target"].read_text() == "keep"
    if case == "symbolic link":
        assert path.is_symlink()


def test_in_place_refuses_a_description_it_would_replace_by_a_file(tmp_path, capsys):
    """--in-place renames a new file over the description: a symbolic link to it would be
    replaced by a file, the linked description left as it was; refused before the port."""
    real = tmp_path / "real.toml"
    real.write_text((ROBOTS_DIR / "parallel.toml").read_text())
    link = tmp_path / "parallel.toml"
    link.symlink_to(real)
    code, out, err = dxl(capsys, "calibrate", "--robot", "parallel", "--description", str(link),
                         "--in-place", "--port", str(tmp_path / "ttyUSB9"))
    assert code == 2 and err.count("\n") == 1 and "symbolic link" in err, err
    assert link.is_symlink() and sorted(p.name for p in tmp_path.iterdir()) == [
        "parallel.toml", "real.toml"]


# ---- signals during a move ---------------------------------------------------------------------


@hil
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP],
                         ids=lambda s: signal.Signals(s).name)
def test_a_signal_during_a_move_stops_it_without_a_record(tmp_path, signum):
    log, record = tmp_path / "emu.log", tmp_path / "r.json"
    with emulator("parallel", log) as port:
        proc = subprocess.Popen([sys.executable, "-m", "cochlea.apps.cochlea_dxl", "home",
                                 "--robot", "parallel", "--port", port, "--record",
                                 str(record), "--timeout-s", "60"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            line = proc.stdout.readline()
            assert line.startswith("homing slider.d1"), line + proc.stderr.read()
            time.sleep(0.3)  # the move is under way (the default scenario has no stop)
            proc.send_signal(signum)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    assert proc.returncode == 128 + signum, err
    assert err == (f"cochlea-dxl home: interrupted by {signal.Signals(signum).name} (every "
                   "torque is off); nothing done, nothing written\n")
    assert "homed" not in out
    only(tmp_path, "emu.log")
    rows = timeline(log)
    on = max(t for t, kind, i, a, v in rows if kind == "write" and a == 64 and v == "1")
    offs = {i for t, kind, i, a, v in rows if kind == "write" and a == 64 and v == "0"
            and t > on}
    assert offs == set(PARALLEL_IDS)  # torque off on every motor after the last one on
    assert cochlea_dxl.EXIT_INTERRUPTED == 130


def test_a_signal_during_the_clean_up_waits_until_every_torque_is_off():
    """A signal that arrives while the stop turns the torques off is held until they all are,
    then stops the command (its exit code) instead of cutting the clean-up short."""
    drives = joint_drives("parallel")

    class Bus:  # the clean-up's side of common.Bus
        watching = None
        _ticks: dict = {}
        off: list[int] = []

        def torque_off(self, every):
            for d in every:
                if d is every[0]:  # the signal comes as the first motor is turned off
                    signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)
                    time.sleep(0.01)
                self.off.append(d.id)
            return []

    bus = Bus()
    with cochlea_dxl._stop_signals():
        with pytest.raises(cochlea_dxl.Interrupted) as stop:
            with common.motion(bus, [], drives, "a test"):
                raise common.MotorLost("ID 1 stopped answering", 1)
    assert stop.value.signum == signal.SIGTERM
    assert bus.off == [d.id for d in drives]


def test_a_signal_while_the_outputs_are_written_cannot_leave_them_unreported():
    """Once the move is over and the torque off, the record is written and "homed" printed
    with the stop signals ignored: no record left under "nothing written". A signal before
    and after still stops the command."""
    main = threading.main_thread().ident
    with cochlea_dxl._stop_signals():
        with common.finishing():
            signal.pthread_kill(main, signal.SIGTERM)
            time.sleep(0.01)
            written = True
        assert written
        with pytest.raises(cochlea_dxl.Interrupted):
            signal.pthread_kill(main, signal.SIGHUP)
            time.sleep(0.01)


# ---- the reboot advice ---------------------------------------------------------------------


@hil
def test_the_reboot_advice_names_only_the_motors_in_alert(tmp_path, capsys):
    with emulator("serial", tmp_path / "emu.log", "--hardware-error", "3:2") as port:
        wait_for_alert(port, 3)
        for argv in (["configure", "--robot", "serial"], ["calibrate", "--robot", "serial",
                                                          "--out", str(tmp_path / "c.toml")]):
            code, out, err = dxl(capsys, *argv, "--port", port)
            assert code == 5 and err.count("\n") == 1, err
            assert "ID 3 (arm1.link3, MX-64)" in err and "overheating" in err
            assert f"cochlea-dxl reboot --ids 3 --port {port} --baud 4000000" in err
            assert "ID 1 " not in err and "ID 2 " not in err
        code, out, _ = dxl(capsys, "info", "--robot", "serial", "--port", port)
        assert code == 1 and f"reboot --ids 3 --port {port}" in out
    assert not (tmp_path / "c.toml").exists()


@hil
def test_a_goal_refused_after_the_bus_watchdog_expired_says_so(tmp_path):
    """A motor whose Bus Watchdog expired refuses every goal with a Data Range Error (the
    e-Manual's rule, which the emulator follows): the one line names the watchdog, the cause a
    user can act on, not only the error bit (seen when a loaded machine stalled ``home``)."""
    with emulator("parallel", tmp_path / "emu.log") as port:
        bus = common.Bus(port, 4_000_000)
        try:
            spec = SLIDER.spec
            bus.write(SLIDER.id, spec.item("Bus Watchdog"), 1)  # 20 ms
            bus.write(SLIDER.id, spec.item("Torque Enable"), 1)
            bus.write(SLIDER.id, spec.item("Goal Current"), 0)
            time.sleep(0.2)  # no contact for ten watchdog periods: it expires
            with pytest.raises(common.BusError) as caught:
                bus.write(SLIDER.id, spec.item("Goal Current"), -10)
        finally:
            bus.write(SLIDER.id, SLIDER.spec.item("Torque Enable"), 0)
            bus.close()
    message = str(caught.value)
    assert "Data Range Error" in message and "Bus Watchdog expired" in message, message


@hil
def test_a_stop_during_the_baud_writes_leaves_every_motor_at_the_new_rate(tmp_path, capsys,
                                                                          monkeypatch):
    """``configure --baud-to``: a SIGTERM (or Ctrl-C, a hang-up) that comes between two
    motors' Baud Rate writes waits until every motor has its new rate, so the chain is never
    left at two rates that no single ``--baud`` reaches."""
    real_write, sent = common.Bus.write, []

    def write(bus, motor_id, item, value, reply=True):
        if item.name == "Baud Rate" and not sent:
            sent.append(motor_id)
            os.kill(os.getpid(), signal.SIGTERM)  # arrives before the other motors' writes
        return real_write(bus, motor_id, item, value, reply)

    monkeypatch.setattr(common.Bus, "write", write)
    with emulator("parallel", tmp_path / "emu.log", "--baud", "57600") as port:
        code, _, err = dxl(capsys, "configure", "--robot", "parallel", "--port", port,
                           "--baud", "57600", "--baud-to", "4000000")
        assert sent and code == 128 + signal.SIGTERM, err
        monkeypatch.setattr(common.Bus, "write", real_write)
        code, out, _ = dxl(capsys, "scan", "--port", port, "--baud", "57600", "--baud",
                           "4000000", "--ids", "1-8")
    assert {b for b, _, _ in scanned(out)} == {4_000_000} and len(scanned(out)) == 5, out
