"""Issue 28: the controller on emulated Cortex-M cores. ``make qemu-firmware`` cross-compiles the
replay firmware of embedded/ports/qemu_mps2/ (the period loop of the portable core: supervisor,
generated controller, clip, goal currents; on canned measurements of a host simulation) for
QEMU's mps2-an386 (Cortex-M4F) and mps2-an500 (Cortex-M7), in double and in float, and the
same replay for the host. Each firmware runs under qemu-system-arm with semihosting and its
rows are compared with the host build's: the goal currents equal, the commands to 1e-12 of the
run's peak in double (newlib's libm is not glibc's: bit-identical is not what we get) and to
5e-5 of it in float. See docs/embedded.md, "Cortex-M under QEMU".

The tools come from embedded/ports/ensure_tools.sh (it installs them with apt as root): when
they are missing and cannot be installed the tests fail with its one line, they do not skip."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
PORTS = ROOT / "embedded" / "ports"
QEMU_DIR = PORTS / "qemu_mps2"
ENSURE = PORTS / "ensure_tools.sh"
SCENARIOS = ("serial_task", "parallel_task_realistic")
MACHINES = {"an386": "cortex-m4", "an500": "cortex-m7"}
PRECISIONS = ("double", "float")
PERIODS = 300
#: The bounds, relative to the run's peak command of each joint (docs/embedded.md).
DOUBLE_BOUND, FLOAT_BOUND = 1e-12, 5e-5
#: The float build's final estimate against the host's, relative to its norm.
FLOAT_ESTIMATE_BOUND = 1e-5
#: The rule numbers of embedded/core/cochlea_rt.h.
COMPLETED, POSITION_LIMIT = 1, 3


def qemu_command(machine: str, elf: Path, out: Path) -> list[str]:
    """The emulator's command line: no display, no monitor, no UART; the semihosting console
    (SYS_WRITE0) into ``out``, the firmware's SYS_EXIT status as QEMU's exit status; one
    nanosecond of virtual time per instruction (-icount shift=0: the C line counts them)."""
    return ["qemu-system-arm", "-M", f"mps2-{machine}", "-cpu", MACHINES[machine],
            "-icount", "shift=0",
            "-nographic", "-monitor", "none", "-serial", "none",
            "-chardev", f"file,id=semihost,path={out}",
            "-semihosting-config", "enable=on,target=native,chardev=semihost",
            "-kernel", str(elf)]


def ensure_tools() -> None:
    run = subprocess.run(["bash", str(ENSURE)], capture_output=True, text=True, timeout=900)
    if run.returncode != 0:
        pytest.fail(run.stderr.strip() or f"ensure_tools.sh exited {run.returncode}",
                    pytrace=False)


def make_firmware(build: Path, *extra: str, targets: tuple[str, ...] = ("qemu-firmware",)):
    run = subprocess.run(["make", "--no-print-directory", "-s", *targets, f"BUILD={build}",
                          *extra], cwd=ROOT, capture_output=True, text=True, timeout=900)
    if run.returncode != 0:
        pytest.fail(f"make {' '.join(targets)} failed:\n{run.stderr[-4000:]}", pytrace=False)


def run_qemu(machine: str, elf: Path, out: Path) -> tuple[int, str]:
    out.unlink(missing_ok=True)
    run = subprocess.run(qemu_command(machine, elf, out), capture_output=True, text=True,
                         timeout=120, stdin=subprocess.DEVNULL)
    return run.returncode, out.read_text() if out.exists() else ""


def parse(text: str) -> dict:
    """The firmware's lines (replay.c): header, rows (commands as doubles, goal currents as
    int16), the final estimate and the end."""
    def real(h: str) -> float:
        return struct.unpack(">d", bytes.fromhex(h))[0]

    def int16(h: str) -> int:
        return struct.unpack(">h", bytes.fromhex(h))[0]

    out = {"rows": [], "tau": [], "goal": []}
    for line in text.splitlines():
        kind, *fields = line.split()
        if kind == "S":
            out["header"] = (fields[0], fields[1], int(fields[2], 16), int(fields[3], 16))
        elif kind == "R":
            nq = (len(fields) - 1) // 2
            out["rows"].append(int(fields[0], 16))
            out["tau"].append([real(h) for h in fields[1:1 + nq]])
            out["goal"].append([int16(h) for h in fields[1 + nq:]])
        elif kind == "P":
            out["p_hat"] = np.array([real(h) for h in fields])
        elif kind == "C":
            out["ticks"] = tuple(int(h, 16) for h in fields)
        elif kind == "E":
            out["end"] = (int(fields[0], 16), int(fields[1], 16))
        else:
            raise AssertionError(f"unexpected line {line!r}")
    out["tau"], out["goal"] = np.array(out["tau"]), np.array(out["goal"])
    return out


@pytest.fixture(scope="module")
def firmware(tmp_path_factory):
    """``make qemu-firmware`` into a temporary build folder, and the host replays' output."""
    ensure_tools()
    build = tmp_path_factory.mktemp("qemu-build")
    make_firmware(build)
    hosts = {}
    for scenario in SCENARIOS:
        for precision in PRECISIONS:
            run = subprocess.run([str(build / "qemu" / f"host-{precision}" / scenario)],
                                 capture_output=True, text=True, timeout=60)
            assert run.returncode == 0, run.stdout[-2000:]
            hosts[scenario, precision] = parse(run.stdout)
    return build, hosts


def peak_relative(got: np.ndarray, want: np.ndarray) -> float:
    """The largest difference of each joint's command over the run's peak of that joint."""
    peak = np.maximum(np.abs(want).max(axis=0), 1e-300)
    return float((np.abs(got - want).max(axis=0) / peak).max())


@pytest.mark.slow
@pytest.mark.parametrize("precision", PRECISIONS)
@pytest.mark.parametrize("machine", list(MACHINES))
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_firmware_on_cortex_m_matches_the_host(firmware, scenario, machine, precision):
    build, hosts = firmware
    elf = build / "qemu" / f"{machine}-{precision}" / f"{scenario}.elf"
    status, text = run_qemu(machine, elf, elf.with_suffix(".out"))
    assert status == 0, f"QEMU exited {status}: {text[-500:]}"
    got, want = parse(text), hosts[scenario, precision]
    nq = got["tau"].shape[1]
    assert got["header"] == want["header"] == (scenario, precision, nq, PERIODS)
    assert got["end"] == want["end"] == (COMPLETED, PERIODS)
    assert got["rows"] == want["rows"] == list(range(PERIODS))
    assert np.all(np.isfinite(got["tau"])) and np.abs(want["tau"]).max() > 0
    difference = peak_relative(got["tau"], want["tau"])
    estimate = float(np.linalg.norm(got["p_hat"] - want["p_hat"])
                     / np.linalg.norm(want["p_hat"]))
    if precision == "double":
        assert difference <= DOUBLE_BOUND, difference
        assert estimate <= DOUBLE_BOUND, estimate
        np.testing.assert_array_equal(got["goal"], want["goal"])
    else:
        assert difference <= FLOAT_BOUND, difference
        assert estimate <= FLOAT_ESTIMATE_BOUND, estimate
        assert np.abs(got["goal"] - want["goal"]).max() <= 1  # one LSB of rounding at most
    # The goal currents move: the comparison is not of a run of zeros.
    assert len(np.unique(want["goal"])) > 3
    # The instruction count: the calibration and the periods counted (the host has no count).
    assert want["ticks"] == (0, 0, 0, 0)
    calibration, instructions, ticks, longest = got["ticks"]
    assert calibration > 0 and instructions == 2 << 20 and 0 < longest <= ticks


@pytest.mark.slow
def test_a_stopped_run_ends_qemu_with_its_status(tmp_path):
    """Inputs whose 11th measurement is past joint 1's position limit: the supervisor stops the
    loop there, on the Cortex-M4F as on the host, and the semihosting exit carries status 1 to
    QEMU's exit status (a firmware that always exits 0 would pass a comparison of rows)."""
    ensure_tools()
    text = (QEMU_DIR / "inputs_serial_task.h").read_text()
    head, rows = text.split("static const double input_q[INPUT_STEPS][INPUT_NQ] = {\n", 1)
    rows = rows.split("\n")
    first = rows[10].split(", ")
    first[0] = "    {0x1.0p+7"  # 128 rad: past any joint limit
    rows[10] = ", ".join(first)
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    (inputs / "inputs_serial_task.h").write_text(
        head + "static const double input_q[INPUT_STEPS][INPUT_NQ] = {\n" + "\n".join(rows))
    build = tmp_path / "build"
    elf = build / "qemu" / "an386-double" / "serial_task.elf"
    host = build / "qemu" / "host-double" / "serial_task"
    make_firmware(build, f"QEMU_INPUTS={inputs}", "QEMU_SCENARIOS=serial_task",
                  targets=(str(elf), str(host)))
    status, text = run_qemu("an386", elf, tmp_path / "out.txt")
    got = parse(text)
    # Periods 0..9 commanded; period 10 logged (its state) and stopped before any command.
    assert status == 1 and got["end"] == (POSITION_LIMIT, 11), (status, got.get("end"))
    assert got["rows"] == list(range(10))
    run = subprocess.run([str(host)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 1
    host_rows = parse(run.stdout)
    assert host_rows["end"] == got["end"] and host_rows["rows"] == got["rows"]
    np.testing.assert_array_equal(host_rows["goal"], got["goal"])
    assert peak_relative(got["tau"], host_rows["tau"]) <= DOUBLE_BOUND


def test_missing_tools_fail_with_one_line(tmp_path):
    """No tool on the PATH and installing not allowed: exit 3, one line naming every missing
    package and the command that installs it."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for tool in ("bash", "ls", "id"):
        (bin_dir / tool).symlink_to(shutil.which(tool))
    run = subprocess.run([str(bin_dir / "bash"), str(ENSURE)], capture_output=True, text=True,
                         env={"PATH": str(bin_dir), "COCHLEA_NO_INSTALL": "1"}, timeout=60)
    assert run.returncode == 3
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and run.stdout == ""
    assert "qemu-system-arm" in lines[0] and "gcc-arm-none-eabi" in lines[0]
    assert "apt-get install -y --no-install-recommends" in lines[0]


def test_ensure_tools_finds_the_installed_tools():
    """On this machine (after ensure_tools.sh has run once): nothing missing, nothing said."""
    ensure_tools()
    run = subprocess.run(["bash", str(ENSURE)], capture_output=True, text=True,
                         env={**os.environ, "COCHLEA_NO_INSTALL": "1"}, timeout=60)
    assert (run.returncode, run.stderr, run.stdout) == (0, "", "")
    for tool in ("qemu-system-arm", "arm-none-eabi-gcc"):
        assert shutil.which(tool), tool


@pytest.mark.parametrize("args, message", [
    (["no_such_scenario"], "unknown scenario"),
    (["serial_task", "--periods", "0"], "outside 1..5000"),
])
@pytest.mark.slow
def test_record_inputs_refuses_bad_input(tmp_path, args, message):
    out = tmp_path / "inputs.h"
    run = subprocess.run([sys.executable, str(QEMU_DIR / "record_inputs.py"), *args,
                          "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and message in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and "Traceback" not in run.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
@pytest.mark.parametrize("scenario", SCENARIOS)
def test_inputs_are_what_the_simulation_measures(tmp_path, scenario):
    """The committed canned measurements are record_inputs.py's of today's simulation (to
    1e-12: the replay is of what the controller would see)."""
    out = tmp_path / f"inputs_{scenario}.h"
    run = subprocess.run([sys.executable, str(QEMU_DIR / "record_inputs.py"), scenario,
                          "--periods", str(PERIODS), "--out", str(out)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr

    def values(text: str) -> np.ndarray:
        body = [ln for ln in text.splitlines() if ln.startswith("    {")]
        return np.array([[float.fromhex(v) for v in ln.strip(" {},").split(", ")]
                         for ln in body])

    fresh = values(out.read_text())
    committed = values((QEMU_DIR / f"inputs_{scenario}.h").read_text())
    assert fresh.shape == committed.shape == (2 * PERIODS, fresh.shape[1])
    np.testing.assert_allclose(committed, fresh, rtol=1e-12, atol=1e-12)
