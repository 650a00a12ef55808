"""Issue 28 item 1: the OpenCR board port (embedded/ports/opencr/, ``make opencr-firmware``),
the shared STM32 firmware on ROBOTIS's OpenCR (an STM32F746ZG, Cortex-M7 with a
double-precision FPU). See docs/embedded.md, "OpenCR (STM32F746) port".

No emulator models this chip (QEMU 7.2 has no STM32F7 machine; its mps2-an500 Cortex-M7 has
none of the F746's peripherals), so what is checked here, and how:

- the build: warning-free (``-Werror``) in float and double for ``-mcpu=cortex-m7
  -mfpu=fpv5-d16 -mfloat-abi=hard``, linked, with its size and static worst stack reported;
- the memory map an STM32F746 expects (RM0385 section 2.2.2): the vector table at the start
  of flash (0x08000000) with the initial stack pointer at the DTCM's top (0x20010000) and the
  port's handlers at their interrupt numbers; .data, .bss and the stack in the DTCM
  (0x20000000, 64 KB), the DMA's receive ring in SRAM1 (0x20010000); the image built for the
  double-precision FPU;
- the HAL's logic against a register model on the host (tests/opencr_model.c): the port's
  hal_opencr.c, the shared clock and, in the "firmware" cases, the whole shared firmware with
  the core and serial_joint, every register access going to the model. It checks the DMA ring
  read (bytes in order across the ring's end, a lap whose interrupt is still pending, a lapped
  ring counted as lost bytes, a read that ends at its timeout), that a write returns only
  after transmission complete (TC) and gives up at its deadline on a line that never
  completes, the power switch's pin, and in the firmware: the bus powered only after the
  configuration is accepted and the motors' boot time before the first byte, powered off
  after the safe stop's last byte (no motor answers in the model: the start fails and shuts
  down), never powered after a watchdog reset.

What only a board can show: the clock tree and the over-drive at 216 MHz, the DMA and USART
timing at 4 Mbaud, the transceiver's turnaround after TC, the power switch's FET, the
watchdog's reset, and the period on the real core."""

from __future__ import annotations

import json
import re
import struct
import subprocess
import time
from pathlib import Path

import pytest

from cochlea.dynamixel.drives import joint_drives
from tests.test_dynamixel_hil import emulator
from tests.test_embedded_qemu import ensure_tools
from tests.test_embedded_stm32 import EMULATOR_SETTLE_S, value

ROOT = Path(__file__).resolve().parent.parent
OPENCR, COMMON = ROOT / "embedded" / "ports" / "opencr", ROOT / "embedded" / "ports" / "common"
GEN = ROOT / "generated_c" / "embedded"
#: RM0385 section 2.2.2: flash, the DTCM, SRAM1 and SRAM2.
FLASH, DTCM, SRAM1, SRAM2 = 0x0800_0000, 0x2000_0000, 0x2001_0000, 0x2004_C000
FLASH_SIZE = 1024 * 1024
#: The vector table: 16 core entries and the STM32F746's 98 interrupts.
IRQS = 98
HANDLERS = {12: "DMA1_Stream1_IRQHandler", 38: "USART2_IRQHandler", 39: "USART3_IRQHandler"}
#: The model's Dynamixel bus timing: 4 Mbaud, TC 20 status reads after the last byte.
SETTLE_NS = 1_000_000_000


@pytest.fixture(scope="module")
def firmware(tmp_path_factory) -> tuple[Path, str]:
    """``make opencr-firmware`` into a temporary build folder: both precisions, its report."""
    ensure_tools()
    build = tmp_path_factory.mktemp("opencr-build")
    run = subprocess.run(["make", "--no-print-directory", "opencr-firmware", f"BUILD={build}"],
                         cwd=ROOT, capture_output=True, text=True, timeout=900)
    if run.returncode != 0:
        pytest.fail(f"make opencr-firmware failed:\n{run.stderr[-4000:]}", pytrace=False)
    assert "warning" not in (run.stderr + run.stdout).lower(), run.stderr[-4000:]
    return build / "opencr", run.stdout


def symbols(elf: Path) -> dict[str, int]:
    out = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True,
                         check=True).stdout
    return {m[2]: int(m[0], 16) for m in re.findall(r"^([0-9a-f]+) (\w) (\S+)$", out, re.M)}


@pytest.mark.slow  # its module fixture builds the firmware (make opencr-firmware, 4 s)
@pytest.mark.parametrize("precision", ["float", "double"])
def test_the_firmware_builds_and_reports_its_size_and_stack(firmware, precision):
    build, report = firmware
    elf = build / precision / "cochlea-opencr.elf"
    assert elf.is_file() and elf.with_suffix(".bin").is_file()
    size = re.search(rf"{re.escape(str(elf))}: text (\d+) B, data (\d+) B, bss (\d+) B, "
                     r"sram1 (\d+) B", report)
    stack = re.search(rf"{re.escape(str(elf))}: worst stack (\d+) B \(static bound: thread "
                      r"(\d+),", report)
    assert size and stack, report
    text, data, bss, sram1 = map(int, size.groups())
    assert 20_000 < text + data < FLASH_SIZE
    assert sram1 == 1024  # the DMA ring, and nothing else, in SRAM1
    # the DTCM holds .data, .bss and the stack's static bound, with room to spare
    assert data + bss + int(stack.group(1)) < 64 * 1024
    assert 500 < int(stack.group(2)) < int(stack.group(1))


def boot_table_is_quiet(words: tuple, names: dict, load: int, size: int) -> None:
    """The table the core starts on (at the image's load address): the stack's top, the
    reset handler, the faults', and a handler that silences every other exception (a
    bootloader's SysTick still running), so that no firmware handler runs before .bss is."""
    assert words[0] == DTCM + 64 * 1024 == names["_estack"]  # the initial stack pointer
    assert words[1] == names["Reset_Handler"] | 1 and load <= words[1] < load + size
    assert set(words[2:7]) == {names["Fault_Handler"] | 1}
    quiet = names["Boot_Quiet_Handler"] | 1
    assert [words[i] for i in (11, 12, 14, 15)] == [quiet] * 4
    assert set(words[16:]) == {quiet}


@pytest.mark.slow  # the same firmware build
@pytest.mark.parametrize("precision", ["float", "double"])
def test_the_image_is_laid_out_as_an_stm32f746_expects(firmware, precision):
    build, _ = firmware
    elf = build / precision / "cochlea-opencr.elf"
    names = symbols(elf)
    image = elf.with_suffix(".bin").read_bytes()
    assert names["boot_vectors"] == FLASH
    boot_table_is_quiet(struct.unpack_from(f"<{16 + IRQS}I", image), names, FLASH, FLASH_SIZE)
    # the firmware's own table, which Reset_Handler moves VTOR to: aligned as VTOR needs
    assert names["vectors"] % 512 == 0 and FLASH < names["vectors"] < FLASH + FLASH_SIZE
    words = struct.unpack_from(f"<{16 + IRQS}I", image, names["vectors"] - FLASH)
    assert words[0] == names["_estack"] and words[1] == names["Reset_Handler"] | 1
    assert words[15] == names["SysTick_Handler"] | 1
    for irq, handler in HANDLERS.items():
        assert words[16 + irq] == names[handler] | 1, handler
    others = {w for i, w in enumerate(words[16:]) if i not in HANDLERS}
    assert others == {names["Default_Handler"] | 1}
    # .data, .bss and the stack in the DTCM; the ring the DMA writes in SRAM1
    assert DTCM <= names["_sdata"] <= names["_ebss"] < DTCM + 64 * 1024
    assert SRAM1 <= names["rx_ring"] < SRAM2
    headers = subprocess.run(["arm-none-eabi-readelf", "-A", str(elf)], capture_output=True,
                             text=True, check=True).stdout
    assert "Tag_CPU_arch: v7E-M" in headers, headers
    # the M7's double-precision FPv5 (the M4F's is FPv4-SP: no double in hardware)
    assert "Tag_FP_arch: FPv5/FP-D16 for ARMv8" in headers, headers
    assert "Tag_ABI_VFP_args: VFP registers" in headers, headers


@pytest.mark.slow
def test_the_bootloader_build_links_where_opencrs_bootloader_jumps(tmp_path):
    """``OPENCR_LOAD=bootloader``: the image at 0x08040000, within the bootloader's 768 KB
    (ROBOTIS's FLASH_FW_ADDR_START and FLASH_FW_SIZE), starting on the quiet table: the
    bootloader jumps with VTOR on the image and its SysTick still interrupting."""
    ensure_tools()
    run = subprocess.run(["make", "--no-print-directory", "opencr-firmware", f"BUILD={tmp_path}",
                          "OPENCR_LOAD=bootloader"], cwd=ROOT, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stderr[-4000:]
    load, size = 0x0804_0000, 768 * 1024
    for precision in ("float", "double"):
        elf = tmp_path / "opencr-bootloader" / precision / "cochlea-opencr.elf"
        names = symbols(elf)
        image = elf.with_suffix(".bin").read_bytes()
        assert names["boot_vectors"] == load and len(image) < size
        boot_table_is_quiet(struct.unpack_from(f"<{16 + IRQS}I", image), names, load, size)
        assert names["vectors"] % 512 == 0 and load < names["vectors"] < load + len(image)
        # .data's image follows the code in the bootloader's region, not below it
        assert load < names["_sidata"] < load + size
    wrong = subprocess.run(["make", "--no-print-directory", "opencr-firmware", f"BUILD={tmp_path}",
                            "OPENCR_LOAD=usb"], cwd=ROOT, capture_output=True, text=True,
                           timeout=60)
    assert wrong.returncode == 2 and "OPENCR_LOAD=usb is not swd or bootloader" in wrong.stderr


def test_an_unknown_scenario_is_one_line_from_make(tmp_path):
    run = subprocess.run(["make", "--no-print-directory", "opencr-firmware", f"BUILD={tmp_path}",
                          "OPENCR_SCENARIO=no_such_scenario"], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 2
    errors = [line for line in run.stderr.splitlines() if line.strip()]
    assert len(errors) == 1 and "unknown scenario" in errors[0], run.stderr
    assert not (tmp_path / "opencr").exists()


def build_model(out: Path, *defines: str, scenario: str = "serial_joint") -> Path:
    """tests/opencr_model.c with the port's HAL, the shared firmware, the core and the
    scenario, for the host (BOARD_HOST_MODEL); defines: the firmware's settings."""
    flags = ["-std=c99", "-O1", "-Wall", "-Wextra", "-Werror", "-DBOARD_HOST_MODEL",
             f"-I{ROOT / 'embedded' / 'core'}", f"-I{GEN}", f"-I{OPENCR}", f"-I{COMMON}",
             f"-DSTM32_SCENARIO={scenario}", *defines]
    firmware_object = out / "firmware.o"
    for command in (
            ["cc", *flags, "-Dmain=opencr_firmware_main", "-c", str(COMMON / "firmware.c"),
             "-o", str(firmware_object)],
            ["cc", *flags, str(ROOT / "tests" / "opencr_model.c"), str(firmware_object),
             str(OPENCR / "hal_opencr.c"), str(COMMON / "stm32_timebase.c"),
             str(COMMON / "stream.c"), *map(str, sorted((ROOT / "embedded" / "core").glob("*.c"))),
             str(GEN / f"{scenario}.c"), str(GEN / f"{scenario}_scenario.c"),
             "-o", str(out / "model"), "-lm"]):
        run = subprocess.run(command, capture_output=True, text=True, timeout=300)
        if run.returncode != 0:
            pytest.fail(f"the register model does not build:\n{run.stderr[-4000:]}",
                        pytrace=False)
    return out / "model"


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> Path:
    return build_model(tmp_path_factory.mktemp("opencr-model"))


def run_model(model: Path, case: str, *options: str
              ) -> tuple[list[tuple[int, str, int]], dict[str, str], str, str]:
    """The model's events (time, what, value), its "key value" lines, the firmware's console
    and the whole output."""
    run = subprocess.run([str(model), case, *options], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    events = [(int(t), what, int(v)) for t, what, v in
              re.findall(r"^event (\d+) (\w+) (-?\d+)$", run.stdout, re.M)]
    values = dict(re.findall(r"^(\w+) (-?\d+)$", run.stdout, re.M))
    console = run.stdout.split("console_begin\n", 1)[1].split("console_end", 1)[0] \
        if "console_begin" in run.stdout else ""
    return events, values, console, run.stdout


def test_the_bus_is_usart3_at_4_mbaud_with_dma1_stream1_channel4_circular(model):
    _, values, _, _ = run_model(model, "ring")
    assert int(values["brr"]) == 0x15  # OVER8: USARTDIV 27 of 2 x 54 MHz = 4.000 Mbaud
    scr = int(values["dma_scr"])
    assert scr >> 25 & 7 == 4 and scr & 1  # channel 4 (USART3_RX), enabled
    assert scr & (1 << 8) and scr & (1 << 10) and scr & (1 << 4)  # circular, MINC, TCIE
    assert (scr >> 6) & 3 == 0  # peripheral to memory
    assert int(values["dma_par"]) == 0x4000_4824  # USART3_RDR
    assert int(values["cr3"]) & (1 << 6)  # DMAR


def test_the_dma_ring_read_keeps_order_across_the_rings_end(model):
    _, values, _, _ = run_model(model, "ring")
    assert values["first"] == "1000" and values["second"] == "100"  # no mismatch line
    assert "mismatch" not in values
    assert values["laps"] == "1" and values["overflows"] == "0"


def test_a_lap_whose_interrupt_is_still_pending_loses_nothing(model):
    """NDTR reloaded, its transfer-complete interrupt not yet taken: the position looks
    behind the last one; the read counts the lap itself (no bytes lost, none repeated)."""
    _, values, _, _ = run_model(model, "pending")
    assert (values["first"], values["second"], values["third"]) == ("1000", "100", "10")
    assert values["overflows"] == "0"


def test_a_lapped_ring_counts_the_lost_bytes_and_reads_the_newest(model):
    _, values, _, _ = run_model(model, "overflow")
    assert values["got"] == "1024" and values["overflows"] == "50"


def test_a_read_with_nothing_on_the_line_ends_at_its_timeout(model):
    _, values, _, _ = run_model(model, "timeout")
    assert values["got"] == "0"
    assert 2_000_000 <= int(values["waited_ns"]) < 2_100_000


def test_a_write_returns_after_transmission_complete_then_the_pin_turns(model):
    events, values, _, _ = run_model(model, "write")
    assert values["wrote"] == "6"
    kinds = [(what, v) for _, what, v in events if what in ("bus", "tc", "direction")]
    assert kinds[-8:] == [("bus", 0xFF), ("bus", 0xFF), ("bus", 0xFD), ("bus", 0x00),
                          ("bus", 0xFE), ("bus", 0x03), ("tc", 1), ("direction", 0)]
    assert kinds.index(("direction", 1)) < kinds.index(("bus", 0xFF))


def test_a_write_on_a_line_that_never_completes_gives_up_at_its_deadline(model):
    events, values, _, _ = run_model(model, "write", "--tc-stuck")
    assert values["wrote"] == "-1"
    # 1 ms and twice the 6 bytes' wire time (30 us at 4 Mbaud), then one poll
    assert 1_030_000 <= int(values["write_ns"]) < 1_100_000
    assert ("tc", 1) not in [(what, v) for _, what, v in events]


def test_the_power_switch_is_pf15_high_on(model):
    events, values, _, _ = run_model(model, "power")
    assert [(what, v) for _, what, v in events if what == "power"] == [("power", 1),
                                                                      ("power", 0)]
    assert (int(values["moder_f"]) >> 30) & 3 == 1  # PF15 an output
    assert values["power_pin"] == "0"


def test_the_firmware_powers_the_bus_for_the_start_and_off_after_the_safe_stop(model):
    """No motor answers in the model: the start fails at the PINGs and shuts down (zero
    current, torque off to every motor); the power goes on only after the configuration is
    accepted, the first byte waits for the motors' boot time, and the power goes off after
    the safe stop's last byte has left (TC), before the end line."""
    events, values, console, _ = run_model(model, "firmware")
    lines = [line for line in console.replace("\r", "").splitlines() if line]
    assert lines[0].startswith("cochlea-opencr scenario=serial_joint "), lines
    assert lines[1].startswith("start failed error=1 step=1"), lines
    assert lines[-1].startswith("end rule=none exit=5 "), lines
    power = [(t, v) for t, what, v in events if what == "power"]
    bus = [t for t, what, _ in events if what == "bus"]
    tc = [t for t, what, _ in events if what == "tc"]
    assert [v for _, v in power] == [0, 1, 0], power  # off at reset, on for the start, off
    on, off = power[1][0], power[2][0]
    assert bus and on + SETTLE_NS <= bus[0]
    assert off >= bus[-1] and off >= tc[-1]
    assert int(values["bus_bytes"]) == len(bus) > 10 * 6  # at least a 10-byte PING a motor
    assert values["power_pin"] == "0"


def test_after_a_watchdog_reset_the_bus_is_never_powered(model):
    events, values, console, _ = run_model(model, "firmware", "--watchdog-reset")
    assert "refused what=watchdog-reset" in console
    assert [v for _, what, v in events if what == "power"] == [0, 0]
    assert values["bus_bytes"] == "0" and values["power_pin"] == "0"


def homing_header(folder: Path, scenario: str, **entry_changes) -> Path:
    """A homing record of the parallel robot's slider as cochlea-dxl home writes it, and the
    header cochlea.dynamixel.homing_firmware makes of it for ``scenario`` (its folder)."""
    from cochlea.dynamixel.homing_firmware import main as homing_firmware

    (slider,) = [d for d in joint_drives("parallel") if d.type == "prismatic"]
    entry = {"joint": slider.name, "motor_id": slider.id, "model": slider.spec.name,
             "raw_counts": 1234, "stop_m": 0.0125, "direction": slider.direction,
             "ratio_m_per_rad": slider.ratio, "marker_address": 88, "marker": 4321,
             **entry_changes}
    record = folder / "parallel.json"
    record.write_text(json.dumps({"format": "cochlea-homing/2", "robot": "parallel",
                                  "description": "shipped", "date": "2026-11-26T13:40:00",
                                  "port": "/dev/ttyACM0", "joints": [entry]}))
    out = folder / "homing" / "homing_record.h"
    assert homing_firmware(["--scenario", scenario, "--record", str(record), "--out",
                            str(out)]) == 0
    return out.parent


@pytest.mark.slow
def test_a_slider_without_its_homing_record_never_powers_the_bus(tmp_path):
    """The parallel robot's slider counts its turns only from a homing record: a firmware
    built without one refuses before the bus is powered, saying how to build it."""
    binary = build_model(tmp_path, scenario="parallel_joint")
    events, values, console, _ = run_model(binary, "firmware")
    assert "refused what=homing: a prismatic joint needs its homing record" in console
    assert "STM32_HOMING_RECORD=FILE" in console
    assert [v for _, what, v in events if what == "power"] == [0, 0]
    assert values["bus_bytes"] == "0"


@pytest.mark.slow
def test_a_slider_with_its_homing_record_compiled_in_starts_the_bus(tmp_path):
    """With the record compiled in (its offset and token from the record, checked against the
    scenario's drives at build time), the firmware passes the gate and starts the bus: here
    no motor answers, so the start fails at the PINGs and shuts down. The console's first line
    names the record's date."""
    folder = homing_header(tmp_path, "parallel_joint")
    header = (folder / "homing_record.h").read_text()
    (slider,) = [j for j, d in enumerate(joint_drives("parallel")) if d.type == "prismatic"]
    assert f"#define STM32_HOMING_DRIVE {slider} " in header
    assert "#define STM32_HOMING_MARKER 4321u" in header
    binary = build_model(tmp_path, "-DSTM32_HOMED=1", f"-I{folder}",
                         scenario="parallel_joint")
    events, values, console, _ = run_model(binary, "firmware")
    lines = [line for line in console.replace("\r", "").splitlines() if line]
    assert lines[0].startswith("cochlea-opencr scenario=parallel_joint ") and \
        lines[0].endswith(" homed=2026-11-26T13:40:00"), lines
    assert lines[1].startswith("start failed error=1 step=1"), lines
    assert [v for _, what, v in events if what == "power"] == [0, 1, 0]


def test_a_homing_record_that_does_not_fit_is_refused_when_the_firmware_is_built(tmp_path):
    """Another motor ID than the description's slider, a token the C bridge's 16 bits would
    truncate, an offset that is not finite, or the serial robot (no prismatic joint): one
    line from the header's generator, no header."""
    from cochlea.dynamixel.homing_firmware import main as homing_firmware

    for change in ({"motor_id": 17}, {"marker": 70000}, {"raw_counts": 10**320}):
        with pytest.raises(AssertionError):  # one line, exit 2
            homing_header(tmp_path, "parallel_joint", **change)
        assert not (tmp_path / "homing" / "homing_record.h").exists()
    record = tmp_path / "parallel.json"
    assert homing_firmware(["--scenario", "serial_joint", "--record", str(record), "--out",
                            str(tmp_path / "h.h")]) == 2
    assert not (tmp_path / "h.h").exists()


#: The emulator run's build: 300 periods, and the tolerances the model's pace on a shared
#: machine needs (as tests/test_embedded_stm32.py's QEMU build); 100 ms of boot time.
EMULATOR_BUILD = ("-DSTM32_DURATION_S=0.3", "-DSTM32_WATCHDOG_MISSES=100000",
                  "-DSTM32_WATCHDOG_ERRORS=100000", "-DSTM32_READ_TIMEOUT_NS=100000000",
                  "-DSTM32_BUS_WATCHDOG_MS=2540", "-DOPENCR_POWER_SETTLE_MS=100u")
GOAL_CURRENT, TORQUE_ENABLE = 102, 64


@pytest.mark.hil
def test_a_run_against_the_emulator_ends_in_torque_off_then_the_power_off(tmp_path):
    """The whole firmware with the OpenCR HAL on the register model, its USART3 and DMA ring
    on cochlea-emulator's pseudo-terminal, in real time: the start-up, 300 periods, the safe
    stop confirmed by every motor, and only then the power switch off, with every byte of
    the run already sent and received. The emulated motors get no torque (as in the STM32F4
    port's QEMU test: the model's periods are not a board's)."""
    binary = build_model(tmp_path, *EMULATOR_BUILD)
    ids = [d.id for d in joint_drives("serial")]
    still = [a for i in ids for a in ("--true-fit", f"{i}:1e-6,0")]
    log = tmp_path / "emulator.log"
    with emulator("serial", "serial_joint", log, *still) as port:
        time.sleep(EMULATOR_SETTLE_S)
        _, values, console, out = run_model(binary, "emulator", port)
    lines = [line for line in console.replace("\r", "").splitlines() if line]
    assert lines[1] == "start ok", lines
    end = dict(re.findall(r"(\w+)=(\S+)", lines[-1]))
    n = len(ids)
    assert end["rule"] == "completed" and end["exit"] == "0", lines[-1]
    assert end["rows"] == "300" and end["reads"] == "300"
    assert int(end["good_reads"]) >= 270 and end["rx_overflows"] == "0", lines[-1]
    assert end["confirmed_off"] == f"{n}/{n}"
    # the DMA lapped its ring many times over the run, and lost nothing
    received = int(values["rx_bytes"])
    assert int(values["laps"]) == received // 1024 > 10
    # power: off at reset, on for the start, off after the last byte either way
    power = re.findall(r"^power_at (\d) (\d+) (\d+)$", out, re.M)
    assert power == [("0", "0", "0"), ("1", "0", "0"),
                     ("0", values["bus_bytes"], values["rx_bytes"])], power
    # the safe stop in the emulator's log: zero current, torque off to every motor, twice,
    # then each motor read back
    logged = [line.split() for line in log.read_text().splitlines()]
    writes = [(int(value(e, "address")), int(value(e, "value"))) for e in logged
              if e[1] == "sync-write"]
    assert writes[-4 * n:] == ([(GOAL_CURRENT, 0)] * n + [(TORQUE_ENABLE, 0)] * n) * 2
    last_stop = max(k for k, e in enumerate(logged) if e[1] == "sync-write")
    assert [int(value(e, "id")) for e in logged[last_stop:]
            if e[1] == "read" and value(e, "address") == str(TORQUE_ENABLE)] == ids


def _start_errors() -> list[str]:
    """enum cochlea_start_error's names in order (embedded/core/bridge.h)."""
    text = (ROOT / "embedded" / "core" / "bridge.h").read_text()
    body = text.split("enum cochlea_start_error {", 1)[1].split("};", 1)[0]
    return re.findall(r"^\s*(COCHLEA_START_\w+)", body, re.M)


@pytest.mark.hil
def test_the_slider_homed_on_the_emulator_starts_and_refuses_once_rebooted(tmp_path,
                                                                          monkeypatch):
    """The whole firmware on the register model, on the emulator, for the parallel robot:
    cochlea-dxl home finds the slider's stop (its motor mounted 500 deg of screw away from
    the description's zero) and writes the record and the token; the firmware built with that
    record counts the slider from the stop and starts (500 deg off, its first read would be
    out of the slider's limits); after a REBOOT of the slider's motor (the token back to 0, as
    at power-on) the same firmware refuses at the homing step, nothing moved."""
    from cochlea.dynamixel import homing, protocol
    from cochlea.dynamixel.bringup import home
    from cochlea.dynamixel.bringup.common import Bus
    from cochlea.dynamixel.emulator import Truth, VirtualChain
    from cochlea.dynamixel.homing_firmware import main as homing_firmware
    from cochlea.sim import load_scenario, unit_setups
    from tests.test_homing_records import FAST as HOME_FAST
    from tests.test_homing_records import STOP_M, parse

    monkeypatch.setenv("HOME", str(tmp_path))
    drives = joint_drives("parallel")
    (slider,) = [d for d in drives if d.type == "prismatic"]
    setup = unit_setups(load_scenario("parallel_joint"))[0]
    pose = {j.name: q for j, q in zip(setup.controller_model.joints, setup.plant_x0)}
    start = {d.name: pose[d.name] for d in drives}
    chain = VirtualChain("parallel", "parallel_joint",
                         truth=Truth(offset_deg={slider.id: 500.0}, hard_stop_m=STOP_M)).start()
    try:
        assert home.run(parse("--robot", "parallel", "--port", chain.path, "--stop-m",
                              str(STOP_M), *HOME_FAST)) == 0
        record = homing.default_record("parallel")
        folder = tmp_path / "homing"
        assert homing_firmware(["--scenario", "parallel_joint", "--record", str(record),
                                "--out", str(folder / "homing_record.h")]) == 0
        binary = build_model(tmp_path, *EMULATOR_BUILD, "-DSTM32_HOMED=1", f"-I{folder}",
                             scenario="parallel_joint")
        consoles = []
        for reboot in (False, True):
            if reboot:
                with Bus(chain.path, 4_000_000) as bus:
                    assert bus.request(protocol.reboot(slider.id), slider.id).error == 0
            for name, q in start.items():
                chain.move_joint(name, q)  # the scenario's initial pose, by hand
            time.sleep(EMULATOR_SETTLE_S)
            _, _, console, _ = run_model(binary, "emulator", chain.path)
            consoles.append([line for line in console.replace("\r", "").splitlines() if line])
    finally:
        chain.close()
    homed, rebooted = consoles
    date = json.loads(record.read_text())["date"]
    assert homed[0].split(" homed=")[1] == re.sub(r"[^0-9A-Za-z:.+_-]", "_", date)[:40], homed
    assert homed[1] == "start ok", homed
    failed = dict(re.findall(r"(\w+)=(\S+)", rebooted[1]))
    assert rebooted[1].startswith("start failed"), rebooted
    assert int(failed["error"]) == _start_errors().index("COCHLEA_START_NOT_HOMED")
    assert failed["step"] == "12" and failed["detail"] == "0"  # the token a reboot leaves
