"""``cochlea-dxl`` scan, info, configure and reboot against ``cochlea-emulator`` (a second process
on a pseudo-terminal, as on a bench): scan finds exactly the chain at its baud rate and nothing
at another; info passes a configured chain and flags a register changed behind its back;
configure's dry run writes nothing, a second run writes nothing, its verify pass catches a write
that did not take, and a baud change is verified at the new rate; reboot clears a hardware
alert. Wrong options and a missing port end in one line and their exit codes."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from cochlea.apps.cochlea_dxl import main
from cochlea.dynamixel.bringup.common import Bus, load_drives
from cochlea.dynamixel.control_table import MX64, XM540_W270
from cochlea.dynamixel.drives import joint_drives
from tests.test_dynamixel_hil import emulator as hil_emulator

hil = pytest.mark.hil


def emulator(robot: str, log: Path, *options: str):
    """``cochlea-emulator`` (its default scenario) with real motors' baud behaviour; yields its
    pseudo-terminal."""
    return hil_emulator(robot, f"{robot}_joint", log, "--check-baud", *options)


def dxl(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def events(log: Path, kind: str) -> list[tuple[int, int, int]]:
    """``(id, address, value)`` of the emulator's logged events of ``kind`` (read the log once
    the emulator stopped: it is buffered)."""
    rows = []
    for line in log.read_text().splitlines():
        t, k, *fields = line.split()
        if k == kind:
            values = dict(f.split("=", 1) for f in fields)
            rows.append((int(values["id"]), int(values["address"]), values["value"]))
    return rows


def scanned(out: str) -> list[tuple[int, int, str]]:
    """``(baud, id, model)`` of scan's table rows."""
    return [(int(r[0]), int(r[1]), r[2]) for r in (line.split() for line in out.splitlines())
            if r and r[0].isdigit()]


# ---- scan ----------------------------------------------------------------------------------------


@hil
@pytest.mark.parametrize("per_id", [False, True])
def test_scan_finds_exactly_the_chain_at_its_baud_and_nothing_at_another(tmp_path, capsys,
                                                                         per_id):
    drives = joint_drives("parallel")
    chain = {d.id: d.spec.name for d in drives if d.id != 4}
    with emulator("parallel", tmp_path / "emu.log", "--baud", "1000000",
                  "--missing-motor", "4") as port:
        more = ["--per-id"] if per_id else []
        code, out, _ = dxl(capsys, "scan", "--port", port, "--baud", "57600", "--baud",
                           "1000000", "--ids", "0-20", *more)
        assert code == 0
        assert scanned(out) == [(1_000_000, i, chain[i]) for i in sorted(chain)]
        assert f"found {len(chain)} motors ({len(chain)} at 1000000 baud" in out
        # At the wrong rate only: nothing, said in one line, exit 1.
        code, out, err = dxl(capsys, "scan", "--port", port, "--baud", "4000000", "--ids",
                             "1-6", *more)
        assert code == 1 and out == "" and err.count("\n") == 1
        assert "no motor answered" in err and "4000000 baud (IDs 1-6)" in err
    # Nothing was written by a scan.
    log = tmp_path / "emu.log"
    assert events(log, "write") == [] and events(log, "reboot") == []
    assert {i for i, _, _ in events(log, "ping")} == set(chain)


def test_the_models_the_descriptions_use_are_the_ones_scan_names():
    models = {d.spec for robot in ("serial", "parallel") for d in joint_drives(robot)}
    assert models <= {MX64, XM540_W270}


# ---- configure and info --------------------------------------------------------------------------


@hil
def test_configure_dry_run_writes_nothing_then_configures_idempotently(tmp_path, capsys):
    log = tmp_path / "emu.log"
    drives = joint_drives("serial")
    with emulator("serial", log) as port:
        code, out, _ = dxl(capsys, "info", "--robot", "serial", "--port", port)
        assert code == 1 and "DIFFERS" in out  # factory settings: position mode, 500 us, ...
        code, out, _ = dxl(capsys, "configure", "--robot", "serial", "--port", port,
                           "--dry-run")
        planned = [line for line in out.splitlines() if line.startswith("would write ")]
        assert code == 0 and "nothing written" in out
        # Every register that differs from the runtime's needs, per motor, with units.
        assert len(planned) == 3 * len(drives)
        for d in drives:
            assert (f"would write ID {d.id} ({d.name}, MX-64): Current Limit (38) 1941 (6522 mA)"
                    f" -> {d.current_limit_lsb} (" in out)
        assert "Return Delay Time (9) 250 (500 us) -> 0 (0 us)" in out
        code, out, _ = dxl(capsys, "configure", "--robot", "serial", "--port", port)
        assert code == 0 and "verified by reading back" in out
        assert [line.replace("writing ", "would write ", 1) for line in out.splitlines()
                if line.startswith("writing ")] == planned
        # Idempotent: the second run finds nothing to write.
        code, out, _ = dxl(capsys, "configure", "--robot", "serial", "--port", port)
        assert code == 0 and "already configured" in out
        code, out, _ = dxl(capsys, "info", "--robot", "serial", "--port", port)
        assert code == 0 and "DIFFERS" not in out and "all 6 motors as" in out
    writes = events(log, "write")
    # The dry run and the second run wrote nothing: the writes are exactly the plan's, once.
    assert sorted((i, a) for i, a, _ in writes) == sorted(
        (d.id, a) for d in drives for a in (11, 9, 38))
    assert all(a != 64 for _, a, _ in writes)  # the torque was never touched, let alone on
    for d in drives:
        assert (d.id, 38, str(d.current_limit_lsb)) in writes
        assert (d.id, 11, "0") in writes and (d.id, 9, "0") in writes


@hil
def test_info_flags_a_register_changed_behind_its_back(tmp_path, capsys):
    with emulator("parallel", tmp_path / "emu.log") as port:
        assert dxl(capsys, "configure", "--robot", "parallel", "--port", port)[0] == 0
        d = load_drives_for("parallel")[2]
        with Bus(port, 4_000_000) as bus:
            bus.write(d.id, d.spec.item("Return Delay Time"), 100)
            bus.write(d.id, d.spec.item("Bus Watchdog"), 5)  # the runtime's own: fine
        code, out, _ = dxl(capsys, "info", "--robot", "parallel", "--port", port)
        assert code == 1
        flagged = [line for line in out.splitlines() if line.rstrip().endswith("DIFFERS")]
        assert len(flagged) == 1 and "Return Delay Time" in flagged[0]
        assert "100 (200 us)" in flagged[0]
        assert out.index(f"ID {d.id} ({d.name}") < out.index(flagged[0])
        assert "1 register differs" in out
        # configure puts it back, and the watchdog off at rest: those two only.
        code, out, _ = dxl(capsys, "configure", "--robot", "parallel", "--port", port)
        writes = [line for line in out.splitlines() if line.startswith("writing ")]
        assert code == 0 and len(writes) == 2
        assert f"ID {d.id} ({d.name}, {d.spec.name}): Bus Watchdog (98) 5 (100 ms) -> 0" \
            in writes[0] and "Return Delay Time (9) 100 (200 us) -> 0" in writes[1]


def load_drives_for(robot: str):
    class Args:
        description = None

    Args.robot = robot
    return load_drives(Args)


@hil
def test_verify_catches_a_register_that_did_not_take(tmp_path, capsys):
    with emulator("serial", tmp_path / "emu.log", "--ignore-write", "2:9") as port:
        code, out, err = dxl(capsys, "configure", "--robot", "serial", "--port", port)
        assert code == 1
        assert ("verify: ID 2 (arm1.link2, MX-64): Return Delay Time (9) reads 250 (500 us), "
                "expected 0 (0 us)") in out
        assert out.count("verify: ") == 1 and err.count("\n") == 1
        assert "verify failed on 1 register" in err


@hil
def test_a_wrong_chain_or_an_alert_stops_configure_before_any_write(tmp_path, capsys):
    log = tmp_path / "emu.log"
    with emulator("serial", log, "--model-number", "5:1120", "--missing-motor", "2") as port:
        code, _, err = dxl(capsys, "configure", "--robot", "serial", "--port", port)
        assert code == 5 and err.count("\n") == 1
        assert "ID 2 (arm1.link2, MX-64) did not answer PING" in err
        assert "ID 5 (arm2.link2, MX-64) is XM540-W270 (1120), not the MX-64's 311" in err
        code, _, err = dxl(capsys, "info", "--robot", "serial", "--port", port)
        assert code == 5 and "did not answer PING" in err
    assert events(log, "write") == []


@hil
def test_baud_change_is_last_and_verified_at_the_new_rate(tmp_path, capsys):
    with emulator("parallel", tmp_path / "emu.log", "--baud", "57600") as port:
        code, out, _ = dxl(capsys, "configure", "--robot", "parallel", "--port", port, "--baud",
                           "57600", "--baud-to", "4000000")
        assert code == 0 and "verified by reading back at 4000000 baud" in out
        lines = [line for line in out.splitlines() if line.startswith("writing ")]
        assert all("Baud Rate" in line for line in lines[-5:])
        assert not any("Baud Rate" in line for line in lines[:-5])
        code, out, _ = dxl(capsys, "scan", "--port", port, "--baud", "57600", "--baud",
                           "4000000", "--ids", "1-8")
        assert {b for b, _, _ in scanned(out)} == {4_000_000} and len(scanned(out)) == 5
        code, out, _ = dxl(capsys, "info", "--robot", "parallel", "--port", port)
        assert code == 0


# ---- reboot --------------------------------------------------------------------------------------


def wait_for_alert(port: str, motor_id: int) -> None:
    """Start the emulator's fault clock (it counts from the first Torque Enable 1) and wait
    until the motor raised its alert (which turns its torque off)."""
    with Bus(port, 4_000_000) as bus:
        bus.write(motor_id, MX64.item("Torque Enable"), 1)
        deadline = time.monotonic() + 10
        while not bus.alert(motor_id):
            assert time.monotonic() < deadline, "the emulator did not raise the alert"
            time.sleep(0.01)


@hil
def test_reboot_clears_a_hardware_alert(tmp_path, capsys):
    log = tmp_path / "emu.log"
    with emulator("serial", log, "--hardware-error", "3:2") as port:
        wait_for_alert(port, 3)
        code, out, _ = dxl(capsys, "scan", "--port", port, "--baud", "4000000", "--ids", "1-6")
        row3 = next(line for line in out.splitlines() if line.split()[1:2] == ["3"])
        assert code == 0 and "4 (overheating)" in row3
        assert f"reboot --port {port} --baud 4000000 --ids 3" in out
        # configure refuses a motor in alert, before any write.
        code, _, err = dxl(capsys, "configure", "--robot", "serial", "--port", port)
        assert code == 5 and "ID 3 (arm1.link3, MX-64): 4 (overheating)" in err
        # An ID that is not there: nothing rebooted.
        code, _, err = dxl(capsys, "reboot", "--port", port, "--ids", "3,9")
        assert code == 5 and "ID 9 did not answer PING" in err and "nothing rebooted" in err
        code, out, _ = dxl(capsys, "reboot", "--port", port, "--ids", "3")
        assert code == 0, out
        assert "ID 3: rebooted, back without alert (was 4 (overheating)); torque off" in out
        code, out, _ = dxl(capsys, "scan", "--port", port, "--baud", "4000000", "--ids", "3")
        assert "0 (none)" in out and "0 (off)" in out and "hardware alert" not in out
    assert [i for i, _, _ in events(log, "reboot")] == [3]
    # Only the test's own Torque Enable 1 (to start the fault); the tools wrote nothing.
    assert events(log, "write") == [(3, 64, "1")]


# ---- options and the port ---------------------------------------------------------------------


@pytest.mark.parametrize("argv, text", [
    (["scan", "--port", "/dev/null", "--baud", "12345"], "--baud: expected a Dynamixel baud"),
    (["scan", "--port", "/dev/null", "--ids", "1-300"], "--ids: expected motor IDs 0..252"),
    (["scan", "--port", "/dev/null", "--ids", "x"], "--ids: expected motor IDs"),
    (["reboot", "--port", "/dev/null"], "--ids"),
    (["info", "--robot", "delta", "--port", "/dev/null"], "--robot: invalid choice"),
    (["configure", "--robot", "serial"], "--port"),
    (["configure", "--robot", "serial", "--port", "/dev/null", "--baud-to", "9"],
     "--baud-to: expected a Dynamixel baud"),
    (["frobnicate"], "invalid choice"),
    (["calibrate"], "the following arguments are required: --robot, --port"),
    ([], "SUBCOMMAND"),
])
def test_bad_options_are_one_line_and_exit_2(capsys, argv, text):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and text in err and err.count("\n") == 1, err


def test_a_bad_description_is_exit_2_and_a_missing_port_exit_5(tmp_path, capsys):
    code, _, err = dxl(capsys, "info", "--robot", "serial", "--port", "/dev/null",
                       "--description", str(tmp_path / "none.toml"))
    assert code == 2 and "--description" in err and "no such file" in err
    bad = tmp_path / "bad.toml"
    bad.write_text("format = 1\n")
    code, _, err = dxl(capsys, "configure", "--robot", "serial", "--port", "/dev/null",
                       "--description", str(bad))
    assert code == 2 and str(bad) in err and err.count("\n") == 1
    for argv in (["scan", "--port", str(tmp_path / "ttyUSB9")],
                 ["reboot", "--port", str(tmp_path / "ttyUSB9"), "--ids", "1"]):
        code, out, err = dxl(capsys, *argv)
        assert code == 5 and out == "" and err.count("\n") == 1
        assert f"--port {tmp_path / 'ttyUSB9'}: cannot open the serial port" in err


@pytest.mark.slow
def test_the_console_script_prints_no_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "cochlea.apps.cochlea_dxl", "info", "--robot",
                           "serial", "--port", str(tmp_path / "none")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 5 and done.stdout == ""
    assert done.stderr.startswith("cochlea-dxl info: --port ") and done.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []  # nothing left behind


@hil
@pytest.mark.parametrize("subcommand", ["home", "calibrate --torque-fit"])
def test_what_turns_a_torque_on_refuses_a_motor_in_hardware_alert(tmp_path, capsys,
                                                                  subcommand):
    """home and the torque fit enable a motor: one in alert (torque held off until a reboot)
    is refused before any write, naming the alert and cochlea-dxl reboot (exit 5)."""
    slider = next(d for d in joint_drives("parallel") if d.type == "prismatic")
    left = next(d for d in joint_drives("parallel") if d.type == "revolute")
    target = slider if subcommand == "home" else left
    log = tmp_path / "emu.log"
    options = (["--record", str(tmp_path / "r.json")] if subcommand == "home" else
               ["--joint", target.name, "--lever-m", "0.1", "--csv", str(tmp_path / "f.csv")])
    with emulator("parallel", log, "--hardware-error", f"{target.id}:2") as port:
        wait_for_alert(port, target.id)
        code, _, err = dxl(capsys, *subcommand.split(), "--robot", "parallel", "--port", port,
                           *options)
    assert code == 5, err
    assert (f"ID {target.id} ({target.name}, {target.spec.name}) is in hardware alert "
            "(overheating)") in err
    assert f"cochlea-dxl reboot --ids {target.id}" in err
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "f.csv").exists()
    # Only the test's own Torque Enable 1 (to start the fault); the tool wrote nothing.
    assert events(log, "write") == [(target.id, 64, "1")]
