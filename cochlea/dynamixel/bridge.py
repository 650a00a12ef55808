"""``DynamixelBackend``: the real motors of a robot description, behind the loop's backend
interface (:mod:`cochlea.runtime.backend`).

Start-up (:meth:`DynamixelBackend.enable`), each step on every motor before the next, every
write confirmed by its status packet; any failure raises :class:`BackendError` after the safe
shut-down, before anything moved:

1. PING every motor of the description and check its model number (and its alert bit);
2. Torque Enable 0, and Bus Watchdog 0 (clears a watchdog error latched by an earlier run,
   which would make Goal Current read-only);
3. Operating Mode 0 (current control);
4. Return Delay Time 0;
5. Current Limit from the description (see :func:`cochlea.dynamixel.drives.current_limit_lsb`);
6. Goal Current 0 (the mode change reset it to the Current Limit);
7. Bus Watchdog (default 100 ms): the motors stop by themselves if the loop stops talking;
   (for a robot with a slider its homing record is checked after 1., before any write:
   :meth:`_check_homing`)
8. SYNC_READ until the first good read; the joints must lie within their limits;
9. Torque Enable 1, deferred to the first nonzero command (:meth:`~DynamixelBackend.write`):
   its Goal Current is written first, then one SYNC_WRITE of Torque Enable 1 to every motor
   and one SYNC_READ of Torque Enable confirming each (two transactions, not a round trip per
   motor: the first Goal Current is not held for milliseconds before the second command). A
   motor is never powered at zero current while the loop gets ready (thread starts, memory
   locking: milliseconds, tens under load), during which the parallel robot's slider fell
   freely on the emulator (a velocity-limit stop at t = 0 under load).

Every address and size the bridge writes or reads comes from the drives' model data
(``cochlea/dynamixel/models``, each model's control-table items), none from the X series'
constants: a confirmed WRITE or READ to one motor uses that motor's item; a frame for all
motors (the torque-on and its read-back, the shut-down's) is one SYNC_WRITE / SYNC_READ of the
item they all share (:func:`~cochlea.dynamixel.drives.shared_item`), or, where the models place
it differently (an X-series arm with a P-series joint: Torque Enable 64 and 512), one
BULK_WRITE / BULK_READ with each motor's own address; and every value written is checked
against its item's size and range before the port is opened
(:func:`~cochlea.dynamixel.drives.encode_item`).

The per-period transfers come from the models' data (:func:`choose_transfers`, summary
``read_instruction`` / ``write_instruction``): FAST_SYNC_READ (one combined status packet)
when every model answers it, BULK_READ / BULK_WRITE when a mixed chain's models place the
items at different addresses, SYNC_READ / SYNC_WRITE otherwise. The rest of this text says
SYNC_READ for any of them.

Each period: :meth:`~DynamixelBackend.read` is one SYNC_READ of 126..135 (current, velocity,
position; with ``realtime_tick``, 120..135: the Realtime Tick first), :meth:`~DynamixelBackend.
write` one SYNC_WRITE of Goal Current (the first nonzero one followed by the torque's
SYNC_WRITE and its confirming SYNC_READ, step 9; a torque that does not come on fails every
read after it as ``not-enabled``, so the loop's read watchdog stops the run). Both work in
preallocated buffers and report failures (timeout, CRC, error byte, hardware alert, port,
stale packet) as a False return and counters, never as an exception.

With ``realtime_tick`` (``cochlea-run`` sets it) a stale status packet (a motor repeating old
data) is refused by its Realtime Tick, the motor's millisecond counter: a tick equal to the one
carried by a reply that had already arrived 1.1 ms (one tick and a tenth for the motor's clock)
before this request cannot be fresh, whatever the host's or the bus's delays, so the read fails
as ``stale-packet``. At 1 kHz a single repeated packet is within that bound and passes (it is
one period old); two in a row are refused. The tick costs 6 bytes per motor and period
(122..125 lie between it and the state; see :mod:`cochlea.dynamixel.budget`).

Protocol 2.0 has no sequence numbers: a status packet later than the read timeout would pass
for the next period's. So after a failed read the next one first waits until the line has been
quiet for one timeout, dropping what arrives (and fails as ``late-traffic`` if it never is).

Shut-down (:meth:`~DynamixelBackend.disable`, also at interpreter exit and after a failed
start-up): SYNC_WRITE Goal Current 0, SYNC_WRITE Torque Enable 0 (each sent twice, no reply
needed, so one dead motor cannot hold up the others), then a READ of Torque Enable per motor
to confirm; ``shutdown_report`` says what was confirmed.
"""

from __future__ import annotations

import atexit
import math
import os
import time
from pathlib import Path

import numpy as np

from ..runtime.backend import BackendError
from . import homing
from . import lane as c_lane
from . import protocol as proto
from .budget import DEFAULT_ADAPTER_LATENCY_S, BusBudget, Verdict, bus_budget
from .control_table import (
    ALERT_BIT,
    CURRENT_MODE,
    MODELS_BY_NUMBER,
    MX64,
    STATE_ADDRESS,
    STATE_LENGTH,
    WATCHDOG_UNIT_S,
    baud_code,
    describe_error,
    describe_hardware_error,
)
from .drives import (
    DEFAULT_RAMP_NM,
    JointDrive,
    check_baud,
    drive_item,
    encode_item,
    joint_drives,
    shared_item,
)
from .port import SerialPort, is_socket_address, latency_timer_ms, open_port

#: Failure kinds a period can report (index into ``DynamixelBackend.failures``).
TIMEOUT, CRC, ERROR_BYTE, ALERT, LENGTH, PORT, LATE, NON_FINITE, NOT_ENABLED, INTERNAL, \
    STALE = range(11)
FAILURE_NAMES = ("timeout", "crc", "error-byte", "hardware-alert", "length", "port",
                 "late-traffic", "non-finite-command", "not-enabled", "internal", "stale-packet")

#: The per-period SYNC_READ with ``realtime_tick``: from Realtime Tick (120) to the end of the
#: state (135). Moving, Moving Status and Present PWM (122..125) lie between and come along: one
#: contiguous block, one packet per motor (6 bytes more per motor than 126..135 alone).
TICK_ADDRESS = MX64.item("Realtime Tick").address
TICK_READ_LENGTH = STATE_ADDRESS + STATE_LENGTH - TICK_ADDRESS
#: The Realtime Tick counts milliseconds modulo 32768; a tick that has not moved across more
#: than this (s, one tick and a tenth for the motor's clock) is a stale packet.
TICK_S = 1e-3
STALE_AFTER_S = 1.1 * TICK_S

#: What ``DynamixelBackend._next_packet`` returns besides the parser's own codes (>= 0).
_PORT_FAILED, _TIMED_OUT = -1, -2

#: ``homing``: "auto" checks the slider's homing record on a real port and not on a
#: pseudo-terminal (the emulator's slider starts where its scenario puts it, as if homed);
#: "required" always checks it; "off" never does.
HOMING_MODES = ("auto", "required", "off")

_STATE_DTYPE = np.dtype([("current", "<i2"), ("velocity", "<i4"), ("position", "<i4")])
_TICK_STATE_DTYPE = np.dtype([("tick", "<u2"), ("moving", "u1"), ("moving_status", "u1"),
                              ("pwm", "<i2"), ("current", "<i2"), ("velocity", "<i4"),
                              ("position", "<i4")])
assert _STATE_DTYPE.itemsize == STATE_LENGTH and _TICK_STATE_DTYPE.itemsize == TICK_READ_LENGTH
_GOAL_DTYPE = np.dtype([("id", "u1"), ("current", "<i2")])
#: One BULK_WRITE entry: ID, address (2), length (2), Goal Current (2).
_BULK_GOAL_DTYPE = np.dtype([("id", "u1"), ("address", "<u2"), ("length", "<u2"),
                             ("current", "<i2")])


#: ``read_instruction``: "auto" chooses from the data (:func:`choose_transfers`).
READ_INSTRUCTIONS = ("auto", "sync", "fast", "bulk")
WRITE_INSTRUCTIONS = ("auto", "sync", "bulk")
_READ_NAMES = {"sync": "SYNC_READ", "fast": "FAST_SYNC_READ", "bulk": "BULK_READ"}
_WRITE_NAMES = {"sync": "SYNC_WRITE", "bulk": "BULK_WRITE"}
#: The items each period reads, in the order of the state block, and the one it writes.
STATE_ITEMS = ("Present Current", "Present Velocity", "Present Position")
TICK_ITEMS = ("Realtime Tick",) + STATE_ITEMS


def _block(spec, items: tuple[str, ...]) -> tuple[int, int, tuple[int, ...]]:
    """``(address, length, offsets)`` of the contiguous block holding ``items`` in ``spec``'s
    control table (offsets of each item from the block's start; its size is in the tuple
    too, so two models agree only if addresses, sizes and offsets all do)."""
    found = [spec.item(name) for name in items]
    start = min(it.address for it in found)
    end = max(it.address + it.size for it in found)
    return start, end - start, tuple((it.address - start, it.size) for it in found)


#: The field of the state's record each item of the per-period block fills.
_STATE_FIELDS = {"Realtime Tick": "tick", "Present Current": "current",
                 "Present Velocity": "velocity", "Present Position": "position"}


def _check_state_layout(spec, items: tuple[str, ...], dtype: np.dtype) -> None:
    """Refuse, in one line, a model whose block of ``items`` is not laid out as the bridge's
    state record ``dtype`` parses it (offsets and sizes in bytes, the block's length)."""
    _, length, offsets = _block(spec, items)
    want = tuple((dtype.fields[_STATE_FIELDS[name]][1],
                  dtype.fields[_STATE_FIELDS[name]][0].itemsize) for name in items)
    if length != dtype.itemsize or offsets != want:
        raise BackendError(f"the {spec.name}'s {', '.join(items)} lie at {offsets} (offset, "
                           f"bytes) in a {length}-byte block: the bridge parses {want} in "
                           f"{dtype.itemsize} bytes")


def choose_transfers(specs, items: tuple[str, ...] = STATE_ITEMS,
                     goal_item: str = "Goal Current") -> tuple[str, str, str]:
    """The per-period read and write of a chain of motors of these models (their data:
    ``cochlea/dynamixel/models``): ``(read, write, why)``.

    * read: "bulk" (BULK_READ, per-motor address and length) when the motors' blocks of
      ``items`` lie at different addresses; "fast" (FAST_SYNC_READ) when they all lie at the
      same address and every model's data says it answers FAST_SYNC_READ
      (``fast_sync_read = true``); "sync" (SYNC_READ) otherwise -- an unsourced
      ``fast_sync_read`` counts as no;
    * write: "sync" (SYNC_WRITE) when every model's ``goal_item`` has one address and size,
      "bulk" (BULK_WRITE) otherwise.

    Raises :class:`BackendError` for a chain no transfer can read into one state layout (the
    items' sizes or order within the block differ): the parse would misread them."""
    specs = list(specs)
    blocks = []
    for spec in specs:
        try:
            blocks.append(_block(spec, items))
        except KeyError as exc:
            raise BackendError(f"the {spec.name} has no {exc.args[0]} item: the bridge "
                               "cannot read it") from None
    if len({(length, offsets) for _, length, offsets in blocks}) > 1:
        raise BackendError("the motors' control tables place " + ", ".join(items)
                           + " differently within the block (" + "; ".join(
                               f"{sp.name}: {b[2]}" for sp, b in zip(specs, blocks))
                           + "): no single read layout fits them")
    goals = set()
    for spec in specs:
        try:
            it = spec.item(goal_item)
        except KeyError:
            raise BackendError(f"the {spec.name} has no {goal_item} item") from None
        if it.size != 2:
            raise BackendError(f"the {spec.name}'s {goal_item} is {it.size} bytes, not 2")
        goals.add(it.address)
    write = "sync" if len(goals) == 1 else "bulk"
    if len({b[0] for b in blocks}) > 1:
        return "bulk", write, ("the motors read " + ", ".join(items) + " at different "
                               "addresses: BULK_READ")
    unsure = sorted({sp.name for sp in specs if sp.fast_sync_read is None})
    no = sorted({sp.name for sp in specs if sp.fast_sync_read is False})
    if not unsure and not no:
        return "fast", write, "every model answers FAST_SYNC_READ (its data)"
    why = []
    if no:
        why.append(", ".join(no) + " without FAST_SYNC_READ")
    if unsure:
        why.append(", ".join(unsure) + ": FAST_SYNC_READ support not sourced")
    return "sync", write, "SYNC_READ (" + "; ".join(why) + ")"


#: How far (rad for a revolute joint, m for a prismatic one) a joint may stand from the
#: scenario's initial pose when the run starts (cochlea-run --start-tolerance-deg/-mm).
START_TOLERANCE = (math.radians(5.0), 5e-3)


class DynamixelBackend:
    """The motors of ``robot`` (``"serial"`` or ``"parallel"``) as described in
    ``description`` (default: the shipped ``models/robots/ROBOT.toml``; or ``system``,
    the description already loaded), on the serial port ``port``.

    Joint order: serial, arm 1's joints then arm 2's; parallel, th1, th2, d1, th1', th2'.
    ``x = [q, qd]`` in rad (m) and rad/s (m/s), efforts in N m (N).

    Options: ``baud`` must be the motors' configured rate (the bridge does not change it);
    ``watchdog_s`` the Bus Watchdog (20 ms steps, 0.02..2.54 s); ``timeout_s`` how long a read
    waits for all status packets (default: the bus time plus 3 ms); ``ramp_Nm`` the fit's
    blending band (:mod:`cochlea.dynamixel.drives`); ``position_margin_rad`` how far outside its
    limits a joint may be at start-up; ``adapter_latency_s`` for the bus budget (default: the
    adapter's latency timer from sysfs, 0 for a pseudo-terminal, else 1 ms); ``realtime_tick``
    to read the Realtime Tick with the state and refuse stale packets (see the module
    docstring); ``offset_current`` whether each command gets the fit's offset current, the
    gearbox's friction (:func:`cochlea.robots.motor_fit.bridge_compensates_friction` decides it
    from the controller: False when the controller compensates friction itself, so that it is
    compensated once).
    """

    name = "dynamixel"
    #: The motors know only what they measure: no true state (Backend.true_state).
    true_state = None

    def __init__(self, robot: str, port: str, baud: int = 4_000_000, *,
                 description: str | Path | None = None, watchdog_s: float = 0.1,
                 timeout_s: float | None = None, ramp_Nm: float = DEFAULT_RAMP_NM,
                 position_margin_rad: float = math.radians(2.0),
                 adapter_latency_s: float | None = None, retries: int = 3,
                 open_port=open_port, system=None, homing: str = "auto",
                 homing_record: str | Path | None = None, realtime_tick: bool = False,
                 offset_current: bool = True, read_instruction: str = "auto",
                 write_instruction: str = "auto", expected_start=None,
                 start_tolerance: tuple[float, float] = START_TOLERANCE):
        self.robot = robot
        self.port_path = str(port)
        baud_code(baud)  # a rate the motors do not have is the user's mistake, before the port
        self.baud = int(baud)
        self.drives: list[JointDrive] = joint_drives(robot, description, ramp_Nm,
                                                    system=system)
        check_baud(self.drives, self.baud)  # a rate one of the models does not take
        self.nq = n = len(self.drives)
        self.ids = [d.id for d in self.drives]
        if not 0.02 <= watchdog_s <= 127 * WATCHDOG_UNIT_S:
            raise BackendError(f"the Bus Watchdog must be 0.02..2.54 s, got {watchdog_s} s")
        self.watchdog_lsb = max(1, min(127, int(math.ceil(watchdog_s / WATCHDOG_UNIT_S - 1e-9))))
        if adapter_latency_s is None:
            timer = latency_timer_ms(self.port_path)
            if timer is not None:
                adapter_latency_s = timer * 1e-3
            elif self.port_path.startswith("/dev/pts/") or is_socket_address(self.port_path):
                adapter_latency_s = 0.0  # the emulator: no adapter holds the bytes
            else:
                adapter_latency_s = DEFAULT_ADAPTER_LATENCY_S
        self.realtime_tick = bool(realtime_tick)
        # The per-period transfers, from the models' data (a mixed chain whose items lie at
        # different addresses: BULK_READ / BULK_WRITE; FAST_SYNC_READ where every model has it).
        if read_instruction not in READ_INSTRUCTIONS:
            raise BackendError(f"read_instruction must be one of {', '.join(READ_INSTRUCTIONS)}"
                               f", got {read_instruction!r}")
        if write_instruction not in WRITE_INSTRUCTIONS:
            raise BackendError(f"write_instruction must be one of "
                               f"{', '.join(WRITE_INSTRUCTIONS)}, got {write_instruction!r}")
        items = TICK_ITEMS if self.realtime_tick else STATE_ITEMS
        dtype = _TICK_STATE_DTYPE if self.realtime_tick else _STATE_DTYPE
        auto_read, auto_write, why = choose_transfers([d.spec for d in self.drives], items)
        self.read_instruction = auto_read if read_instruction == "auto" else read_instruction
        self.write_instruction = auto_write if write_instruction == "auto" \
            else write_instruction
        if read_instruction != "auto" and read_instruction != auto_read:
            why = f"{_READ_NAMES[self.read_instruction]} (asked; the data: {why})"
        if auto_read == "bulk" and self.read_instruction != "bulk":
            raise BackendError(f"{_READ_NAMES[self.read_instruction]} cannot read this chain: "
                               + why)
        if auto_write == "bulk" and self.write_instruction != "bulk":
            raise BackendError("SYNC_WRITE cannot write this chain's Goal Current: the models "
                               "place it at different addresses")
        self.read_choice = why
        # Each motor's block of the state items, at its address in its model's data (one
        # address for all unless BULK_READ: choose_transfers), parsed into ``dtype``.
        self._reads = [(d.id, *_block(d.spec, items)[:2]) for d in self.drives]
        for d in self.drives:
            _check_state_layout(d.spec, items, dtype)
        read_address, read_length = self._reads[0][1:]
        self._read_length = read_length
        self.budget: BusBudget = bus_budget(n, self.baud, adapter_latency_s=adapter_latency_s,
                                            read_length=read_length,
                                            read_instruction=self.read_instruction,
                                            write_instruction=self.write_instruction)
        self.timeout_s = timeout_s if timeout_s is not None else self.budget.cycle_s + 3e-3
        self.position_margin = position_margin_rad
        self.expected_start = None if expected_start is None else \
            np.asarray(expected_start, float).ravel()
        if self.expected_start is not None and self.expected_start.shape != (n,):
            raise BackendError(f"the expected start pose has {self.expected_start.size} "
                               f"joints, the description {n}")
        self.start_tolerance = tuple(float(v) for v in start_tolerance)
        if not all(math.isfinite(v) and v > 0 for v in self.start_tolerance):
            raise BackendError(f"the start tolerance must be positive, got "
                               f"{start_tolerance}")
        self.retries = max(1, retries)
        if homing not in HOMING_MODES:
            raise BackendError(f"homing must be one of {', '.join(HOMING_MODES)}, got {homing!r}")
        self.homing, self.homing_record = homing, homing_record
        #: Which description the homing record must have been made for (the path given, or
        #: the shipped one; ``system`` alone is taken for the shipped one).
        self.description = description
        self.homing_report = "no slider"
        self._homing_markers: list[tuple[JointDrive, int]] = []
        self._open_port = open_port
        self._port: SerialPort | None = None
        self._active = False
        #: Torque Enable 1 is still to be written (start-up step 9, at the first nonzero
        #: command); why it failed, if it did (every read fails as not-enabled then).
        self._torque_pending = False
        self.torque_on_error: str | None = None
        self._torque_failed_id = -1
        self._suspect = False  # the last read failed: wait for a quiet line first
        self.last_io_time_s = 0.0
        self._read_time = 0.0

        # ---- preallocated per-period state -----------------------------------------------------
        self._parser = proto.PacketParser(status=True)
        if self.read_instruction == "bulk":
            self._read_frame = proto.bulk_read(self._reads)
        elif self.read_instruction == "fast":
            self._read_frame = proto.fast_sync_read(read_address, read_length, self.ids)
        else:
            self._read_frame = proto.sync_read(read_address, read_length, self.ids)
        self._read_view = memoryview(self._read_frame)
        # Every address and size written or read below is the drives' model data's
        # (cochlea/dynamixel/models); a frame that is one SYNC_WRITE or SYNC_READ for all
        # motors takes the item they all share (shared_item: a chain whose models place it
        # differently is refused here, in one line). Goal Current is 2 bytes on every model
        # (choose_transfers checks it): the preallocated frames below carry an int16.
        goal = [drive_item(d, "Goal Current") for d in self.drives]
        if self.write_instruction == "bulk":
            self._write_frame, _ = proto.bulk_write_buffer(
                [(d.id, it.address, it.size) for d, it in zip(self.drives, goal)])
            self._goal = np.frombuffer(self._write_frame.params, _BULK_GOAL_DTYPE,
                                       count=n)["current"]
        else:
            it = shared_item(self.drives, "Goal Current")
            self._write_frame = proto.sync_write_buffer(it.address, it.size, self.ids)
            self._goal = np.frombuffer(self._write_frame.params, _GOAL_DTYPE, count=n,
                                       offset=4)["current"]
        self._raw = bytearray(read_length * n)
        self._raw_view = memoryview(self._raw)
        state = np.frombuffer(self._raw, dtype)
        self._cur, self._vel, self._pos = state["current"], state["velocity"], state["position"]
        self._tick = state["tick"] if self.realtime_tick else None
        # Per motor: the last Realtime Tick seen, and when the reply that first carried it had
        # arrived (perf_counter s): the motor sampled it no later than that.
        self._last_tick = [-1] * n
        self._tick_seen = [0.0] * n
        self._slot_of = [-1] * 256
        for j, motor_id in enumerate(self.ids):
            self._slot_of[motor_id] = j
        self._slots = bytearray(n)  # 0 waiting, 1 good, 2 failed
        # A SYNC_READ's whole reply checked and copied in C when it is what a healthy chain
        # sends (None: no library, or another read instruction; see _sync_read).
        self._status_block = (c_lane.status_block(self._parser.buf, self.ids, read_length,
                                                  self._raw)
                              if self.read_instruction == "sync" else None)
        f = np.array
        self._q_per_count = f([d.q_per_count for d in self.drives])
        self._q_offset = f([d.q_offset for d in self.drives])
        self._qd_per_lsb = f([d.qd_per_lsb for d in self.drives])
        self._mA_per_lsb = f([d.spec.current_unit_mA for d in self.drives])
        self._torque_per_effort = f([d.torque_per_effort for d in self.drives])
        self._inv_a = f([1.0 / d.fit.a for d in self.drives])
        self._inv_ramp = f([1.0 / d.fit.ramp for d in self.drives])
        #: Whether the commands carry the fit's offset current (friction compensated here).
        self.offset_current = bool(offset_current)
        self._i0 = f([d.fit.offset_current * self.offset_current for d in self.drives])
        self._lsb_per_ampere = f([d.lsb_per_ampere for d in self.drives])
        self._limit = f([float(d.current_limit_lsb) for d in self.drives])
        self._neg_limit = -self._limit
        self._torque = np.zeros(n)
        self._blend = np.zeros(n)
        self._amps = np.zeros(n)
        self._finite = np.zeros(n, dtype=bool)
        #: Present Current of the last good read (mA) and the last Goal Current sent (LSB).
        self.present_current_mA = np.zeros(n)
        #: The same current at the joint (A), signed so that a positive current drives the
        #: joint positively (the loop logs it: Backend.joint_current_A).
        self.joint_current_A = np.zeros(n)
        self._joint_A_per_lsb = f([d.spec.current_unit_mA * 1e-3
                                   * math.copysign(1.0, d.torque_per_effort)
                                   for d in self.drives])
        self.goal_current_lsb = self._goal

        # ---- diagnostics -------------------------------------------------------------------------
        self.failures = [0] * len(FAILURE_NAMES)  # periods failed, by first cause
        self.garbage_packets = 0  # headers with impossible fields, packets of the wrong kind
        self.unexpected_packets = 0  # good packets nobody asked for (duplicates, other IDs)
        self.reads = 0  # SYNC_READs since enable() returned
        self.startup_reads = 0  # those of the start-up
        self.good_reads = 0
        self.writes = 0
        self.last_failure = -1
        self.last_failure_id = -1
        self.alert_ids: set[int] = set()
        #: Hardware Error Status (70) of each motor that raised its alert, read in the period
        #: after the alert (that period fails anyway: the alert bit stays until a reboot).
        self.alert_status: dict[int, int] = {}
        self._alert_pending = -1  # the motor whose status is still to be read, or -1
        self._alert_tries = 0
        #: Per motor: the READ of its Hardware Error Status, and the item's size (bytes).
        self._alert_frames = {}
        for d in self.drives:
            it = drive_item(d, "Hardware Error Status")
            self._alert_frames[d.id] = (proto.read(d.id, it.address, it.size), it.size)
        self.shutdown_report = "not started"
        #: Firmware Version of each motor, from its PING reply at start-up.
        self.firmware: dict[int, int] = {}
        torque = [drive_item(d, "Torque Enable") for d in self.drives]
        if self.write_instruction == "bulk":
            self._zero_frame = proto.bulk_write(
                [(d.id, it.address, encode_item(d, it, 0)) for d, it in zip(self.drives, goal)])
            self._torque_off_frame = proto.bulk_write(
                [(d.id, it.address, encode_item(d, it, 0))
                 for d, it in zip(self.drives, torque)])
        else:
            self._zero_frame = self._write_all("Goal Current", 0)
            self._torque_off_frame = self._write_all("Torque Enable", 0)
        #: The shut-down's confirming READ of Torque Enable, per motor: (frame, its 0).
        self._torque_off_checks = [(proto.read(d.id, it.address, it.size),
                                    encode_item(d, it, 0)) for d, it in zip(self.drives, torque)]
        # Start-up step 9's two transactions, made once: Torque Enable 1 to every motor (no
        # reply), then a read of Torque Enable from every motor, at the item's address and size
        # in the models' data: one SYNC_WRITE and one SYNC_READ where every model places it
        # alike, else (an X-series arm with a P-series joint: 64 and 512) one BULK_WRITE and
        # one BULK_READ, each motor at its own address.
        self._torque_on_frame = self._write_all("Torque Enable", 1)
        self._torque_sizes = [it.size for it in torque]
        if len({(it.address, it.size) for it in torque}) == 1:
            it = torque[0]
            self._torque_check_frame = proto.sync_read(it.address, it.size, self.ids)
            self._torque_on_what = (f"torque on (SYNC_WRITE {it.address} = 1, read back by "
                                    "SYNC_READ)")
        else:
            self._torque_check_frame = proto.bulk_read(
                [(d.id, it.address, it.size) for d, it in zip(self.drives, torque)])
            where = ", ".join(sorted({f"{it.address} ({d.spec.name})"
                                      for d, it in zip(self.drives, torque)}))
            self._torque_on_what = (f"torque on (BULK_WRITE Torque Enable = 1 at {where}, "
                                    "read back by BULK_READ)")
        #: Start-up steps 2.-7.: (what, one confirmed WRITE per motor), each motor's item at
        #: its own address and size, every value checked against its item here, before the
        #: port is opened.
        mode = [CURRENT_MODE] * n
        self._setup_writes = [
            self._writes("Torque Enable", [0] * n, "torque off"),
            self._writes("Bus Watchdog", [0] * n, "clear the Bus Watchdog"),
            self._writes("Operating Mode", mode, "current control mode"),
            self._writes("Return Delay Time", [0] * n, "return delay 0"),
            self._writes("Current Limit", [d.current_limit_lsb for d in self.drives],
                         "the current limit"),
            self._writes("Goal Current", [0] * n, "goal current 0"),
            self._writes("Bus Watchdog", [self.watchdog_lsb] * n, "the Bus Watchdog"),
        ]

    def _write_all(self, name: str, value: int) -> bytes:
        """One SYNC_WRITE of ``value`` to item ``name`` of every motor where their models
        place it alike (the shipped robots' frames), else one BULK_WRITE, each motor's item
        at its own address (a mixed chain's)."""
        items = [drive_item(d, name) for d in self.drives]
        if len({(it.address, it.size) for it in items}) > 1:
            return proto.bulk_write([(d.id, it.address, encode_item(d, it, value))
                                     for d, it in zip(self.drives, items)])
        it = shared_item(self.drives, name)
        return proto.sync_write(it.address, it.size,
                                [(d.id, encode_item(d, it, value)) for d in self.drives])

    def _writes(self, name: str, values, what: str) -> list[tuple[JointDrive, str, bytes]]:
        """A confirmed WRITE of ``values`` (one per motor) to item ``name``:
        ``(drive, what it does, frame)`` per motor, at the item's address in its model."""
        out = []
        for d, value in zip(self.drives, values):
            it = drive_item(d, name)
            out.append((d, f"{what} (WRITE {it.address} = {value})",
                        proto.write(d.id, it.address, encode_item(d, it, int(value)))))
        return out

    # ---- the Backend interface ------------------------------------------------------------------

    def enable(self) -> None:
        if self._active:
            return
        try:
            self._port = self._open_port(self.port_path, self.baud)
            self._startup()
        except BackendError:
            self.disable()
            raise
        except Exception as exc:  # noqa: BLE001 (anything else is a start-up failure too)
            self.disable()
            raise BackendError(f"start-up on {self.port_path} failed: {exc!r}") from exc
        # The counters cover the run from here; the start-up's reads are kept apart.
        self.startup_reads, self.reads, self.good_reads, self.writes = self.reads, 0, 0, 0
        self.failures = [0] * len(FAILURE_NAMES)
        self._active = True
        atexit.register(self.disable)

    def read(self, x: np.ndarray) -> bool:
        t0 = time.perf_counter()
        try:
            ok = self._sync_read(x, t0)
        except Exception:  # noqa: BLE001 (the loop must never see an exception)
            ok = self._fail(INTERNAL, -1)
        self._read_time = time.perf_counter() - t0
        return ok

    def write(self, tau: np.ndarray) -> bool:
        t0 = time.perf_counter()
        try:
            ok = self._sync_write(tau, t0)
        except Exception:  # noqa: BLE001
            ok = self._fail(INTERNAL, -1)
        self.last_io_time_s = self._read_time + (time.perf_counter() - t0)
        return ok

    def disable(self) -> None:
        """Goal Current 0 and Torque Enable 0 on every motor, then close the port. Never
        raises; a second call does nothing."""
        self._active = False
        port, self._port = self._port, None
        if port is None:
            return
        try:
            atexit.unregister(self.disable)
            self.shutdown_report = self._shutdown(port)
        except Exception as exc:  # noqa: BLE001
            self.shutdown_report = f"shut-down interrupted: {exc!r}"
        finally:
            port.close()

    # ---- reports --------------------------------------------------------------------------------

    @property
    def enabled(self) -> bool:
        return self._active

    def check_rate(self, rate_hz: float) -> Verdict:
        """Whether this bus can carry the loop's rate (see :mod:`cochlea.dynamixel.budget`)."""
        return self.budget.check(rate_hz)

    def describe_last_failure(self) -> str:
        if self.last_failure < 0:
            return "no failure"
        who = f" (ID {self.last_failure_id}{self._joint_of(self.last_failure_id)})" \
            if self.last_failure_id >= 0 else ""
        return FAILURE_NAMES[self.last_failure] + who

    def failure_detail(self) -> str:
        """Why the reads failed, for the loop's stop line: the motor and its hardware error
        when one raised its alert (the bits decoded, e.g. ``ID 3 (arm1.link3, MX-64): hardware
        error (overload)``), the torque that did not come on, else the last failure and its
        motor."""
        if self.torque_on_error is not None:
            return f"the torque did not come on: {self.torque_on_error}"
        if self.alert_ids:
            notes = []
            for motor_id in sorted(self.alert_ids):
                d = self.drives[self._slot_of[motor_id]]
                status = self.alert_status.get(motor_id)
                what = "Hardware Error Status not read" if status is None \
                    else describe_hardware_error(status)
                notes.append(f"{self._who(d)}: hardware error ({what})")
            return "; ".join(notes)
        if self.last_failure < 0:
            return "no failure recorded"
        j = self._slot_of[self.last_failure_id] if 0 <= self.last_failure_id < 256 else -1
        return (f"last failure {FAILURE_NAMES[self.last_failure]}"
                + (f" from {self._who(self.drives[j])}" if j >= 0 else ""))

    def position_quantum(self) -> np.ndarray:
        """One encoder count of each joint (rad, or m for the slider through its pinion), in
        the loop's joint order: what a run's convergence floor is measured against."""
        return np.abs(self._q_per_count)

    def summary(self) -> dict:
        """Counters and settings for a run's summary (JSON-ready)."""
        port = self._port
        return {
            "port": self.port_path, "baud": self.baud, "motors": self.ids,
            # The budget of the transfers sent each period, chosen from the models' data
            # (choose_transfers), and why. (Within bus_budget: the embedded program's summary
            # has every key of this level, tests/test_embedded_program.py.)
            "bus_budget": {"bytes_per_period": self.budget.total_bytes,
                           "wire_s": self.budget.wire_s, "bus_s": self.budget.bus_s,
                           "with_adapter_latency_s": self.budget.cycle_s,
                           "read_instruction": _READ_NAMES[self.read_instruction],
                           "write_instruction": _WRITE_NAMES[self.write_instruction],
                           "read_choice": self.read_choice},
            "read_timeout_s": self.timeout_s, "watchdog_s": self.watchdog_lsb * WATCHDOG_UNIT_S,
            "realtime_tick_check": self.realtime_tick,
            # Who compensates the gearbox's friction: the bridge's offset current, or the
            # controller (then the commands carry the fit's slope alone).
            "friction_compensated_by": "bridge" if self.offset_current else "controller",
            "reads": self.reads, "good_reads": self.good_reads, "writes": self.writes,
            "failures": {name: c for name, c in zip(FAILURE_NAMES, self.failures) if c},
            "garbage_packets": self.garbage_packets,
            "unexpected_packets": self.unexpected_packets,
            "last_failure": self.describe_last_failure(),
            "low_latency": None if port is None else port.low_latency,
            "homing": self.homing_report,
            "shutdown": self.shutdown_report,
        }

    def _joint_of(self, motor_id: int) -> str:
        j = self._slot_of[motor_id] if 0 <= motor_id < 256 else -1
        return f", {self.drives[j].name}" if j >= 0 else ""

    # ---- per period -----------------------------------------------------------------------------

    def _fail(self, kind: int, motor_id: int) -> bool:
        self.failures[kind] += 1
        self.last_failure = kind
        self.last_failure_id = motor_id
        if kind < NON_FINITE:
            self._suspect = True
        return False

    def _quiet(self, port: SerialPort, t0: float) -> bool:
        """After a failed read, replies may still be on their way: Protocol 2.0 has no sequence
        numbers, so a late one would pass for the next period's. Wait until the line has been
        quiet for one read timeout, dropping what arrives; give up at twice that."""
        parser = self._parser
        give_up = t0 + 2 * self.timeout_s
        quiet_until = t0 + self.timeout_s
        while True:
            got = port.read_into(parser.space(), quiet_until if quiet_until < give_up
                                 else give_up)
            parser.reset()
            now = time.perf_counter()
            if got < 0:
                return False
            if got == 0 and now >= quiet_until:
                self._suspect = False
                return True
            if now >= give_up:
                return False
            if got > 0:
                quiet_until = now + self.timeout_s

    def _sync_read(self, x: np.ndarray, t0: float) -> bool:
        self.reads += 1
        port = self._port
        if not self._active or port is None:
            return self._fail(NOT_ENABLED, -1)
        if self.torque_on_error is not None:
            return self._fail(NOT_ENABLED, self._torque_failed_id)
        parser = self._parser
        port.discard_input()
        parser.reset()
        if self._suspect and not self._quiet(port, t0):
            return self._fail(LATE, -1)
        if self._alert_pending >= 0:
            return self._read_alert(port)
        asked = time.perf_counter()
        deadline = asked + self.timeout_s
        if not port.write(self._read_view, len(self._read_frame), deadline):
            return self._fail(PORT, -1)
        if self.read_instruction == "fast":
            ok = self._fast_sync_read(port, deadline)
            if not ok:
                return False
            return self._finish_read(x, asked)
        block = self._status_block
        if block is not None:
            # The whole reply as a healthy chain sends it, in one C call; anything else (a
            # timeout, a fault, a stuffed byte) goes on below on the same bytes, as before.
            while parser.pending < block.total:
                got = port.read_into(parser.space(), deadline)
                if got <= 0:
                    break
                parser.commit(got)
            if parser.pending >= block.total and block(parser.start, parser.pending):
                parser.start += block.total
                return self._finish_read(x, asked)
        slots, slot_of = self._slots, self._slot_of
        n = self.nq
        length = self._read_length
        for j in range(n):
            slots[j] = 0
        pending = n
        failure, failure_id = -1, -1
        while pending:
            code = self._next_packet(port, deadline)
            if code == _PORT_FAILED:
                return self._fail(PORT, -1)
            if code == _TIMED_OUT:
                if failure < 0:
                    failure = TIMEOUT
                    failure_id = self.ids[slots.index(0)]
                break
            if code == proto.OK:
                j = slot_of[parser.id]
                if j < 0 or slots[j]:
                    self.unexpected_packets += 1
                    continue
                pending -= 1
                error = parser.error
                if error & ALERT_BIT:
                    if parser.id not in self.alert_ids:
                        self.alert_ids.add(parser.id)
                        self._alert_pending, self._alert_tries = parser.id, 0
                    failure, failure_id = ALERT, parser.id  # outranks every other cause
                if parser.params_len != length or error & 0x7F:
                    slots[j] = 2
                    if failure < 0:
                        failure = LENGTH if parser.params_len != length else ERROR_BYTE
                        failure_id = parser.id
                    continue
                slots[j] = 1
                start = parser.params_start
                self._raw_view[j * length:(j + 1) * length] = \
                    parser.view[start:start + length]
            elif code == proto.CRC_FAILURE:
                if failure < 0:
                    failure, failure_id = CRC, parser.id
                j = slot_of[parser.id]
                if j >= 0 and slots[j] == 0:
                    slots[j] = 2
                    pending -= 1
            else:
                self.garbage_packets += 1
        if failure >= 0:
            return self._fail(failure, failure_id)
        return self._finish_read(x, asked)

    def _finish_read(self, x: np.ndarray, asked: float) -> bool:
        """Every motor's block is in ``_raw``: the stale-packet check, then the state."""
        n = self.nq
        if self.realtime_tick and not self._fresh(asked, time.perf_counter()):
            return False
        q, qd = x[:n], x[n:]
        np.multiply(self._pos, self._q_per_count, out=q)
        np.add(q, self._q_offset, out=q)
        np.multiply(self._vel, self._qd_per_lsb, out=qd)
        np.multiply(self._cur, self._mA_per_lsb, out=self.present_current_mA)
        np.multiply(self._cur, self._joint_A_per_lsb, out=self.joint_current_A)
        self.good_reads += 1
        return True

    def _fast_sync_read(self, port: SerialPort, deadline: float) -> bool:
        """The reply to a FAST_SYNC_READ: one combined status packet (ID 0xFE) holding every
        motor's block (:func:`cochlea.dynamixel.protocol.check_fast_sync`), copied into
        ``_raw``. Its faults go through the same counters and failure kinds as SYNC_READ's: a
        motor missing from the packet ``length`` (that motor), a CRC that fails (the packet's:
        ``crc``, the motor unknown; a block's running CRC: ``crc``, that motor), another ID
        where a block belongs (``length``), an error byte or the alert bit in a block
        (``error-byte``, ``hardware-alert``), a motor answering alone with an error (a model or
        firmware without FAST_SYNC_READ: ``error-byte``), nothing in time (``timeout``)."""
        parser = self._parser
        length = self._read_length
        ids = self.ids
        while True:
            code = self._next_packet(port, deadline)
            if code == _PORT_FAILED:
                return self._fail(PORT, -1)
            if code == _TIMED_OUT:
                return self._fail(TIMEOUT, ids[0])
            if code == proto.CRC_FAILURE:
                return self._fail(CRC, parser.id if self._slot_of[parser.id] >= 0 else -1)
            if code != proto.OK:
                self.garbage_packets += 1
                continue
            if parser.id != proto.BROADCAST_ID:
                if self._slot_of[parser.id] < 0:
                    self.unexpected_packets += 1
                    continue
                # A motor answering on its own: it refused the instruction (or its alert).
                if parser.error & ALERT_BIT:
                    return self._alert(parser.id)
                return self._fail(ERROR_BYTE if parser.error & 0x7F else LENGTH, parser.id)
            break
        result, k = proto.check_fast_sync(parser, ids, length)
        if result == proto.FAST_BLOCK_CRC:
            return self._fail(CRC, ids[k])
        if result:
            return self._fail(LENGTH, ids[k])
        buf, raw = parser.view, self._raw_view
        failure, failure_id = -1, -1
        for j in range(self.nq):
            at = proto.fast_block(parser, j, length)
            error = buf[at]
            if error & ALERT_BIT:
                if ids[j] not in self.alert_ids:
                    self.alert_ids.add(ids[j])
                    self._alert_pending, self._alert_tries = ids[j], 0
                failure, failure_id = ALERT, ids[j]
            elif error & 0x7F and failure < 0:
                failure, failure_id = ERROR_BYTE, ids[j]
            raw[j * length:(j + 1) * length] = buf[at + 2:at + 2 + length]
        if failure >= 0:
            return self._fail(failure, failure_id)
        return True

    def _alert(self, motor_id: int) -> bool:
        if motor_id not in self.alert_ids:
            self.alert_ids.add(motor_id)
            self._alert_pending, self._alert_tries = motor_id, 0
        return self._fail(ALERT, motor_id)

    def _fresh(self, asked: float, arrived: float) -> bool:
        """The Realtime-Tick check of a read whose packets all came (``asked``: when the
        request was sent; ``arrived``: when the last reply was in): False, a ``stale-packet``
        failure, if a motor's tick has not moved since a reply that was in more than
        STALE_AFTER_S before this request. No allocation: ints and floats only."""
        last, seen, ticks = self._last_tick, self._tick_seen, self._tick
        for j in range(self.nq):
            tick = int(ticks[j])
            if tick != last[j]:
                last[j] = tick
                seen[j] = arrived
            elif asked - seen[j] > STALE_AFTER_S:
                return self._fail(STALE, self.ids[j])
        return True

    def _next_packet(self, port: SerialPort, deadline: float) -> int:
        """The parser's code for the next packet on the line (``proto.OK``, ``CRC_FAILURE``,
        or another for garbage), reading from ``port`` as needed until ``deadline``;
        ``_PORT_FAILED`` if the port failed, ``_TIMED_OUT`` if nothing whole came in time."""
        parser = self._parser
        while True:
            code = parser.parse()
            if code != proto.NEED_MORE:
                return code
            got = port.read_into(parser.space(), deadline)
            if got > 0:
                parser.commit(got)
            elif got < 0:
                return _PORT_FAILED
            else:
                return _TIMED_OUT

    def _read_alert(self, port: SerialPort) -> bool:
        """Instead of the state, this period reads the Hardware Error Status of the motor that
        raised its alert, so the stop can say what it was; a failed period all the same."""
        motor_id = self._alert_pending
        self._alert_tries += 1
        if self._alert_tries >= 3:
            self._alert_pending = -1  # give up; the shut-down report reads it once more
        parser = self._parser
        frame, size = self._alert_frames[motor_id]
        deadline = time.perf_counter() + self.timeout_s
        if not port.write(memoryview(frame), len(frame), deadline):
            return self._fail(PORT, -1)
        while True:
            code = self._next_packet(port, deadline)
            if code == _PORT_FAILED:
                return self._fail(PORT, -1)
            if code == _TIMED_OUT:
                break
            if code == proto.OK and parser.id == motor_id and parser.params_len == size:
                start = parser.params_start
                self.alert_status[motor_id] = proto.from_le(
                    parser.view[start:start + size], False)
                self._alert_pending = -1
                break
        return self._fail(ALERT, motor_id)

    def _sync_write(self, tau: np.ndarray, t0: float) -> bool:
        port = self._port
        if not self._active or port is None:
            return self._fail(NOT_ENABLED, -1)
        self.writes += 1
        finite = bool(np.isfinite(tau, out=self._finite).all())
        if finite:
            torque, blend, amps = self._torque, self._blend, self._amps
            np.multiply(tau, self._torque_per_effort, out=torque)  # motor torque, N m
            np.multiply(torque, self._inv_ramp, out=blend)
            np.clip(blend, -1.0, 1.0, out=blend)
            np.multiply(blend, self._i0, out=blend)
            np.multiply(torque, self._inv_a, out=amps)
            np.add(amps, blend, out=amps)  # A: tau / a + I0 clip(tau / ramp, -1, 1)
            np.multiply(amps, self._lsb_per_ampere, out=amps)
            np.rint(amps, out=amps)
            np.clip(amps, self._neg_limit, self._limit, out=amps)
            self._goal[:] = amps
        else:
            self._goal[:] = 0  # a NaN or infinite command: zero current, and report it
        frame = self._write_frame
        length = frame.encode()
        if not port.write(frame.view, length, t0 + self.timeout_s):
            return self._fail(PORT, -1)
        if not finite:
            return self._fail(NON_FINITE, -1)
        if self._torque_pending and self._goal.any():
            return self._torque_on()
        return True

    def _torque_on(self) -> bool:
        """Start-up step 9 at the first nonzero command, its Goal Current already written: two
        transactions, one SYNC_WRITE of Torque Enable 1 to every motor, then one SYNC_READ of
        Torque Enable confirming each (asked again, up to ``retries`` times in all, only while a
        reply is missing or corrupted: a reply lost on the wire). A motor that does not answer,
        answers with an error or its alert, or reads back anything but 1 is a refusal: a failed
        write, and every read after it fails (``not-enabled``), so the loop stops safely within
        its read watchdog instead of running a controller on unpowered motors.

        (It was one confirmed WRITE per motor: six round trips, 2.3 ms idle and 5-8 ms under
        load, during which the first Goal Current was held on the motors already powered.)"""
        self._torque_pending = False
        port, parser, slot_of = self._port, self._parser, self._slot_of
        what, timeout = self._torque_on_what, self._setup_timeout()
        frame = self._torque_on_frame
        if not port.write(memoryview(frame), len(frame), time.perf_counter() + timeout):
            return self._refuse_torque(-1, f"the serial port {self.port_path} failed during "
                                           f"{what}")
        # Per motor: None (no reply yet), "crc" (only corrupted ones), or (error, parameters).
        got: list = [None] * self.nq
        frame, tries = self._torque_check_frame, 0
        while tries < self.retries and any(g is None or g == "crc" for g in got):
            tries += 1
            port.discard_input()
            parser.reset()
            deadline = time.perf_counter() + timeout
            if not port.write(memoryview(frame), len(frame), deadline):
                return self._refuse_torque(-1, f"the serial port {self.port_path} failed "
                                               f"during {what}")
            pending = sum(1 for g in got if g is None or g == "crc")
            while pending:
                code = self._next_packet(port, deadline)
                if code == _PORT_FAILED:
                    return self._refuse_torque(-1, f"the serial port {self.port_path} failed "
                                                   f"during {what}")
                if code == _TIMED_OUT:
                    break
                j = slot_of[parser.id]
                if code == proto.OK and j >= 0 and (got[j] is None or got[j] == "crc"):
                    got[j] = (parser.error, parser.params())
                    pending -= 1
                elif code == proto.CRC_FAILURE and j >= 0 and got[j] is None:
                    got[j] = "crc"
                    pending -= 1
                elif time.perf_counter() >= deadline:
                    break  # a flood of packets nobody asked for ends at the deadline too
        problems, first = [], -1
        for d, g, size in zip(self.drives, got, self._torque_sizes):
            who = self._who(d)
            if g is None:
                problem = (f"{who} did not answer {what} on {self.port_path} at {self.baud} "
                           f"baud ({tries} tries): check its power, cable, ID and baud rate")
            elif g == "crc":
                problem = (f"{who} answered {what} with corrupted packets (CRC) {tries} times: "
                           "check the cable and the baud rate")
            elif g[0] & ALERT_BIT:
                problem = (f"{who} reports a hardware error ({self._hardware_error_text(d)}): "
                           "remove the cause and reboot the motor (power cycle) before a run")
            elif g[0] & 0x7F:
                problem = f"{who} refused {what}: {describe_error(g[0])}"
            elif len(g[1]) != size or proto.from_le(g[1], False) != 1:
                value = proto.from_le(g[1], False) if len(g[1]) == size else f"{len(g[1])} bytes"
                problem = (f"{who} reads Torque Enable {value} after {what}: the write did not "
                           "take (check the motor's Hardware Error Status and Bus Watchdog)")
            else:
                continue
            problems.append(problem)
            first = d.id if first < 0 else first
        if problems:
            return self._refuse_torque(first, "; ".join(problems))
        return True

    def _refuse_torque(self, motor_id: int, why: str) -> bool:
        """The torque did not come on: this write fails, and every read after it
        (``not-enabled``, naming ``motor_id``; -1 when the port failed)."""
        self.torque_on_error, self._torque_failed_id = why, motor_id
        return self._fail(NOT_ENABLED, motor_id)

    # ---- start-up and shut-down -----------------------------------------------------------------

    def _who(self, d: JointDrive) -> str:
        return f"ID {d.id} ({d.name}, {d.spec.name})"

    def _transact(self, frame: bytes, motor_id: int, timeout: float, tries: int):
        """Send a unicast instruction and wait for its status packet: ``(result, error,
        params)`` with ``result`` one of ``"ok"``, ``"timeout"``, ``"crc"``, ``"port"``."""
        port, parser = self._port, self._parser
        result = "timeout"
        view = memoryview(frame)
        for _ in range(tries):
            deadline = time.perf_counter() + timeout
            port.discard_input()
            parser.reset()
            if not port.write(view, len(frame), deadline):
                return "port", 0, b""
            while True:
                code = parser.parse()
                if code == proto.OK:
                    if parser.id == motor_id:
                        return "ok", parser.error, parser.params()
                    continue
                if code == proto.CRC_FAILURE:
                    result = "crc"
                    continue
                if code != proto.NEED_MORE:
                    continue
                got = port.read_into(parser.space(), deadline)
                if got < 0:
                    return "port", 0, b""
                if got == 0:
                    break
                parser.commit(got)
        return result, 0, b""

    def _setup_timeout(self) -> float:
        return max(0.02, 4 * self.timeout_s)

    # ---- confirmed instructions outside the periods (the start-up and the shut-down) ----------

    def command(self, d: JointDrive, what: str, frame: bytes) -> bytes:
        """One instruction to motor ``d``, retried, its status checked; the reply's parameters.
        Raises :class:`BackendError` naming the motor and what to check."""
        result, error, params = self._transact(frame, d.id, self._setup_timeout(), self.retries)
        if result == "timeout":
            raise BackendError(f"{self._who(d)} did not answer {what} on {self.port_path} at "
                               f"{self.baud} baud ({self.retries} tries): check its power, "
                               "cable, ID and baud rate")
        if result == "crc":
            raise BackendError(f"{self._who(d)} answered {what} with corrupted packets (CRC) "
                               f"{self.retries} times: check the cable and the baud rate")
        if result == "port":
            raise BackendError(f"the serial port {self.port_path} failed during {what}")
        if error & ALERT_BIT:
            raise BackendError(f"{self._who(d)} reports a hardware error "
                               f"({self._hardware_error_text(d)}): remove the cause and reboot "
                               "the motor (power cycle) before a run")
        if error & 0x7F:
            raise BackendError(f"{self._who(d)} refused {what}: {describe_error(error)}")
        return params

    def _hardware_error_text(self, d: JointDrive) -> str:
        frame, size = self._alert_frames[d.id]
        result, _, params = self._transact(frame, d.id, self._setup_timeout(), 1)
        if result != "ok" or len(params) != size:
            return "Hardware Error Status unreadable"
        return describe_hardware_error(proto.from_le(params, False))

    def _startup(self) -> None:
        n = self.nq
        # 1. PING: every motor there, of the model the description names.
        problems = []
        for d in self.drives:
            try:
                params = self.command(d, "PING", proto.ping(d.id))
            except BackendError as exc:
                problems.append(str(exc))
                continue
            number = proto.from_le(params[0:2], False) if len(params) >= 2 else -1
            if len(params) >= 3:
                self.firmware[d.id] = params[2]
            if number != d.spec.number:
                other = MODELS_BY_NUMBER.get(number)
                problems.append(f"{self._who(d)} is model number {number}"
                                f"{f' ({other.name})' if other else ''}, not the "
                                f"{d.spec.name}'s {d.spec.number}: check the IDs and the "
                                "description")
        if problems:
            raise BackendError("; ".join(problems))
        self._check_homing()
        # 2.-7. Configure, torque off: each step on every motor before the next.
        for step in self._setup_writes:
            for d, what, frame in step:
                self.command(d, what, frame)
        self._keep_homing_marker()
        # 8. The first good read; the joints within their limits.
        x = np.zeros(2 * n)
        self._active = True  # the read path checks it
        try:
            for _ in range(3 * self.retries):
                if self.read(x):
                    break
            else:
                hint = ("; a firmware that does not answer FAST_SYNC_READ (the data give no "
                        "first version): cochlea-run --read-instruction sync reads with "
                        "SYNC_READ" if self.read_instruction == "fast" else "")
                raise BackendError(f"no good {_READ_NAMES[self.read_instruction]} of the "
                                   f"motors' state on {self.port_path} "
                                   f"in {3 * self.retries} tries (last failure: "
                                   f"{self.describe_last_failure()}){hint}")
        finally:
            self._active = False
        self._unwrap_and_check(x[:n])
        # 9. Torque on: with the first nonzero command (_sync_write), after its Goal Current.
        self._torque_pending, self.torque_on_error = True, None

    # ---- the slider's homing (issue 15) -------------------------------------------------------

    def _check_homing(self) -> None:
        """A joint whose encoder loses its turns at power-on (every prismatic joint: the
        parallel robot's slider, a user arm's carriages) needs a homing record of this power
        cycle (:mod:`cochlea.dynamixel.bringup.home`), made for this description and holding
        an entry per such joint; each joint is then counted from the stop its homing found,
        valid while its motor holds its marker. Without one, or with any entry invalid, the
        start-up is refused in one line naming ``cochlea-dxl home``. The serial robot has no
        such joint."""
        self._homing_markers = []
        sliders = [j for j, d in enumerate(self.drives) if d.type == "prismatic"]
        if not sliders:
            return
        socket_port = is_socket_address(self.port_path)  # only the emulator listens on one
        virtual = socket_port or os.path.realpath(self.port_path).startswith("/dev/pts/")
        if self.homing == "off" or (self.homing == "auto" and virtual):
            self.homing_report = ("not checked (" + (
                "homing off" if self.homing == "off" else
                "a socket: the virtual chain" if socket_port else
                "a pseudo-terminal: the virtual chain") + ")")
            return
        path = Path(self.homing_record) if self.homing_record is not None \
            else homing.default_record(self.robot, self.description)
        record = homing.load_record(path, self.robot, self.description)
        entries = homing.check_record(record, path, self.robot, self.description,
                                      [self.drives[j] for j in sliders])
        offsets = []
        for j, entry in zip(sliders, entries):
            d = self.drives[j]
            it = homing.marker_item(d)
            params = self.command(d, "READ the homing marker", proto.read(d.id, it.address, 2))
            marker = proto.from_le(params, False) if len(params) == 2 else -1
            offsets.append((j, homing.reference_offset(entry, record, path, d, marker)))
            self._homing_markers.append((d, marker))
        for j, offset in offsets:  # all or none: every entry valid before any offset is used
            self._q_offset[j] = offset
        self.homing_report = f"homed {record.get('date') or ''} ({path})"

    def _keep_homing_marker(self) -> None:
        """Write the homing token back after the configuration: should a firmware reset its
        gains on the Operating Mode write (the same value), the next start-up in this power
        cycle still finds it. The turns themselves survive a write of current control."""
        for d, marker in self._homing_markers:
            self.command(d, "restore the homing marker",
                          proto.write(d.id, homing.marker_item(d).address,
                                      proto.le(marker, 2)))

    def _unwrap_and_check(self, q: np.ndarray) -> None:
        """A revolute joint's absolute encoder is single-turn after power-up: take the turn that
        puts it nearest the middle of its limits, then refuse joints outside their limits."""
        problems = []
        for j, d in enumerate(self.drives):
            lo, hi = d.position_limits
            if d.type == "revolute":
                turns = round(((lo + hi) / 2 - q[j]) / (2 * math.pi))
                self._q_offset[j] += 2 * math.pi * turns
                q[j] += 2 * math.pi * turns
            if not lo - self.position_margin <= q[j] <= hi + self.position_margin:
                if d.type == "revolute":
                    where = (f"{math.degrees(q[j]):.1f} deg, outside its limits "
                             f"[{math.degrees(lo):g}, {math.degrees(hi):g}] deg")
                else:
                    where = f"{q[j]:.4f} m, outside its limits [{lo:g}, {hi:g}] m"
                problems.append(f"{d.name} (ID {d.id}) reads {where}")
        if problems:
            raise BackendError("; ".join(problems) + ": check zero_offset_deg and direction in "
                               "the description, or move the joint by hand with the power off")
        self._check_start(q)

    def _check_start(self, q: np.ndarray) -> None:
        """The run's controller and its desired path start from the scenario's initial pose:
        a robot standing elsewhere would meet an initial error the study never had (a jump
        towards the path at the gains' full authority, maybe through the keep-out region), so
        a joint farther from it than the tolerance is refused before the torque comes on."""
        if self.expected_start is None:
            return
        problems = []
        for j, d in enumerate(self.drives):
            revolute = d.type == "revolute"
            tolerance = self.start_tolerance[0 if revolute else 1]
            if abs(q[j] - self.expected_start[j]) <= tolerance:
                continue
            if revolute:
                problems.append(f"{d.name} (ID {d.id}) is at {math.degrees(q[j]):.1f} deg, "
                                f"the scenario starts it at "
                                f"{math.degrees(self.expected_start[j]):.1f} deg")
            else:
                problems.append(f"{d.name} (ID {d.id}) is at {q[j] * 1e3:.1f} mm, the "
                                f"scenario starts it at {self.expected_start[j] * 1e3:.1f} mm")
        if problems:
            rad, m = self.start_tolerance
            raise BackendError(
                "the robot is not at the scenario's initial pose: " + "; ".join(problems)
                + f" (tolerance {math.degrees(rad):g} deg, {m * 1e3:g} mm): move the joints "
                "there by hand with the power off, or run a scenario whose initial state is "
                "where the robot stands (--start-tolerance-deg, --start-tolerance-mm widen it)")

    def _shutdown(self, port: SerialPort) -> str:
        deadline = time.perf_counter() + 0.05
        for frame in (self._zero_frame, self._torque_off_frame) * 2:
            port.write(memoryview(frame), len(frame), deadline)
        self._port = port  # for the confirming reads only
        try:
            unconfirmed = []
            for d, (frame, off) in zip(self.drives, self._torque_off_checks):
                result, error, params = self._transact(frame, d.id, max(0.01, self.timeout_s), 2)
                if result != "ok" or params != off:
                    unconfirmed.append(d)
                elif error & ALERT_BIT:
                    self.alert_ids.add(d.id)
            alerts = [self.drives[self._slot_of[i]] for i in sorted(self.alert_ids)]
            notes = [f"{self._who(d)}: hardware error ({self._hardware_error_text(d)})"
                     for d in alerts]
        finally:
            self._port = None
        if unconfirmed:
            who = ", ".join(self._who(d) for d in unconfirmed)
            text = (f"goal current 0 and torque off sent; not confirmed by {who} (its Bus "
                    f"Watchdog, {self.watchdog_lsb * WATCHDOG_UNIT_S * 1e3:.0f} ms, stops it)")
        else:
            text = f"goal current 0 and torque off sent; torque off confirmed by all {self.nq}"
        return "; ".join([text] + notes)
