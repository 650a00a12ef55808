"""What the bring-up subcommands share: options, the description's motors, the serial port at a
baud rate with unicast transactions (retries, failures that name the motor and what to check),
and the registers the runtime relies on (:func:`runtime_settings`), which ``info`` compares
and ``configure`` writes.

Exit codes of ``cochlea-dxl`` (the dispatcher maps exceptions to them):

* 0 done, everything as expected;
* 1 the check found a difference (``info``: a register differs; ``configure``: a write did
  not take; ``reboot``: a motor still in alert or not back; ``scan``: no motor answered);
* 2 the user's input is wrong (an option, the description, an output path that cannot be
  written: a missing folder, a folder that is a file, a read-only folder, an existing path that
  is not a regular file); nothing was written and nothing moved;
* 5 the port does not open, or a motor of the description is missing, of another model or
  does not answer (as ``cochlea-run``'s "the backend could not start");
* 6 a motor went into hardware alert while the command moved or configured the motors: the move
  was stopped (goal current 0, torque off on every motor that answers), nothing reported as
  done, nothing written; the message names the motor(s), the error bits and the ``reboot`` of
  those motors only (:class:`HardwareAlert`);
* 7 a motor stopped answering, or answered with a garbled (CRC) or stale packet (another ID's,
  a wrong length, a Realtime Tick that did not move), while the command moved or configured
  the motors: stopped the same way (:class:`MotorLost`);
* 128 + the signal's number (129 SIGHUP, 130 SIGINT, 143 SIGTERM): interrupted; a move was
  stopped the same way, nothing written (:mod:`cochlea.apps.cochlea_dxl`).
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import stat
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ... import files
from ...console import signals_held
from ...errors import CochleaError
from ...robots import ROBOTS
from ...runtime.backend import BackendError
from ...runtime.supervisor import EXIT_BACKEND
from ...text import strict_int
from .. import protocol as proto
from ..control_table import (
    ALERT_BIT,
    BAUD_RATES,
    BROADCAST_ID,
    CURRENT_MODE,
    DATA_RANGE,
    MAX_ID,
    MODELS,
    MX64,
    OPERATING_MODES,
    Item,
    ModelSpec,
    baud_code,
    describe_error,
    describe_hardware_error,
)
from ..drives import JointDrive, joint_drives
from ..port import SerialPort, is_socket_address, open_port

EXIT_OK = 0
#: A check found a difference (see the module docstring).
EXIT_DIFFERS = 1
#: The port or the motors (cochlea-run's code for a backend that could not start).
EXIT_BUS = EXIT_BACKEND
#: A motor went into hardware alert during a move or a configuration (see the docstring).
EXIT_ALERT = 6
#: A motor stopped answering, or answered garbled or stale packets, during a move.
EXIT_LOST = 7

#: The runtime's default rate (cochlea-run --baud), what info and configure talk at by default.
DEFAULT_BAUD = 4_000_000
#: One READ of Realtime Tick (ms, modulo 32768), Moving, Moving Status, Present PWM, Present
#: Current, Present Velocity, Present Position: 120..135 on the MX(2.0) and X series, 568..583
#: on the P series (each model's address: :func:`present_address`).
PRESENT = struct.Struct("<H4xhii")
TICK_MODULO_MS = 32768
#: A motor whose Realtime Tick did not move over more than this (s) answered a stale packet.
STALE_AFTER_S = 0.003
#: How long one unicast request waits for its status packet: a USB adapter holds received
#: bytes up to its latency timer (16 ms by default), so less would miss motors that answered.
REPLY_TIMEOUT_S = 0.05
RETRIES = 3
#: Broadcast PING: motors answer in turn, each up to about 3 ms per ID later (the ROBOTIS SDK
#: waits this long too), plus the adapter's latency timer.
PING_SLOT_S = 3e-3
ADAPTER_LATENCY_S = 0.016

MODE_NAMES = {0: "current", 1: "velocity", 3: "position", 4: "extended position",
              5: "current-based position", 16: "PWM"}
assert set(MODE_NAMES) == set(OPERATING_MODES)


class BusError(CochleaError):
    """The port, or a motor on it, did not do what was asked (exit code 5)."""

    exit_code = EXIT_BUS


class MotionStopped(BusError):
    """A motor went wrong while the command moved or configured the motors (:func:`motion`
    stopped them); ``motor_id`` is the motor whose packet showed it."""

    def __init__(self, message: str, motor_id: int | None = None):
        super().__init__(message)
        self.motor_id = motor_id


class HardwareAlert(MotionStopped):
    """A status packet carried the hardware alert bit during a move (exit code 6)."""

    exit_code = EXIT_ALERT


class MotorLost(MotionStopped):
    """A motor stopped answering, or answered a garbled or stale packet, during a move (exit
    code 7)."""

    exit_code = EXIT_LOST


# ---- options -----------------------------------------------------------------------------------


def baud_rate(text: str) -> int:
    """argparse type: a Dynamixel baud rate."""
    try:
        value = strict_int(text)
        baud_code(value)
    except (ValueError, CochleaError):
        raise argparse.ArgumentTypeError(
            f"expected a Dynamixel baud rate ({', '.join(str(b) for b in BAUD_RATES.values())}),"
            f" got {text!r}") from None
    return value


def id_list(text: str) -> list[int]:
    """argparse type: motor IDs like ``1,2,5-7``, each 0..252, at least one."""
    ids: set[int] = set()
    try:
        for part in text.split(","):
            part = part.strip()
            if not part:
                continue
            first, sep, last = part.partition("-")
            lo, hi = int(first), int(last) if sep else int(first)
            if not 0 <= lo <= hi <= MAX_ID:
                raise ValueError
            ids.update(range(lo, hi + 1))
    except ValueError:
        ids = set()
    if not ids:
        raise argparse.ArgumentTypeError(f"expected motor IDs 0..{MAX_ID} like 1,2,5-7, got "
                                         f"{text!r}")
    return sorted(ids)


def add_port(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--port", required=True, metavar="PATH",
                        help="the serial port, e.g. /dev/ttyUSB0, or the pseudo-terminal "
                             "cochlea-emulator prints")


def add_baud(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--baud", type=baud_rate, default=DEFAULT_BAUD, metavar="B",
                        help=f"the motors' present baud rate (default {DEFAULT_BAUD}, the "
                             "runtime's; a new motor is at 57600)")


def add_robot(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--robot", required=True, choices=list(ROBOTS))
    parser.add_argument("--description", type=Path, metavar="FILE",
                        help="the robot description (default: the shipped one for ROBOT)")


def load_drives(args: argparse.Namespace) -> list[JointDrive]:
    """The description's motors; a bad description is the user's mistake (exit 2)."""
    if args.description is not None and not args.description.is_file():
        raise CochleaError(f"--description {args.description}: no such file; expected a robot "
                           "description (TOML)")
    try:
        return joint_drives(args.robot, args.description)
    except BackendError as exc:  # joint_drives reports a bad description as a BackendError
        raise CochleaError(str(exc)) from None


def check_output(path: Path, option: str, *, new: bool = False,
                 then: str = "; nothing moved") -> Path:
    """Refuse, before anything moves (exit 2), an output path the command could not write in
    the end: its folder missing, not a folder or not writable (tried: a temporary file is
    created there and removed), or the path itself existing as anything but a regular file (a
    folder, a FIFO, a device, a socket, a symbolic link), which is never replaced. ``new``:
    an existing file is refused too (the command never overwrites it). The file is then
    written atomically beside it (:func:`cochlea.files.atomic_path`)."""
    path = Path(path)
    p = files.file_problem(path, replace=not new, links=False)
    if p is None:
        return path
    folder = path.parent
    kind = "a FIFO" if p.code == "not_regular" and stat.S_ISFIFO(p.mode or 0) else p.kind
    raise CochleaError({
        "unusable": f"{option} {path}: cannot look at it ({p.reason}); expected a file in a "
                    f"writable folder{then}",
        "symlink": f"{option} {path}: exists and is a symbolic link; expected a regular file "
                   f"(never replaced){then}",
        "not_regular": f"{option} {path}: exists and is {kind}; expected a regular file "
                       f"(never replaced){then}",
        "exists": f"{option} {path}: already exists; expected a new file (cochlea-dxl never "
                  "overwrites one)",
        "under_file": f"{option} {path}: its folder {folder} does not exist; expected an "
                      f"existing folder{then}",
        "folder_missing": f"{option} {path}: its folder {folder} does not exist; expected an "
                          f"existing folder{then}",
        "folder_not_folder": f"{option} {path}: {folder} is not a folder; expected a file in "
                             f"a folder{then}",
        "folder_not_writable": f"{option} {path}: cannot write in its folder {folder} "
                               f"({p.reason}); expected a writable folder{then}",
    }[p.code])


def present_address(spec: ModelSpec) -> int:
    """Where ``spec``'s block of :data:`PRESENT` starts (its Realtime Tick: 120 on the X series,
    568 on the P series); a model whose block is laid out otherwise is refused in one line."""
    offsets = {"Realtime Tick": (0, 2), "Present Current": (6, 2), "Present Velocity": (8, 4),
               "Present Position": (12, 4)}
    try:
        start = spec.item("Realtime Tick").address
        found = {n: (spec.item(n).address - start, spec.item(n).size) for n in offsets}
    except KeyError as exc:
        raise BusError(f"the {spec.name} has no {exc.args[0]} item: cochlea-dxl cannot read "
                       "its present state") from None
    if found != offsets:
        raise BusError(f"the {spec.name}'s Realtime Tick .. Present Position are not laid out "
                       f"as the X series' (offset, bytes: {found}): cochlea-dxl cannot read them")
    return start


def who(motor_id: int, drive: JointDrive | None = None) -> str:
    return f"ID {motor_id}" + (f" ({drive.name}, {drive.spec.name})" if drive else "")


def value_text(item: Item, value: int, spec: ModelSpec = MX64) -> str:
    """A register's value with its unit, e.g. ``250 (500 us)``: by the item's name, in the
    units of ``spec``'s data (a P-series motor's mA and pulses per turn)."""
    a = item.name
    if a == "Baud Rate":
        return f"{value} ({BAUD_RATES[value]} baud)" if value in BAUD_RATES else str(value)
    if a == "Return Delay Time":
        return f"{value} ({value * 2} us)"
    if a == "Drive Mode":
        return f"{value} ({'reverse' if value & 1 else 'normal'} direction)"
    if a == "Operating Mode":
        return f"{value} ({MODE_NAMES.get(value, 'unknown')})"
    if a in ("Current Limit", "Goal Current", "Present Current"):
        if spec.current_unit_mA is None:
            return str(value)
        return f"{value} ({value * spec.current_unit_mA:.0f} mA)"
    if a in ("Homing Offset", "Max Position Limit", "Min Position Limit", "Goal Position",
             "Present Position"):
        if spec.counts_per_rev is None:
            return str(value)
        return f"{value} ({value * 360 / spec.counts_per_rev:.1f} deg)"
    if a == "Torque Enable":
        return f"{value} ({'on' if value else 'off'})"
    if a == "Hardware Error Status":
        return f"{value} ({describe_hardware_error(value)})"
    if a == "Bus Watchdog":
        state = "tripped" if value < 0 else "off" if value == 0 else f"{value * 20} ms"
        return f"{value} ({state})"
    return str(value)


# ---- the registers the runtime relies on ---------------------------------------------------------


@dataclass(frozen=True)
class Setting:
    """A register as the runtime needs it. ``accept`` is what ``info`` also takes as fine
    (None: only ``value``)."""

    item: Item
    value: int
    why: str
    accept: object = None  # callable(int) -> bool, or None

    def acceptable(self, present: int) -> bool:
        return present == self.value or (self.accept is not None and self.accept(present))


def runtime_settings(drive: JointDrive) -> list[Setting]:
    """What ``configure`` writes, in this order, and ``info`` expects (torque off first and
    the baud rate last are the subcommands' own steps).

    Homing Offset and Drive Mode are not among them: they shift and reverse Present Position,
    and the description's ``zero_offset_deg`` and ``direction`` hold only with the values they
    were calibrated with, whatever those are."""
    spec = drive.spec
    return [
        Setting(spec.item("Bus Watchdog"), 0, "off at rest: the runtime sets its own at start "
                "(0 also clears a tripped one)", accept=lambda v: v >= 0),
        Setting(spec.item("Status Return Level"), 2, "every instruction answered: the runtime "
                "confirms each write"),
        Setting(spec.item("Operating Mode"), CURRENT_MODE, "the runtime commands currents"),
        Setting(spec.item("Return Delay Time"), 0, "reply at once: the default 500 us per "
                "motor does not fit a 1 kHz period"),
        Setting(spec.item("Current Limit"), int(drive.current_limit_lsb),
                "from the description's torque (force) limit through the fit"),
    ]


# ---- the bus -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Reply:
    error: int  # the status packet's error byte (bit 7: hardware alert)
    params: bytes


class Bus:
    """The serial port at one baud rate; unicast requests wait for their status packet."""

    def __init__(self, path: str, baud: int, *, timeout_s: float = REPLY_TIMEOUT_S,
                 retries: int = RETRIES):
        self.path, self.baud = str(path), int(baud)
        self.timeout_s, self.retries = timeout_s, retries
        self.names: dict[int, JointDrive] = {}  # for messages: the description's joints
        #: While :func:`motion` moves or configures motors: what it does (for messages); every
        #: status packet is then checked (alert bit, ID, CRC, length; see :meth:`request`).
        self.watching: str | None = None
        self._ticks: dict[int, tuple[int, float]] = {}  # id -> last Realtime Tick, when read
        self._parser = proto.PacketParser(status=True)
        self._port: SerialPort | None = None
        self.open(baud)

    def open(self, baud: int) -> None:
        self.close()
        try:
            # A serial device, or the emulator's socket (cochlea-emulator --listen), as the
            # bridge opens them: bring-up against a loaded machine's virtual chain too.
            self._port = open_port(self.path, baud)
        except BackendError as exc:
            expected = "the emulator's socket (is cochlea-emulator --listen running there?)" \
                if is_socket_address(self.path) else \
                "a serial port (check the path, the adapter's cable and who else has it open)"
            raise BusError(f"--port {self.path}: {exc}; expected {expected}") from None
        self.baud = int(baud)

    def close(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            port.close()

    def __enter__(self) -> Bus:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def who(self, motor_id: int) -> str:
        return who(motor_id, self.names.get(motor_id))

    # ---- transactions --------------------------------------------------------------------------

    def _send(self, frame: bytes) -> None:
        port = self._port
        port.discard_input()
        self._parser.reset()
        if not port.write(memoryview(frame), len(frame), time.perf_counter() + self.timeout_s):
            raise BusError(f"the serial port {self.path} failed while writing: check the adapter")

    def _packets(self, deadline: float):
        """The good status packets that arrive before ``deadline``, as ``(id, error, params)``;
        a corrupted one as ``(None, 0, b"")``."""
        port, parser = self._port, self._parser
        while True:
            code = parser.parse()
            if code == proto.OK:
                yield parser.id, parser.error, parser.params()
                continue
            if code == proto.CRC_FAILURE:
                yield None, 0, b""
                continue
            if code != proto.NEED_MORE:
                continue
            got = port.read_into(parser.space(), deadline)
            if got < 0:
                raise BusError(f"the serial port {self.path} failed while reading: check the "
                               "adapter")
            if got == 0:
                return
            parser.commit(got)

    def request(self, frame: bytes, motor_id: int, tries: int | None = None) -> Reply | None:
        """Send a unicast instruction until its status packet comes (``tries`` times); None
        if it never did."""
        watched = self.watching is not None
        for _ in range(tries or self.retries):
            self._send(frame)
            for packet_id, error, params in self._packets(time.perf_counter() + self.timeout_s):
                if packet_id == motor_id:
                    if watched and error & ALERT_BIT:
                        raise HardwareAlert(f"{self.who(motor_id)} answered with the hardware "
                                            "alert bit", motor_id)
                    return Reply(error, params)
                if watched:  # during a move, no packet but the motor's own answer will do
                    raise MotorLost(f"{self.who(motor_id)} was answered by "
                                    + ("a garbled packet (CRC)" if packet_id is None else
                                       f"a stale packet of ID {packet_id}"), motor_id)
        if watched:
            raise MotorLost(f"{self.who(motor_id)} stopped answering "
                            f"({tries or self.retries} tries)", motor_id)
        return None

    def send(self, frame: bytes) -> None:
        """An instruction no status packet answers (a broadcast, a motor at a lower Status
        Return Level)."""
        self._send(frame)

    def _expect(self, reply: Reply | None, motor_id: int, what: str) -> Reply:
        if reply is None:
            raise BusError(f"{self.who(motor_id)} did not answer {what} on {self.path} at "
                           f"{self.baud} baud ({self.retries} tries): check its power, cable, ID "
                           "and baud rate (cochlea-dxl scan finds them)")
        if reply.error & 0x7F:
            raise BusError(f"{self.who(motor_id)} refused {what}: "
                           f"{describe_error(reply.error & 0x7F)}")
        return reply

    def ping(self, motor_id: int, tries: int | None = None) -> tuple[int, int] | None:
        """``(model number, firmware)`` of the motor, or None if it did not answer."""
        reply = self.request(proto.ping(motor_id), motor_id, tries)
        if reply is None or len(reply.params) < 3:
            return None
        return proto.from_le(reply.params[0:2], False), reply.params[2]

    def read(self, motor_id: int, item: Item) -> int:
        reply = self._expect(self.request(proto.read(motor_id, item.address, item.size),
                                          motor_id),
                             motor_id, f"READ {item.name} ({item.address})")
        if len(reply.params) != item.size:
            if self.watching is not None:
                raise MotorLost(f"{self.who(motor_id)} answered READ {item.name} "
                                f"({item.address}) with a stale or garbled packet of "
                                f"{len(reply.params)} bytes, not {item.size}", motor_id)
            raise BusError(f"{self.who(motor_id)} answered READ {item.name} ({item.address}) "
                           f"with {len(reply.params)} bytes, not {item.size}")
        return proto.from_le(reply.params, item.signed)

    def write(self, motor_id: int, item: Item, value: int, reply: bool = True) -> None:
        frame = proto.write(motor_id, item.address, proto.le(value, item.size))
        if not reply:
            self.send(frame)
            return
        what = f"WRITE {item.name} ({item.address}) = {value}"
        reply = self.request(frame, motor_id)
        if reply is not None and reply.error & 0x7F == DATA_RANGE and item.name.startswith("Goal "):
            # A motor whose Bus Watchdog expired refuses every goal with a Data Range Error
            # until the watchdog is cleared: name that cause, not only the bit.
            raise BusError(f"{self.who(motor_id)} refused {what}: {describe_error(DATA_RANGE)}: "
                           "its Bus Watchdog expired (this command stalled past it), so it "
                           "holds its torque off")
        self._expect(reply, motor_id, what)

    def present(self, d: JointDrive) -> tuple[int, int, int]:
        """``(Present Current LSB, Present Velocity LSB, Present Position counts)`` of ``d`` in
        one READ with its Realtime Tick. While watched, a tick that did not move since the
        motor's last such read (its answer received more than :data:`STALE_AFTER_S` before
        this request left) is a stale packet: the motor repeats an old answer
        (:class:`MotorLost`)."""
        address = present_address(d.spec)
        what = f"READ Present state ({address}..{address + PRESENT.size - 1})"
        sent = time.perf_counter()
        reply = self._expect(self.request(proto.read(d.id, address, PRESENT.size), d.id),
                             d.id, what)
        if len(reply.params) != PRESENT.size:
            text = (f"{self.who(d.id)} answered {what} with a stale or garbled packet of "
                    f"{len(reply.params)} bytes, not {PRESENT.size}")
            raise MotorLost(text, d.id) if self.watching is not None else BusError(text)
        tick, current, velocity, position = PRESENT.unpack(reply.params)
        if self.watching is not None:
            # The motor sampled the last tick before its answer came (last[1]) and this one
            # after this request left (sent): more than STALE_AFTER_S between those two and
            # a tick that did not move is a stale answer, however late either answer came.
            last = self._ticks.get(d.id)
            if last is not None and last[0] == tick:
                elapsed_ms = (sent - last[1]) * 1e3
                wrapped = elapsed_ms % TICK_MODULO_MS  # a whole wrap of the tick is no proof
                if (elapsed_ms > STALE_AFTER_S * 1e3 and
                        STALE_AFTER_S * 1e3 < wrapped < TICK_MODULO_MS - STALE_AFTER_S * 1e3):
                    raise MotorLost(f"{self.who(d.id)} answered a stale packet (its Realtime "
                                    f"Tick stayed at {tick} ms over {elapsed_ms:.0f} ms)", d.id)
            self._ticks[d.id] = (tick, time.perf_counter())
        return current, velocity, position

    def position(self, d: JointDrive) -> int:
        """The motor's Present Position (counts)."""
        return self.read(d.id, d.spec.item("Present Position"))

    def current_mode_at_rest(self, d: JointDrive) -> None:
        """Torque off, no Bus Watchdog, current control, zero Goal Current: ``d`` ready to be
        enabled without a jump (the mode and the watchdog only take with the torque off)."""
        for name, value in (("Torque Enable", 0), ("Bus Watchdog", 0),
                            ("Operating Mode", CURRENT_MODE), ("Goal Current", 0)):
            self.write(d.id, d.spec.item(name), value)

    def torque_off(self, drives: list[JointDrive]) -> list[str]:
        """Goal Current 0 and Torque Enable 0 on each motor, whatever fails (a finally's
        clean-up): the motors that did not confirm the torque off."""
        failed = []
        for d in drives:
            try:
                self.write(d.id, d.spec.item("Goal Current"), 0)
            except BusError:
                pass  # a refused goal (e.g. after a watchdog error) must not stop the torque off
            try:
                self.write(d.id, d.spec.item("Torque Enable"), 0)
            except BusError:
                failed.append(self.who(d.id))
        return failed

    def alert(self, motor_id: int) -> bool:
        """Whether the motor's status packets carry the hardware alert bit (a PING's)."""
        reply = self.request(proto.ping(motor_id), motor_id)
        return reply is not None and bool(reply.error & ALERT_BIT)

    def broadcast_ping(self, highest_id: int = MAX_ID) -> tuple[dict[int, tuple[int, int]], int]:
        """Every motor that answers a broadcast PING: ``({id: (model number, firmware)},
        corrupted packets)``. Corrupted packets usually mean two motors share an ID."""
        found: dict[int, tuple[int, int]] = {}
        corrupted = 0
        window = (ADAPTER_LATENCY_S + PING_SLOT_S * (highest_id + 1)
                  + 14 * (highest_id + 1) * 10.0 / self.baud)
        self._send(proto.ping(BROADCAST_ID))
        for packet_id, _, params in self._packets(time.perf_counter() + window):
            if packet_id is None:
                corrupted += 1
            elif len(params) >= 3:
                found[packet_id] = (proto.from_le(params[0:2], False), params[2])
        return found, corrupted


def model_name(number: int) -> str:
    for spec in MODELS.values():
        if spec.number == number:
            return spec.name
    return f"model number {number}"


def check_chain(bus: Bus, drives: list[JointDrive], *, torque: bool = False) -> None:
    """Every motor of the description answers PING and is the description's model; all the
    problems in one message (exit 5), before anything is written. ``torque``: the caller will
    enable a motor, so one in hardware alert (its torque held off until a reboot) is refused
    here too, naming ``cochlea-dxl reboot``."""
    bus.names = {d.id: d for d in drives}
    problems, alerted = [], []
    for d in drives:
        answer = bus.ping(d.id)
        if answer is None:
            problems.append(f"{bus.who(d.id)} did not answer PING")
        elif answer[0] != d.spec.number:
            problems.append(f"{bus.who(d.id)} is {model_name(answer[0])} ({answer[0]}), not "
                            f"the {d.spec.name}'s {d.spec.number}")
        elif torque and bus.alert(d.id):
            status = bus.read(d.id, d.spec.item("Hardware Error Status"))
            alerted.append((d.id, f"{bus.who(d.id)} is in hardware alert "
                                  f"({describe_hardware_error(status)})"))
    if problems:
        raise BusError("; ".join(problems) + f" (on {bus.path} at {bus.baud} baud): check the "
                       "power, cables, IDs and --baud; cochlea-dxl scan lists what answers")
    if alerted:
        raise BusError("; ".join(text for _, text in alerted) + ": remove the cause, then "
                       "cochlea-dxl reboot --ids " + ",".join(str(i) for i, _ in alerted)
                       + f" --port {bus.path} --baud {bus.baud} before this step")


# ---- a move, watched ----------------------------------------------------------------------------


@contextlib.contextmanager
def motion(bus: Bus, moved: list[JointDrive], every: list[JointDrive], what: str):
    """Move or configure ``moved`` in the body, every status packet watched
    (:attr:`Bus.watching`): the hardware alert bit raises :class:`HardwareAlert`, no answer, a
    garbled or stale packet :class:`MotorLost`. At the body's end goal current 0 and torque
    off on ``moved``, still watched (an alert on those answers counts too). Whatever stops the
    body (those, any error, a signal): goal current 0 and torque off on ``every`` motor that
    answers, then the exception again; a :class:`MotionStopped` as one line naming the
    motor(s), the alert's bits in words and the ``reboot`` of those motors only. The caller
    writes its outputs only after this returned."""
    bus.watching = what
    bus._ticks.clear()
    try:
        yield
        for d in moved:
            bus.write(d.id, d.spec.item("Goal Current"), 0)
            bus.write(d.id, d.spec.item("Torque Enable"), 0)
    except MotionStopped as exc:
        bus.watching = None
        with _signals_held():
            failed = bus.torque_off(every)
        raise _stopped(bus, exc, every, what, failed) from None
    except BaseException as exc:
        bus.watching = None
        with _signals_held():
            failed = bus.torque_off(every)
        if failed and type(exc) is BusError:
            raise BusError(f"{exc}; torque off NOT confirmed by {', '.join(failed)}") from None
        if failed and not isinstance(exc, Exception):  # a signal: cochlea_dxl says it
            exc.unconfirmed = failed
        raise
    finally:
        bus.watching = None


#: The signals that stop a command (cochlea_dxl turns them into an exception).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _signals_held():
    """The stop signals held back while the torque goes off, so that one arriving then cannot
    cut the torque off short; raised once it is done (:func:`cochlea.console.signals_held`:
    Python-level handlers, which cover numpy's threads too, not a thread's signal mask)."""
    return signals_held(STOP_SIGNALS)


@contextlib.contextmanager
def finishing():
    """After the move, every torque off: the outputs are written and the result printed with
    the stop signals ignored (a few milliseconds), so that a signal cannot leave a record
    written under a message that says nothing was. One before this still stops the command
    with nothing written."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.signal(s, signal.SIG_IGN) for s in STOP_SIGNALS}
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _stopped(bus: Bus, exc: MotionStopped, every: list[JointDrive], what: str,
             failed: list[str]) -> MotionStopped:
    torque = ("goal current 0 and torque off on every motor" if not failed else
              f"goal current 0 and torque off, NOT confirmed by {', '.join(failed)}")
    if not isinstance(exc, HardwareAlert):
        return MotorLost(f"{exc} during {what}: stopped, {torque}; nothing done, nothing "
                         "written: check its power, cable and the bus, then run again",
                         exc.motor_id)
    alerted = []
    for d in every:  # the alert is latched until a reboot: ask every motor
        if d.id == exc.motor_id or bus.alert(d.id):
            try:
                status = value_text(d.spec.item("Hardware Error Status"),
                                    bus.read(d.id, d.spec.item("Hardware Error Status")),
                                    d.spec)
            except BusError:
                status = "Hardware Error Status unread"
            alerted.append((d.id, f"{bus.who(d.id)}: {status}"))
    if not any(i == exc.motor_id for i, _ in alerted):
        alerted.insert(0, (exc.motor_id, f"{bus.who(exc.motor_id)}: alert bit set"))
    return HardwareAlert(f"hardware alert during {what}: "
                         + "; ".join(text for _, text in alerted)
                         + f"; stopped: {torque}; nothing done, nothing written: remove the "
                         "cause (load, temperature, supply voltage), then cochlea-dxl reboot "
                         "--ids " + ",".join(str(i) for i, _ in alerted)
                         + f" --port {bus.path} --baud {bus.baud}", exc.motor_id)
