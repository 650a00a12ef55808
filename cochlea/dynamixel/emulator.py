"""``cochlea-emulator``: a virtual Dynamixel chain on a pseudo-terminal, driven by the plant model.

The motors of a scenario's robot description answer Protocol 2.0 on a pseudo-terminal (PING,
READ, WRITE, REBOOT, SYNC_READ, SYNC_WRITE, BULK_READ, BULK_WRITE and FAST_SYNC_READ where the
model supports it; other instructions get an Instruction Error) with
the control tables of :mod:`cochlea.dynamixel.control_table`: EEPROM items locked while the
torque is on, range and limit checks, Goal Current reset to the Current Limit when the
Operating Mode changes, the Bus Watchdog, the hardware alert bit, Status Return Level.

The joints move in real time under the scenario's plant (the same parameters, friction and
initial state as the simulation): every ``plant_period_s`` (default the simulation's RK4 step,
the scenario's period over its ``plant_substeps``; a request sees the state at its arrival) one
RK4 step integrates the joint efforts that the motors' currents give. On a plant that models
the gearbox's friction (the realistic preset's Coulomb friction, which is the fit's offset) the
current gives the motor's own torque ``a I`` and the plant loses the friction, as on the
motors: a bridge that added the offset current for a controller that compensates friction too
would push each joint with twice its friction. A plant without dry friction has nothing to take
the offset, so there the motors undo the bridge's map for the scenario's controller
(:class:`cochlea.dynamixel.drives.Fit`'s inverse when the bridge adds the offset, ``a I`` when
it leaves it to the controller: :func:`cochlea.robots.motor_fit.bridge_compensates_friction`)
and the plant receives the effort commanded, up to the current's quantisation. A
motor that is not driving (torque off, not
in current control, a hardware error, a tripped watchdog) holds its joint: the gearbox of a
200:1 servo does not back-drive. Present Position, Velocity and Current follow the plant.

Optionally the wire's timing (``wire_timing``): an instruction occupies the bus for its bytes at
the configured baud rate (10 bits each), each motor then waits its Return Delay Time and sends
its status packet, which takes its bytes' time too; replies are written to the pseudo-terminal
when their last byte would have arrived (slept for with a 1 ns timer slack, the last
``WIRE_SPIN_S`` waited on the clock, so that a reply is not late by the sleep's own slack).

Faults (:class:`Faults`), all counted from the first Torque Enable 1 (the start of a run) plus
``delay_s``: dropped replies, corrupted CRCs, late replies (each with a probability, on the
motors ``ids`` or all), a hardware error on one motor (alert bit, torque off), a motor that
stops answering, a motor that repeats a stale status packet (its last reply before the fault,
Realtime Tick and all, for a number of reads or for good); and, from the start, motors missing
from the bus or reporting another model number. The Realtime Tick counts the milliseconds
since the chain started, modulo 32768.

Each motor answers as its model (its data, ``cochlea/dynamixel/models``): its Model Number and
firmware, its control table's addresses, sizes, defaults and limits, its units (counts per
turn, velocity and current units), its EEPROM area (the layout's ``ram_from``), and the
per-period block (Realtime Tick .. Present Position) at its model's addresses: 120..135 on the
X series, 568..583 on the P series. An X-series arm with a P-series joint is one chain.

For the bring-up tools (``cochlea-dxl``, see "Bring-up emulation" below): optionally each motor
hears only instructions sent at the baud rate of its own Baud Rate register (``--check-baud``),
as real motors do (read from the pseudo-terminal's line settings), and a register may ignore
the writes it acknowledges (``--ignore-write ID:ADDRESS``), as a write that did not take.

Everything the motors do is recorded in ``events`` (and ``--log FILE``): each item written (by
WRITE or SYNC_WRITE), each read, ping and reboot, each refused instruction, each fault and
watchdog trip, with its time.

A period's requests (SYNC_WRITE of Goal Current, SYNC_READ) are applied in C when the library
``build/libcochlea-lane.so`` is there (:mod:`cochlea.dynamixel.lane`): the same replies,
tables and events as the Python path below, which takes everything else.

The command (``main``) runs under SCHED_FIFO when permitted and with the garbage collector off
while serving, as the real-time loop does: a virtual device should answer as promptly as a real
one, whatever else the machine runs.

With ``listen`` (``--listen unix:PATH`` or ``socket://HOST:PORT``) the chain serves on a stream
socket instead of the pseudo-terminal: the same bytes, wire timing and faults, one bridge at a
time (one that disconnects leaves the chain listening for the next). The kernel moves a
pseudo-terminal's bytes in worker threads of ordinary priority, which a loaded machine delays
whatever the two ends' SCHED_FIFO; a socket's are delivered in the writer's own system call
(docs/dynamixel.md, "The emulator's socket").
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import dataclasses
import fcntl
import gc
import heapq
import math
import os
import random
import select
import signal
import socket
import struct
import sys
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..console import STOP_SIGNALS, OneLineParser, tolerate_closed_stdout
from ..errors import EXIT_USER_ERROR, CochleaError
from ..kernels import library as ckernels
from ..kernels.naming import source_hash
from ..robots import ROBOTS
from ..robots.description import MAX_FIT, MIN_FIT_SLOPE
from ..robots.motor_fit import bridge_compensates_friction
from ..sim import load_scenario, unit_setups
from ..sim.scenario import PLANT_PRESETS
from ..text import number_argument, strict_float, strict_int, whole_argument
from . import lane as c_lane
from . import protocol as proto
from .control_table import (
    ACCESS,
    ALERT_BIT,
    BAUD_RATES,
    BROADCAST_ID,
    BULK_READ,
    BULK_WRITE,
    CRC_ERROR,
    CURRENT_MODE,
    DATA_LENGTH,
    DATA_LIMIT,
    DATA_RANGE,
    FAST_SYNC_READ,
    HARDWARE_ERROR_BITS,
    INSTRUCTION_ERROR,
    INSTRUCTION_NAMES,
    PING,
    READ,
    REBOOT,
    RESULT_FAIL,
    RETURN_DELAY_UNIT_S,
    SYNC_READ,
    SYNC_WRITE,
    WATCHDOG_UNIT_S,
    WRITE,
    Item,
    baud_code,
)
from .drives import DEFAULT_RAMP_NM, Fit, JointDrive, joint_drives
from .drives import check_baud as check_model_baud
from .port import UNIX_PREFIX, socket_address

#: The command's real-time priority: below cochlea-run's loop (40), above normal processes.
EMULATOR_FIFO_PRIORITY = 30

#: The plant's RK4 step in real time, seconds. Below 50 us the steps of even the smallest plant
#: (about 15 us each) would take most of the processor; above 50 ms a request would see a state
#: a whole step old and the skip-ahead of a late host (50 ms) would drop every step.
PLANT_PERIOD_RANGE_S = (5e-5, 5e-2)
#: The share of the wall time the plant may take: a plant that cannot keep up with real time
#: (a tiny step, a slow machine) skips ahead instead of spinning, so the emulator never takes
#: the whole processor (under SCHED_FIFO that would starve the machine) and always hears its
#: signals and its --duration.
MAX_PLANT_DUTY = 0.8
#: How long before a status packet is due the emulator stops sleeping and waits on the clock,
#: seconds: a sleep here ends about 20 us late (median, 1 ns timer slack; 75 us with the
#: default 50 us slack), which the transaction of a wire-timed read took on top of its wire time.
#: Costs at most this much processor time per reply, and only with wire timing (without it a
#: reply is due at once).
WIRE_SPIN_S = 50e-6
#: The longest --late-ms: a reply later than this is a lost one (--drop-replies).
MAX_LATE_S = 10.0
#: Exit code of the command when its --log could not be written (a full disk, a lost device).
EXIT_LOG_FAILED = 3

_PRESENT = struct.Struct("<hii")  # Present Current, Velocity, Position (126 on the X series)
_TICK = struct.Struct("<H")  # Realtime Tick (120 on the X series)
_INT32 = (-(2**31), 2**31 - 1)


@dataclass
class Faults:
    """What goes wrong, and when (seconds after the first Torque Enable 1, plus ``delay_s``)."""

    drop: float = 0.0  # probability that a status packet is not sent
    crc: float = 0.0  # probability that a status packet's CRC is corrupted
    late: float = 0.0  # probability that a status packet comes late_s late
    late_s: float = 0.005
    ids: frozenset[int] | None = None  # the motors drop/crc/late hit (None: all)
    hardware_error: tuple[int, int] | None = None  # (id, bit of Hardware Error Status)
    silent: int | None = None  # the ID of a motor that stops answering
    missing: frozenset[int] = frozenset()  # IDs not on the bus at all
    model_number: dict[int, int] = field(default_factory=dict)  # ID -> reported model number
    delay_s: float = 0.0
    seed: int = 0
    # (ID, reads): the motor answers its next ``reads`` reads (-1: all) with the data of its
    # last reply before the fault, a stale packet (the Realtime Tick does not move).
    stale: tuple[int, int] | None = None
    # The stale packets answer the motor's unicast READs too (the bring-up tools'), not only
    # its part of a SYNC_READ (the runtime's).
    stale_unicast: bool = False


def check_faults(faults: Faults, ids: list[int]) -> None:
    """Refuse fault settings that are not numbers in range or name motors that are not on the
    chain (``ids``), with the option that sets each (a fault on no motor would silently test
    nothing)."""
    for option, value in (("--drop-replies", faults.drop), ("--corrupt-crc", faults.crc),
                          ("--late-replies", faults.late)):
        if not 0.0 <= value <= 1.0:  # NaN fails too
            raise CochleaError(f"{option}: expected a probability in [0, 1], got {value}")
    if not 0.0 <= faults.late_s <= MAX_LATE_S:
        raise CochleaError(f"--late-ms: expected 0 to {MAX_LATE_S * 1e3:g} ms, got "
                           f"{faults.late_s * 1e3:g}")
    if not 0.0 <= faults.delay_s < math.inf:
        raise CochleaError(f"--fault-delay: expected a finite number of seconds >= 0, got "
                           f"{faults.delay_s}")
    chain = ", ".join(str(i) for i in ids)
    named = [("--fault-ids", i) for i in sorted(faults.ids or ())]
    named += [("--missing-motor", i) for i in sorted(faults.missing)]
    named += [("--model-number", i) for i in sorted(faults.model_number)]
    if faults.hardware_error is not None:
        named.append(("--hardware-error", faults.hardware_error[0]))
        if faults.hardware_error[1] not in HARDWARE_ERROR_BITS:
            raise CochleaError("--hardware-error: BIT must be one of " + ", ".join(
                f"{b} ({n})" for b, n in HARDWARE_ERROR_BITS.items()))
    if faults.silent is not None:
        named.append(("--silent-motor", faults.silent))
    if faults.stale is not None:
        named.append(("--stale-replies", faults.stale[0]))
        if faults.stale[1] == 0 or faults.stale[1] < -1:
            raise CochleaError(f"--stale-replies {faults.stale[0]}:{faults.stale[1]}: expected "
                               "a number of reads >= 1 (or none: every read from the fault on)")
    if faults.stale_unicast and faults.stale is None:
        raise CochleaError("--stale-unicast: expected --stale-replies ID[:N] too (it names the "
                           "motor)")
    for option, motor_id in named:
        if motor_id not in ids:
            raise CochleaError(f"{option}: motor ID {motor_id} is not on this chain (its motors "
                               f"are {chain})")
    if faults.ids is not None and not faults.ids:
        raise CochleaError(f"--fault-ids: expected at least one motor ID of {chain}")
    for motor_id, number in faults.model_number.items():
        if not 0 <= number <= 0xFFFF:
            raise CochleaError(f"--model-number {motor_id}:{number}: expected a model number "
                               "0..65535 (two bytes)")


def _open_log(path: Path):
    try:
        return open(path, "w", encoding="utf-8")  # noqa: SIM115 (closed by close())
    except OSError as exc:
        raise CochleaError(f"--log {path}: cannot write it ({exc.strerror or exc}); expected a "
                           "file in a writable folder") from None


class VirtualMotor:
    """One motor: its control table and what it does with an instruction."""

    #: Whole turns (in counts) the encoder lost at the last power cycle (see power_cycle).
    turn_counts = 0

    def __init__(self, drive: JointDrive, baud_code: int, model_number: int | None = None):
        self.drive = drive
        self.spec = drive.spec
        self.items = {it.address: it for it in self.spec.items}
        a = self.address = {it.name: it.address for it in self.spec.items}
        missing = [n for n in self.NEEDED if n not in a]
        if missing:
            raise CochleaError(f"the {self.spec.name} (ID {drive.id}) cannot be emulated: its "
                               f"control table has no {', '.join(missing)} item")
        present = (a["Present Current"], a["Present Velocity"], a["Present Position"])
        if present != (present[0], present[0] + 2, present[0] + 6) or \
                a["Realtime Tick"] + 6 != present[0]:
            raise CochleaError(f"the {self.spec.name}'s Realtime Tick and Present Current, "
                               f"Velocity, Position are not one block in the X series' order")
        # The registers every instruction and every plant step look at, at this model's
        # addresses (X series: 64, 70, 98, 102, 68, 126, 120).
        self.a_torque, self.a_mode = a["Torque Enable"], a["Operating Mode"]
        self.a_error, self.a_watchdog = a["Hardware Error Status"], a["Bus Watchdog"]
        self.a_goal_current, self.a_limit = a["Goal Current"], a["Current Limit"]
        self.a_level, self.a_present, self.a_tick = (a["Status Return Level"], present[0],
                                                     a["Realtime Tick"])
        # Goal values (address) and the limit (address) that bounds each; a goal the model's
        # table does not list is left out.
        self.goal_limits = {a[g]: a[lim] for g, lim in self.GOAL_LIMIT_NAMES
                            if g in a and lim in a}
        self.goals = frozenset(a[g] for g in self.GOAL_NAMES if g in a)
        self.ram_from = self.spec.ram_from
        self.table = bytearray(self.spec.table_size)
        self.answering = True
        self.last_contact = 0.0
        for it in self.spec.items:
            self._put(it, it.default)
        self._put(self.items[0], self.spec.number if model_number is None else model_number)
        self._put(self.items[6], self.spec.firmware)
        self._put(self.items[7], drive.id)
        self._put(self.items[8], baud_code)
        self.defaults = bytes(self.table)
        self.on_torque = None  # callback(motor) when the torque goes on
        self.ignored: frozenset[int] = frozenset()  # addresses whose writes do not take
        self._key: tuple = ()
        self._state = (False, 0, 0.0)
        self._slope_only = False
        #: The motor's torque over what its fit says (``1 + [plant] torque_constant_error``).
        self.torque_scale = 1.0

    # ---- registers -----------------------------------------------------------------------------

    #: The items the emulator needs of every model.
    NEEDED = ("Model Number", "Firmware Version", "ID", "Baud Rate", "Return Delay Time",
              "Operating Mode", "Current Limit", "Torque Enable", "Status Return Level",
              "Hardware Error Status", "Bus Watchdog", "Goal Current", "Realtime Tick",
              "Present Current", "Present Velocity", "Present Position")
    GOAL_NAMES = ("Goal PWM", "Goal Current", "Goal Velocity", "Goal Position")
    GOAL_LIMIT_NAMES = (("Goal PWM", "PWM Limit"), ("Goal Current", "Current Limit"),
                        ("Goal Velocity", "Velocity Limit"))

    def _put(self, item: Item, value: int) -> None:
        self.table[item.address:item.address + item.size] = proto.le(value, item.size)

    def get(self, address: int) -> int:
        it = self.items[address]
        return proto.from_le(self.table[address:address + it.size], it.signed)

    @property
    def id(self) -> int:
        return self.table[7]

    @property
    def torque_on(self) -> bool:
        return self.table[self.a_torque] == 1

    @property
    def hardware_error(self) -> int:
        return self.table[self.a_error]

    @property
    def watchdog_tripped(self) -> bool:
        return self.table[self.a_watchdog] == 0xFF  # -1

    def state(self) -> tuple[bool, int, float]:
        """``(driving, applied current (LSB), joint effort it gives)``, recomputed only when one
        of the registers it depends on changed (the plant asks at every step)."""
        t, g = self.table, self.a_goal_current
        key = (t[self.a_torque], t[self.a_mode], t[self.a_error], t[self.a_watchdog], t[g],
               t[g + 1])
        if key != self._key:
            driving = (key[0] == 1 and key[1] == CURRENT_MODE and not key[2]
                       and key[3] != 0xFF)
            current = proto.from_le(t[g:g + 2], True) if driving else 0
            effort = self.torque_scale * float(self.drive.effort(current, self.slope_only))
            self._key, self._state = key, (driving, current, effort)
        return self._state

    @property
    def slope_only(self) -> bool:
        """The current gives the motor's own torque ``a I`` (a plant that models the gearbox's
        friction, or a bridge that adds no offset current); otherwise the fit's torque, the
        offset current taken off (see the module docstring)."""
        return self._slope_only

    @slope_only.setter
    def slope_only(self, value: bool) -> None:
        self._slope_only = bool(value)
        self._key = ()  # the effort cached by state() came from the other rule

    @property
    def driving(self) -> bool:
        return self.state()[0]

    @property
    def applied_current(self) -> int:
        return self.state()[1]

    @property
    def return_delay_s(self) -> float:
        return self.table[9] * RETURN_DELAY_UNIT_S

    def set_present(self, current: int, velocity: int, position: int, tick_ms: int) -> None:
        _PRESENT.pack_into(self.table, self.a_present, current, velocity, position)
        _TICK.pack_into(self.table, self.a_tick, tick_ms % 32768)

    def latch_hardware_error(self, bit: int) -> None:
        self.table[self.a_error] |= 1 << bit
        self.table[self.a_torque] = 0  # Shutdown: torque off, output 0

    def trip_watchdog(self) -> None:
        self.table[self.a_watchdog] = 0xFF  # -1: Bus Watchdog Error
        self._put(self.items[self.a_goal_current], 0)

    def reboot(self) -> None:
        """RAM (from the model's ``ram_from``) back to its defaults (torque off, errors
        cleared); EEPROM kept."""
        lo, hi = self.a_tick, self.a_present + 10
        present = bytes(self.table[lo:hi])
        self.table[self.ram_from:] = self.defaults[self.ram_from:]
        self._put(self.items[self.a_goal_current], self.get(self.a_limit))
        self.table[lo:hi] = present

    # ---- instructions --------------------------------------------------------------------------

    def read(self, address: int, length: int) -> tuple[int, bytes]:
        if length < 1 or address + length > len(self.table):
            return ACCESS, b""
        return 0, bytes(self.table[address:address + length])

    def write(self, address: int, data: bytes) -> tuple[int, list[tuple[int, int]]]:
        """Write whole items, all or nothing: ``(error, [(address, value) written])``."""
        if not data:
            return DATA_LENGTH, []
        it = self.items.get(address)
        if it is not None and len(data) == it.size:
            # One whole item (a period's Goal Current): the loop below without its plan.
            if not it.writable or (it.eeprom and self.torque_on):
                return ACCESS, []
            value = int.from_bytes(data, "little", signed=it.signed)
            error = self._check(it, value)
            if error:
                return error, []
            if address not in self.ignored:
                self._apply(it, value)
            return 0, [(address, value)]
        plan = []
        p, end = address, address + len(data)
        while p < end:
            it = self.items.get(p)
            if it is None:
                return ACCESS, []
            if p + it.size > end:
                return DATA_LENGTH, []
            if not it.writable or (it.eeprom and self.torque_on):
                return ACCESS, []
            value = proto.from_le(data[p - address:p - address + it.size], it.signed)
            error = self._check(it, value)
            if error:
                return error, []
            plan.append((it, value))
            p += it.size
        for it, value in plan:
            if it.address not in self.ignored:
                self._apply(it, value)
        return 0, [(it.address, value) for it, value in plan]

    def _check(self, it: Item, value: int) -> int:
        a = it.address
        if not it.lo <= value <= it.hi:
            return DATA_RANGE
        if it.values is not None and value not in it.values:
            return DATA_RANGE  # e.g. an Operating Mode the model does not have (P: no 5)
        if a in self.goals and self.watchdog_tripped:
            return DATA_RANGE  # goal values are read-only after a watchdog error
        if a in self.goal_limits and abs(value) > self.get(self.goal_limits[a]):
            return DATA_LIMIT
        if a == self.a_torque and value == 1 and self.hardware_error:
            return RESULT_FAIL  # only a REBOOT re-enables the torque after a shutdown
        return 0

    def _apply(self, it: Item, value: int) -> None:
        a = it.address
        before = self.get(a) if a in (self.a_mode, self.a_torque) else None
        self._put(it, value)
        if a == self.a_mode and value != before:
            # Goal PWM = PWM Limit, Goal Current = Current Limit, the profiles 0 (those the
            # model's table lists).
            for goal, limit in (("Goal PWM", "PWM Limit"), ("Goal Current", "Current Limit")):
                if goal in self.address and limit in self.address:
                    self._put(self.items[self.address[goal]], self.get(self.address[limit]))
            for name in ("Profile Acceleration", "Profile Velocity"):
                if name in self.address:
                    self._put(self.items[self.address[name]], 0)
        if a == self.a_torque and value == 1 and before == 0 and self.on_torque:
            self.on_torque(self)


#: prctl(2)'s PR_SET_TIMERSLACK (Linux): how late the kernel may end a sleep to batch wake-ups.
_PR_SET_TIMERSLACK = 29


def precise_timers() -> bool:
    """Ask the kernel to end this thread's sleeps on time (a timer slack of 1 ns instead of the
    default 50 us, Linux): a status packet due at its wire time is then written within a few
    microseconds of it, not 50 to 100 us late. A thread under SCHED_FIFO (the command's) has no
    slack anyway. False where refused or not Linux (the sleeps are then as before)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _bind_plant(step, arguments: list[np.ndarray], result: np.ndarray):
    """``(call, source, owner)``: a call running ``step`` on ``arguments`` into ``result``.

    The generated C kernel of the same Function when the library has it (same source hash):
    the geared parallel plant costs about 260 us per step in CasADi's virtual machine, and a
    request, a write and the 1 ms tick each take a step, so a busy machine left the chain's
    replies later than the bridge's read timeout (CI: six timeouts in a row). Else CasADi's
    own buffers (about 10 us instead of 60 us with numpy arguments for the small plants).
    ``owner`` holds what the call points into: keep it as long as the call."""
    name = step.name()
    try:
        lib = ckernels.load()
        if name in lib.manifest["kernels"] and lib.source_hash(name) == source_hash(step):
            # A kernel's 1x1 argument is a 0-d buffer: the same memory, viewed so.
            kernel = lib.kernel(name, **{step.name_in(i): a.reshape(()) if a.size == 1 else a
                                         for i, a in enumerate(arguments)},
                                **{step.name_out(0): result})
            return kernel.call, "c", kernel
    except CochleaError:
        pass
    buffer, call = step.buffer()
    for i, a in enumerate(arguments):
        buffer.set_arg(i, memoryview(a))
    buffer.set_res(0, memoryview(result))
    return call, "casadi", buffer


class _Unit:
    """One plant (an arm, or the parallel mechanism) and its motors."""

    #: ``(joint index, lowest coordinate)`` of each hard stop (see ``--hard-stop-m``).
    stops: tuple[tuple[int, float], ...] = ()

    def __init__(self, setup, substeps: int, h: float, motors: list[VirtualMotor]):
        self.name = setup.name
        self.motors = motors
        self.n = n = len(motors)
        # The plant's state: [q, qd], with the gearbox [q, qd, theta, theta_dot] (the encoder
        # on the link: q and qd are what the motors report).
        self.x = np.asarray(setup.plant_x0, float).copy()
        self.gearbox = setup.gearbox
        # The plant step (x, tau, p, friction, h[, drive]) -> x_next.
        step = setup.plant_function(substeps)
        self._x, self._tau = np.zeros(len(self.x)), np.zeros(n)
        self._next = np.zeros(len(self.x))
        arguments = [self._x, self._tau, np.asarray(setup.plant_params, float).copy(),
                     np.asarray(setup.friction, float).copy(), np.array([h])]
        if setup.drive is not None:  # dry friction (the gearboxes stick and slip), the gear
            arguments.append(np.asarray(setup.drive, float).copy())
        self._arguments = arguments  # the buffers point into these arrays: keep them alive
        self._h = arguments[4]
        self._held = [True] * n
        self._scales = [(float(m.drive.q_offset), float(m.drive.q_per_count),
                         float(m.drive.qd_per_lsb))
                        for m in motors]
        self._call, self.plant_source, self._plant_owner = _bind_plant(step, arguments,
                                                                       self._next)
        # The same step from _next back into _x: several steps called back and forth between
        # the two buffers, without a copy or Python's per-step work (see advance_many).
        self._call_back, _, self._plant_owner_back = _bind_plant(
            step, [self._next, *arguments[1:]], self._x)

    def batchable(self) -> bool:
        """Whether :meth:`advance_many` may take this unit's steps: every motor drives (no
        joint held) and no hard stop is set."""
        return not self.stops and all(m.state()[0] for m in self.motors)

    def advance_many(self, h: float, k: int) -> bool:
        """``k`` steps of ``h`` seconds at once, the same arithmetic as ``k`` calls of
        :meth:`advance`, for a :meth:`batchable` unit. The steps alternate between two
        buffers: with the geared plant's 50 us sub-steps a request 0.5 ms after the last took
        ten steps per unit, and Python's work on each (currents, copies, held joints, finite
        check) cost more than the plant itself. False if the plant went non-finite: the state
        is then kept as it was before the k steps (its speeds zeroed, as advance does)."""
        tau = self._tau
        for j, m in enumerate(self.motors):
            tau[j] = m.state()[2]
        self._h[0] = h
        self._x[:] = self.x
        forth, back = self._call, self._call_back
        for i in range(k):
            if i % 2:
                back()
            else:
                forth()
        return self._accept(self._next if k % 2 else self._x)

    def _accept(self, nxt: np.ndarray) -> bool:
        """``nxt`` becomes the state if finite; else the state stays, its speeds zeroed (the
        link's and, with the gearbox, the rotor's), and False."""
        x, n = self.x, self.n
        if not math.isfinite(sum(nxt.tolist())):  # numpy's sum costs 5x more at this size
            x[n:2 * n] = 0.0
            x[3 * n:] = 0.0
            return False
        x[:] = nxt
        return True

    def advance(self, h: float) -> bool:
        """One RK4 step of ``h`` seconds; False if the plant went non-finite (state kept)."""
        n, x, tau = self.n, self.x, self._tau
        held = self._held
        moving = False
        for j, m in enumerate(self.motors):
            driving, _, effort = m.state()
            held[j] = not driving
            tau[j] = effort
            moving = moving or driving
        if not moving:
            x[n:2 * n] = 0.0
            x[3 * n:] = 0.0  # the rotors' speeds, with the gearbox
            return True
        self._h[0] = h
        self._x[:] = x
        self._call()
        nxt = self._next
        for j in range(n):
            if held[j]:
                nxt[j] = x[j]
                nxt[n + j] = 0.0
                if self.gearbox:
                    nxt[2 * n + j] = x[2 * n + j]
                    nxt[3 * n + j] = 0.0
        if not self._accept(nxt):
            return False
        if self.stops:
            _hold_at_stops(self)
        return True

    def publish(self, tick_ms: int, currents: list[int] | None = None) -> None:
        """Present Current, Velocity and Position of each motor from the plant's state;
        ``currents``: each motor's applied current to report (default: its present one)."""
        n = self.n
        x = self.x[:2 * n].tolist()  # Python floats: numpy scalars cost ~10x in this loop
        lo, hi = _INT32
        for j, (m, (offset, per_count, per_lsb)) in enumerate(zip(self.motors, self._scales)):
            pos = min(max(round((x[j] - offset) / per_count) - m.turn_counts, lo), hi)
            vel = min(max(round(x[n + j] / per_lsb), lo), hi)
            m.set_present(m.state()[1] if currents is None else currents[j], vel, pos, tick_ms)


#: The instructions that read a control table (the others may write one, or do nothing).
_READS = frozenset((PING, READ, SYNC_READ, FAST_SYNC_READ, BULK_READ))

#: How many in-process chains are serving (:meth:`VirtualChain.start`): the host's objects
#: stay frozen (``gc.freeze``) while any is, and are handed back to the collector after the last.
_serving = [0]
_serving_lock = threading.Lock()


def serving_chains() -> int:
    """How many in-process chains serve now (started and not stopped)."""
    with _serving_lock:
        return _serving[0]


def _freeze_host_objects() -> None:
    with _serving_lock:
        if _serving[0] == 0:
            gc.freeze()
        _serving[0] += 1


def _thaw_host_objects() -> None:
    with _serving_lock:
        _serving[0] -= 1
        if _serving[0] == 0:
            gc.unfreeze()


def default_scenario(robot: str, plant: str | None) -> str:
    """The command's scenario without ``--scenario``: the realistic joint-space study, whose
    plant is what the motors have (rotors, gearbox friction, counts), so that a controller
    tried over the virtual chain meets the motors' dynamics, not the rigid links'; the thesis's
    study (rigid links) with ``--plant ideal``."""
    return f"{robot}_joint" if plant == "ideal" else f"{robot}_joint_realistic"


class VirtualChain:
    """The motors of a scenario's robot on a pseudo-terminal, or with ``listen`` on a socket
    (see the module docstring).

    Use :meth:`start` (a background thread) and :meth:`stop`, or :meth:`serve` in the
    foreground; :attr:`path` is the pseudo-terminal to open (the socket's address).
    """

    #: Which motors answer FAST_SYNC_READ (0x8A): None, as their model's data says
    #: (``fast_sync_read`` true; unsourced or false: an Instruction Error); True or False, every
    #: motor or none (a firmware the data does not describe: set on the chain before start()).
    fast_sync_read: bool | None = None

    def __init__(self, robot: str, scenario: str | Path | None = None, *,
                 baud: int = 4_000_000, wire_timing: bool = False, faults: Faults | None = None,
                 plant_period_s: float | None = None, log_path: str | Path | None = None,
                 max_events: int = 200_000, plant: str | None = None,
                 check_baud: bool = False, ignore_writes=(),
                 truth: Truth | None = None, listen: str | None = None):
        code = baud_code(baud)
        # listen: serve on a socket (unix:PATH, socket://HOST:PORT) instead of a
        # pseudo-terminal; None, the pseudo-terminal.
        self.listen = listen
        if listen is not None:
            try:
                socket_address(listen, listening=True)
            except ValueError as exc:
                raise CochleaError(f"--listen {exc}") from None
            if check_baud:
                raise CochleaError("--check-baud needs the pseudo-terminal (a socket has no "
                                   "baud rate to check): drop --listen or --check-baud")
        # plant: a preset of the scenario's [plant] table, e.g. "realistic": the motors' rotors
        # and gearbox friction move the joints (their counts are the motors' own already).
        self.scenario = load_scenario(scenario or f"{robot}_joint", plant_preset=plant)
        if self.scenario.robot != robot:
            raise CochleaError(f"scenario {self.scenario.path} is for the {self.scenario.robot} "
                               f"robot, not {robot}")
        self.robot = robot
        self.faults = faults or Faults()
        self.drives = true_drives(joint_drives(robot, system=self.scenario.system), truth)
        check_model_baud(self.drives, baud)  # a rate one of the models does not take
        check_faults(self.faults, [d.id for d in self.drives])
        if plant_period_s is not None:
            lo, hi = PLANT_PERIOD_RANGE_S
            if not lo <= plant_period_s <= hi:  # NaN fails too
                raise CochleaError(f"--plant-period-ms: expected {lo * 1e3:g} to {hi * 1e3:g} "
                                   f"ms, got {plant_period_s * 1e3:g}")
        self.motors = [VirtualMotor(d, code, self.faults.model_number.get(d.id))
                       for d in self.drives]
        for m in self.motors:
            m.on_torque = self._on_torque
            m.answering = m.id not in self.faults.missing
        self._index()
        self._bringup_options(check_baud, ignore_writes)
        setups = unit_setups(self.scenario)
        if plant_period_s is None:  # the simulation's RK4 step, one per plant period
            plant_period_s = self.scenario.period / self.scenario.plant_substeps
        self.units, start = [], 0
        for s in setups:
            n = s.plant_model.nq
            slope_only = s.coulomb is not None or not bridge_compensates_friction(
                self.scenario.controller_actuators)
            for j, m in enumerate(self.motors[start:start + n]):
                if s.torque_scale is not None:  # the plant's torque-constant error
                    m.torque_scale = float(s.torque_scale[j])
                m.slope_only = slope_only  # last: its setter drops the cached effort
            self.units.append(_Unit(s, 1, plant_period_s, self.motors[start:start + n]))
            start += n
        if start != len(self.motors):
            raise CochleaError(f"the scenario's plant has {start} joints, its description "
                               f"{len(self.motors)} motors")
        install_stops(self.units, truth)
        #: Where the plant's step runs: the generated C kernels, or CasADi (no library built,
        #: or one generated from another description).
        self.plant_source = ("the C kernels" if all(u.plant_source == "c" for u in self.units)
                             else "CasADi")
        self.baud = baud
        self.byte_time = 10.0 / baud if wire_timing else 0.0
        self.wire_timing = wire_timing
        self.h = plant_period_s
        self._rng = random.Random(self.faults.seed)
        self._event_log: deque = deque(maxlen=max_events)  # read through .events
        self.log_path = None if log_path is None else Path(log_path)
        self.log_error: str | None = None  # why the event log stopped, if it failed
        self.counts = {"instructions": 0, "bad_instructions": 0, "replies": 0, "dropped": 0,
                       "corrupted": 0, "late": 0, "watchdog_trips": 0, "plant_overruns": 0,
                       "plant_steps": 0, "stale": 0}
        self.run_start: float | None = None  # time of the first Torque Enable 1
        self._injected_hw = self._injected_silent = False
        self._stale_left = -1 if self.faults.stale is None else self.faults.stale[1]
        self._stale_last: tuple[int, bytes] | None = None  # (address, data) of the last reply
        self._parser = proto.PacketParser(status=False)
        self._queue: list = []  # (due, seq, bytes)
        self._seq = 0
        self._bus_free = 0.0
        self._t0 = time.perf_counter()
        self._plant_time = self._t0  # the plant is integrated up to this time
        self._next_step = self._t0 + self.h
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        #: Held by the serving thread while it changes the plant or the registers (an update,
        #: a request), and by another thread's reads and hands (joint_state, paused, move_joint,
        #: power_cycle): the plant's state is integrated first and published after, and a read
        #: in between saw a position the registers did not yet show (a CI failure, 18 counts).
        self._state_lock = threading.RLock()
        self._frozen = False  # whether start() froze the host's objects (stop() thaws them)
        self.master = self.slave = -1
        self._listener: socket.socket | None = None  # with listen: the listening socket
        self._client: socket.socket | None = None  # and the connected bridge (self.master)
        self._unix_path: str | None = None  # the socket file this chain made (removed at close)
        self.path = ""
        self._last_tick_end = self._t0
        #: The last measured cost of a whole plant step of every unit (s): it bounds how many
        #: steps _tick takes in one go. Unknown at first: the first steps go one by one.
        self._step_cost = math.inf
        # A request's own update publishes the registers only when an instruction reads them
        # (see _tick): the tick it was made at, and the applied currents before any write
        # that came first in the same data.
        self._unpublished: int | None = None
        self._unpublished_currents: list[int] | None = None
        self._publish(0)
        # Last, once everything else was accepted: a refused chain leaves no file behind.
        self._log = _open_log(self.log_path) if self.log_path is not None else None

    # ---- set-up --------------------------------------------------------------------------------

    def _index(self) -> None:
        self.by_id = {m.id: m for m in self.motors}
        # A broadcast's motors in ID order, sorted once per ID change, not once per request.
        self._by_id_order = sorted(self.motors, key=lambda m: m.id)
        # The C lane's motor index by ID too (None: no library, or motors it cannot serve).
        self._lane = c_lane.lane_for(self.motors, self.by_id)

    def open(self) -> str:
        """The port's name for the bridge's ``--port``: the pseudo-terminal's path, or with
        ``listen`` the socket's address (``socket://HOST:0`` gives the port chosen). OSError
        when it cannot be opened (bound)."""
        if self.listen is not None:
            if self._listener is None:
                self._open_socket()
            return self.path
        if self.master < 0:
            self.master, self.slave = os.openpty()
            tty.setraw(self.slave)  # no echo, no line editing: bytes as they are
            os.set_blocking(self.master, False)
            self.path = os.ttyname(self.slave)
        return self.path

    def _open_socket(self) -> None:
        """Listen on ``self.listen``: one bridge at a time is served (as one host owns a
        serial line); a bridge that disconnects leaves the chain listening for the next, its
        motors running on as motors whose host went away."""
        family, address = socket_address(self.listen, listening=True)
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            if family != socket.AF_UNIX:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(address)
            sock.listen(1)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._listener = sock
        if family == socket.AF_UNIX:
            self._unix_path = address
            self.path = UNIX_PREFIX + address
        else:
            host, port = sock.getsockname()[:2]
            self.path = f"socket://{f'[{host}]' if ':' in host else host}:{port}"

    def _accept(self) -> None:
        """A bridge connects: it becomes the line (``self.master``)."""
        try:
            client, _ = self._listener.accept()
        except OSError:  # it went away again, or a transient failure: keep listening
            return
        client.setblocking(False)
        if client.family != socket.AF_UNIX:
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client, self.master = client, client.fileno()

    def _disconnect(self) -> None:
        """The bridge closed its end: what it had not read yet, and any half-received
        instruction, go with it; the chain listens for the next."""
        client, self._client, self.master = self._client, None, -1
        if client is not None:
            client.close()
        self._queue.clear()
        self._parser = proto.PacketParser(status=False)

    def start(self) -> VirtualChain:
        """Serve from a thread of this process (a test's, a benchmark's). The objects alive
        here are frozen out of the collector's way until :meth:`stop`: a full collection
        triggered by the chain's own allocations scans the whole host process, and in a long
        pytest session that pause (tens to hundreds of milliseconds) outlasts a bridge's
        start-up retries (seen once: a PH42's homing marker unanswered three times in 20 ms).
        A chain already serving goes on as it is (one thread serves it, one freeze is held)."""
        if self._thread is not None and self._thread.is_alive():
            return self
        self.open()
        self._stop.clear()
        if not self._frozen:
            _freeze_host_objects()
            self._frozen = True
        self._thread = threading.Thread(target=self.serve, name="cochlea-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._frozen:
            self._frozen = False
            _thaw_host_objects()

    def close(self) -> None:
        self.stop()
        if self._client is not None:
            self._disconnect()
        for fd in (self.master, self.slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = -1
        if self._listener is not None:
            self._listener.close()
            self._listener = None
            if self._unix_path is not None:
                try:
                    os.unlink(self._unix_path)
                except OSError:
                    pass
                self._unix_path = None
        if self._log:
            log, self._log = self._log, None
            try:
                log.close()
            except OSError as exc:
                self._log_failed(exc)

    def __enter__(self) -> VirtualChain:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- state for tests and reports ---------------------------------------------------------

    def joint_state(self) -> np.ndarray:
        """``[q, qd]`` of all joints (SI), in the bridge's order: of one update, whole."""
        with self._state_lock:
            q = np.concatenate([u.x[:u.n] for u in self.units])
            qd = np.concatenate([u.x[u.n:2 * u.n] for u in self.units])
        return np.concatenate([q, qd])

    @contextlib.contextmanager
    def paused(self):
        """The serving thread held between two updates: the plant's state and the registers
        read inside agree (a request's update not yet published is published first, as the
        next read would). Keep it short: the chain answers nothing meanwhile."""
        with self._state_lock:
            if self._unpublished is not None:
                self._publish(self._unpublished, self._unpublished_currents)
            yield self

    @property
    def events(self) -> list[tuple]:
        """``(t, kind, id, address, value)`` of what the chain did, oldest first (the last
        ``max_events``): a copy taken at once, so another thread may go through it while the
        chain serves (the deque itself raised "mutated during iteration" under a test's
        comprehension when a request or a watchdog added an event meanwhile)."""
        return list(self._event_log)  # one C call: no event is added halfway

    def writes(self, kinds=("write", "sync-write")) -> list[tuple]:
        """``(id, address, value)`` of every item written, in order."""
        return [(e[2], e[3], e[4]) for e in self.events if e[1] in kinds]

    def _event(self, now: float, kind: str, motor_id: int, address: int = -1,
               value: object = None) -> None:
        t = now - self._t0
        self._event_log.append((t, kind, motor_id, address, value))
        if self._log:
            try:
                self._log.write(f"{t:.6f} {kind} id={motor_id} address={address} "
                                f"value={value}\n")
            except OSError as exc:
                self._log_failed(exc)

    def _events(self, now: float, items) -> None:
        """Several events at ``now``: ``(kind, motor_id, address, value)`` each, as
        :meth:`_event` records them, the log's lines in one write."""
        t = now - self._t0
        self._event_log.extend([(t, *e) for e in items])
        if self._log:
            try:
                self._log.write("".join([f"{t:.6f} {kind} id={motor_id} address={address} "
                                         f"value={value}\n"
                                         for kind, motor_id, address, value in items]))
            except OSError as exc:
                self._log_failed(exc)

    def _log_failed(self, exc: OSError) -> None:
        """The event log cannot be written (a full disk): stop serving, as a recorder that lost
        its record should; the motors go silent and the bridge on the other end stops safely."""
        self.log_error = f"writing the event log {self.log_path} failed: {exc.strerror or exc}"
        log, self._log = self._log, None
        if log is not None:
            try:
                log.close()
            except OSError:
                pass  # the buffered rest cannot be written either
        self._stop.set()
    # ---- the loop ------------------------------------------------------------------------------

    def serve(self, duration: float | None = None) -> None:
        self.open()
        precise_timers()
        end = None if duration is None else time.perf_counter() + duration
        while not self._stop.is_set():
            now = time.perf_counter()
            if end is not None and now >= end:
                break
            due = self._queue[0][0] if self._queue else math.inf
            wake = min(self._next_step, due, now + 0.05)
            # A status packet due: sleep until shortly before, then wait on the clock (a sleep
            # ends some 20 us late even with precise timers; see WIRE_SPIN_S).
            spin = due <= wake and due - now < 0.01
            # With listen and no bridge connected: wait for one (the plant runs on meanwhile).
            waiting = self.master < 0 and self._listener is not None
            try:
                ready, _, _ = select.select([self._listener if waiting else self.master], [],
                                            [], max(0.0, wake - now - (WIRE_SPIN_S if spin
                                                                       else 0)))
            except (OSError, ValueError):
                break
            if spin and not ready:
                while time.perf_counter() < due:
                    time.sleep(0)  # lets another thread (a test's bridge) have the GIL
            if ready and waiting:
                self._accept()
            elif ready:
                with self._state_lock:
                    self._receive()  # integrates the plant up to the request's arrival itself
                self._flush(time.perf_counter())
                now = time.perf_counter()
                if now < self._next_step and not (self._queue and self._queue[0][0] <= now):
                    # Nothing due: the next request, or the next 1 ms update, integrates on.
                    # (A tick here cost a plant step, the publication and the watchdog's
                    # check per request, for no reader.)
                    continue
            # A status packet due goes out first: the plant's update (a step, the publication,
            # the watchdogs) used to run before it, and made every reply that much later than
            # its wire time. The update runs when it is due, not for a reply.
            now = time.perf_counter()
            self._flush(now)
            if now >= self._next_step:
                with self._state_lock:
                    self._tick(now)
                self._flush(time.perf_counter())
        if self._log:
            try:
                self._log.flush()
            except OSError as exc:
                self._log_failed(exc)

    def _receive(self) -> None:
        try:
            data = os.read(self.master, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # nobody has the pseudo-terminal's other end open; a socket reset
            if self._client is not None:
                self._disconnect()
            return
        if not data:  # readable and empty: the bridge closed its socket
            if self._client is not None:
                self._disconnect()
            return
        self._received(data, time.perf_counter())

    def _received(self, data: bytes, now: float) -> None:
        """The bytes of one read from the line, arrived at ``now``."""
        self._read_line_baud()
        # The state a request sees is the state at its arrival (one sub-step).
        self._tick(now, publish=False)
        if self._lane is not None and self._parser.pending == 0 and self._lane_open():
            self._lane.refresh()  # before the scan: which motors a write reaches counts there
            packets = self._lane.scan(data)
            if packets:  # the period's requests, whole: in C (see lane.py)
                self._lane_serve(now, packets)
                return
        offset = 0
        while offset < len(data):
            offset += self._parser.feed(data[offset:])
            while True:
                code = self._parser.parse()
                if code == proto.NEED_MORE:
                    break
                if code == proto.OK:
                    self._instruction(now)
                elif code == proto.CRC_FAILURE:
                    self.counts["bad_instructions"] += 1
                    m = self.by_id.get(self._parser.id)
                    if m is not None and m.answering and self._hears(m):
                        self._event(now, "crc-error", m.id)
                        self._reply(now, self._parser.frame_len, [(m, CRC_ERROR, b"")], -1)
                else:
                    self.counts["bad_instructions"] += 1

    def _lane_open(self) -> bool:
        """Whether the C lane may serve: nothing it does not model (faults on the replies,
        stale packets, baud checks, writes that do not take; a hardware error, a silent motor
        and a tripped watchdog it does model)."""
        f = self.faults
        return not (self.check_baud or f.stale is not None or f.drop or f.crc or f.late
                    or any(m.ignored for m in self.motors))

    def _lane_serve(self, now: float, packets) -> None:
        """The requests :meth:`Lane.scan` took, applied in C: what :meth:`_instruction` and
        :meth:`_reply` do with a SYNC_WRITE of Goal Current and a SYNC_READ, the same events,
        contacts, counts and replies at the same times. Without wire timing a read's replies
        are all due at once: they are queued as one entry (:meth:`_flush` joins the entries
        due together anyway: the same bytes in the same write)."""
        lane = self._lane
        motors, queue, byte_time = lane.motors, self._queue, self.byte_time
        counts = self.counts
        for inst, frame_len, k in packets:
            counts["instructions"] += 1
            if self._unpublished is not None:
                self._publish_pending(inst == SYNC_READ)
            t = max(now, self._bus_free) + frame_len * byte_time
            actions, out = lane.execute(k)
            events = []
            first = last = -1  # the replies' bytes in out
            for j in range(0, len(actions), 4):
                kind, m = actions[j], motors[actions[j + 1]]  # (a READ's motor: -1, unused)
                if kind == c_lane.REPLY:
                    m.last_contact = now
                    offset, length = actions[j + 2], actions[j + 3]
                    if self.wire_timing:
                        t += m.return_delay_s  # two sums, as _reply adds them
                        t += length * byte_time
                        self._seq += 1
                        heapq.heappush(queue, (t, self._seq, bytes(out[offset:offset + length])))
                    else:
                        first = offset if first < 0 else first
                        last = offset + length
                    counts["replies"] += 1
                elif kind == c_lane.WRITTEN:
                    m.last_contact = now
                    events.append(("sync-write", m.table[7], m.a_goal_current, actions[j + 2]))
                elif kind == c_lane.REFUSED:
                    m.last_contact = now
                    events.append(("refused", m.table[7], m.a_goal_current,
                                   f"sync-write: error {actions[j + 2]}"))
                elif kind == c_lane.READ:
                    events.append(("sync-read", BROADCAST_ID, actions[j + 2], actions[j + 3]))
                elif kind == c_lane.CONTACT:  # a read it heard and does not answer (level 0)
                    m.last_contact = now
            if first >= 0:
                self._seq += 1
                heapq.heappush(queue, (t, self._seq, bytes(out[first:last])))
            if events:
                self._events(now, events)
            self._bus_free = t

    def _publish(self, tick_ms: int, currents: list[int] | None = None) -> None:
        """Every motor's present registers from the plant's state (``currents``: the applied
        currents to report, all motors in order; default: each one's present one)."""
        self._unpublished = self._unpublished_currents = None
        first = 0
        for u in self.units:
            u.publish(tick_ms, None if currents is None else currents[first:first + u.n])
            first += u.n

    def _publish_pending(self, reads: bool) -> None:
        """Before an instruction, when a request's update has not published the registers:
        publish them if the instruction reads (``reads``), else keep the applied currents
        it may change (the state the update saw), once."""
        if reads:
            self._publish(self._unpublished, self._unpublished_currents)
        elif self._unpublished_currents is None:
            self._unpublished_currents = [m.state()[1] for u in self.units for m in u.motors]

    def _tick(self, now: float, publish: bool = True) -> None:
        """Integrate the plant up to ``now`` (steps of at most ``h``, the last one partial), so
        a request sees the state at its arrival and a new current acts from its arrival.
        ``publish=False`` (a request's own update): the registers are published when an
        instruction reads them (:meth:`_publish_pending`); a write does not need them, and
        publishing took about a sixth of the chain's work on a period's two requests."""
        self._faults(now)
        if now - self._plant_time > 0.05:  # 50 ms behind (the host was busy): skip ahead
            self.counts["plant_overruns"] += 1
            self._plant_time = now - self.h
        started = time.perf_counter()
        budget = MAX_PLANT_DUTY * max(started - self._last_tick_end, 0.0)
        steps = 0
        while now - self._plant_time > 1e-6:
            if steps and time.perf_counter() - started > budget:
                # The plant cannot keep up with real time: skip ahead, count it, and let the
                # loop sleep (see MAX_PLANT_DUTY) rather than spin.
                self.counts["plant_overruns"] += 1
                self._plant_time = now
                break
            whole = int((now - self._plant_time) / self.h)
            if whole >= 2:
                # No more of them than the plant's budget has room for, at the last measured
                # cost of a step: a step dearer than real time allows must still fall behind
                # (the budget above), never spin.
                room = budget - (time.perf_counter() - started)
                whole = min(whole, int(room / max(self._step_cost, 1e-9))) if room > 0 else 0
            if whole >= 2 and all(u.batchable() for u in self.units):
                # Several whole steps, every unit driven: each unit takes them in one go.
                batch = time.perf_counter()
                for u in self.units:
                    if not u.advance_many(self.h, whole):
                        self._plant_failed(u, now)
                for _ in range(whole):  # as the steps one by one add them
                    self._plant_time += self.h
                steps += whole
                self.counts["plant_steps"] += whole
                self._step_cost = (time.perf_counter() - batch) / whole
                continue
            steps += 1
            h = min(self.h, now - self._plant_time)
            step = time.perf_counter()
            for u in self.units:
                if not u.advance(h):
                    self._plant_failed(u, now)
            self.counts["plant_steps"] += 1
            self._plant_time += h
            self._step_cost = time.perf_counter() - step
        # Requests integrate up to their arrival themselves: between them, 1 ms is enough.
        self._next_step = self._plant_time + max(self.h, 1e-3)
        self._last_tick_end = time.perf_counter()
        tick_ms = int((now - self._t0) * 1000)
        if publish:
            self._publish(tick_ms)
        else:
            self._unpublished, self._unpublished_currents = tick_ms, None
        for m in self.motors:
            wd = m.table[m.a_watchdog]  # 0 off, 1..127 on, 0xFF (-1) tripped
            if 0 < wd < 0x80 and m.torque_on and now - m.last_contact > wd * WATCHDOG_UNIT_S:
                m.trip_watchdog()
                self.counts["watchdog_trips"] += 1
                self._event(now, "watchdog", m.id, m.a_watchdog, -1)

    def _plant_failed(self, u: _Unit, now: float) -> None:
        """A unit's plant went non-finite: its motors shut down with an overload error."""
        for m in u.motors:
            m.latch_hardware_error(5)
        self._event(now, "fault", -1, -1, f"{u.name}: plant not finite, overload")

    def _active(self, now: float) -> bool:
        return self.run_start is not None and now >= self.run_start + self.faults.delay_s

    def _faults(self, now: float) -> None:
        f = self.faults
        if not self._active(now):
            return
        if f.hardware_error and not self._injected_hw:
            self._injected_hw = True
            motor_id, bit = f.hardware_error
            m = self.by_id.get(motor_id)
            if m is not None:
                m.latch_hardware_error(bit)
                self._event(now, "fault", motor_id, m.a_error,
                            f"hardware error: {HARDWARE_ERROR_BITS.get(bit, bit)}")
        if f.silent is not None and not self._injected_silent:
            self._injected_silent = True
            m = self.by_id.get(f.silent)
            if m is not None:
                m.answering = False
                self._event(now, "fault", f.silent, -1, "stops answering")

    def _on_torque(self, motor: VirtualMotor) -> None:
        if self.run_start is None:
            self.run_start = time.perf_counter()

    def _flush(self, now: float) -> None:
        """Write every status packet due by ``now``, in their order, with one system call: a
        pseudo-terminal write costs tens of microseconds (more on a loaded machine, and each
        one queues the kernel's work to pass the bytes on), and a SYNC_READ's six replies used
        to take six. The bytes and their order on the wire are the same."""
        queue = self._queue
        if not queue or queue[0][0] > now:
            return
        packet = heapq.heappop(queue)[2]
        if queue and queue[0][0] <= now:
            due = [packet]
            while queue and queue[0][0] <= now:
                due.append(heapq.heappop(queue)[2])
            packet = b"".join(due)
        try:
            written = os.write(self.master, packet)
            if written < len(packet):  # the rest once more; a reader whose buffer stays
                os.write(self.master, packet[written:])  # full loses it, as before
        except OSError:
            pass

    # ---- instructions --------------------------------------------------------------------------

    def _contact(self, m: VirtualMotor, now: float) -> bool:
        if not m.answering or not self._hears(m):
            return False
        m.last_contact = now
        return True

    def _instruction(self, now: float) -> None:
        p = self._parser
        pid, inst, params = p.id, p.instruction, p.params()
        self.counts["instructions"] += 1
        if self._unpublished is not None:
            self._publish_pending(inst in _READS)
        replies = []
        broadcast = pid == BROADCAST_ID
        if broadcast:
            targets = self._by_id_order
        else:
            m = self.by_id.get(pid)
            targets = () if m is None else (m,)
        if inst == PING:
            for m in targets:
                if self._contact(m, now):
                    self._event(now, "ping", m.id)
                    replies.append((m, 0, bytes(m.table[0:2]) + bytes(m.table[6:7])))
        elif inst == READ and not broadcast:
            for m in targets:
                if self._contact(m, now):
                    if len(params) != 4:
                        replies.append((m, DATA_LENGTH, b""))
                        continue
                    address, length = proto.from_le(params[0:2], False), \
                        proto.from_le(params[2:4], False)
                    error, data = m.read(address, length)
                    self._event(now, "read", m.id, address, length)
                    if self.faults.stale_unicast and not error:
                        data = self._stale_reply(m, now, address, data)
                    replies.append((m, error, data))
        elif inst == WRITE:
            for m in targets:
                if self._contact(m, now):
                    error = self._write(m, proto.from_le(params[0:2], False), params[2:], now,
                                        "write") if len(params) > 2 else DATA_LENGTH
                    if not broadcast:
                        replies.append((m, error, b""))
        elif inst == REBOOT:
            for m in targets:
                if self._contact(m, now):
                    m.reboot()
                    self._event(now, "reboot", m.id)
                    if not broadcast:
                        replies.append((m, 0, b""))
        elif inst == SYNC_READ and broadcast and len(params) >= 4:
            address, length = proto.from_le(params[0:2], False), proto.from_le(params[2:4], False)
            self._event(now, "sync-read", BROADCAST_ID, address, length)
            for motor_id in params[4:]:
                m = self.by_id.get(motor_id)
                if m is not None and self._contact(m, now):
                    error, data = m.read(address, length)
                    replies.append((m, error, self._stale_reply(m, now, address, data)))
        elif inst == FAST_SYNC_READ and broadcast and len(params) >= 4:
            self._fast_sync_read(now, params, p.frame_len)
            return
        elif inst == BULK_READ and broadcast and len(params) >= 5 and len(params) % 5 == 0:
            self._event(now, "bulk-read", BROADCAST_ID)
            for k in range(0, len(params), 5):
                m = self.by_id.get(params[k])
                if m is not None and self._contact(m, now):
                    address = proto.from_le(params[k + 1:k + 3], False)
                    length = proto.from_le(params[k + 3:k + 5], False)
                    error, data = m.read(address, length)
                    replies.append((m, error, self._stale_reply(m, now, address, data)))
        elif inst == BULK_WRITE and broadcast and len(params) >= 5:
            k = 0
            while k + 5 <= len(params):
                length = proto.from_le(params[k + 3:k + 5], False)
                if k + 5 + length > len(params):
                    break  # a truncated entry: the rest is not applied
                m = self.by_id.get(params[k])
                if m is not None and self._contact(m, now):
                    self._write(m, proto.from_le(params[k + 1:k + 3], False),
                                params[k + 5:k + 5 + length], now, "bulk-write")
                k += 5 + length
        elif inst == SYNC_WRITE and broadcast and len(params) >= 4:
            address, length = proto.from_le(params[0:2], False), proto.from_le(params[2:4], False)
            chunk = 1 + length
            for k in range(4, len(params) - chunk + 1, chunk):
                m = self.by_id.get(params[k])
                if m is not None and self._contact(m, now):
                    self._write(m, address, params[k + 1:k + chunk], now, "sync-write")
        elif not broadcast:
            for m in targets:
                if self._contact(m, now):
                    self._event(now, "refused", m.id, -1,
                                f"{INSTRUCTION_NAMES.get(inst, hex(inst))} not emulated")
                    replies.append((m, INSTRUCTION_ERROR, b""))
        self._reply(now, p.frame_len, replies, inst)

    def _answers_fast_sync(self, m: VirtualMotor) -> bool:
        if self.fast_sync_read is not None:
            return bool(self.fast_sync_read)
        return m.spec.fast_sync_read is True

    def _fast_sync_read(self, now: float, params: bytes, request_len: int) -> None:
        """FAST_SYNC_READ (0x8A): the motors listed answer with one combined status packet
        (:func:`cochlea.dynamixel.protocol.fast_sync_status`). A motor whose model (or
        firmware) lacks the instruction answers its own status packet with an Instruction
        Error instead, and the combined packet is not sent (the chain of replies is broken).
        A dropped reply (fault) leaves its block out; a corrupted one flips its CRC bytes
        (the packet's own CRC then fails too, as on a wire)."""
        address, length = proto.from_le(params[0:2], False), proto.from_le(params[2:4], False)
        self._event(now, "fast-sync-read", BROADCAST_ID, address, length)
        listed = [self.by_id.get(i) for i in params[4:]]
        here = [m for m in listed if m is not None and self._contact(m, now)]
        refused = [m for m in here if not self._answers_fast_sync(m)]
        if refused:
            for m in refused:
                self._event(now, "refused", m.id, -1, "FAST_SYNC_READ not supported by the "
                            f"{m.spec.name} (firmware {m.spec.firmware})")
            self._reply(now, request_len, [(m, INSTRUCTION_ERROR, b"") for m in refused],
                        FAST_SYNC_READ)
            return
        f = self.faults
        active = self._active(now)
        blocks, corrupt = [], []
        for m in here:
            if m.table[m.a_level] == 0:  # Status Return Level 0: PING only
                continue
            error, data = m.read(address, length)
            data = self._stale_reply(m, now, address, data)
            if m.hardware_error:
                error |= ALERT_BIT
            hit = active and (f.ids is None or m.id in f.ids)
            if hit and f.drop and self._rng.random() < f.drop:
                self.counts["dropped"] += 1
                self._event(now, "fault", m.id, -1, "reply dropped")
                continue
            if hit and f.crc and self._rng.random() < f.crc:
                corrupt.append(len(blocks))
                self.counts["corrupted"] += 1
                self._event(now, "fault", m.id, -1, "CRC corrupted")
            blocks.append((m.id, error, data))
        if not blocks:
            return
        packet = bytearray(proto.fast_sync_status(blocks))
        for k in corrupt:  # the block's CRC bytes (the last block's is the packet's)
            at = (proto.PREFIX + 1 + (k + 1) * (length + 4) - 2
                  if k < len(blocks) - 1 else len(packet) - 2)
            packet[min(at, len(packet) - 2)] ^= 0xFF
        t = max(now, self._bus_free) + request_len * self.byte_time
        if self.wire_timing:
            t += here[0].return_delay_s
        t += len(packet) * self.byte_time
        self._seq += 1
        heapq.heappush(self._queue, (t, self._seq, bytes(packet)))
        self.counts["replies"] += 1
        self._bus_free = t

    # ---- fault: stale status packets (--stale-replies) ------------------------------------

    def _stale_reply(self, m: VirtualMotor, now: float, address: int, data: bytes) -> bytes:
        """A SYNC_READ's data for motor ``m``: its last reply's again while the stale-packet
        fault lasts (the same block read), else ``data``, remembered for that fault."""
        f = self.faults
        if f.stale is None or m.id != f.stale[0]:
            return data
        last = self._stale_last
        if (not self._active(now) or self._stale_left == 0 or last is None
                or last[0] != address or len(last[1]) != len(data)):
            self._stale_last = (address, data)
            return data
        if self._stale_left > 0:
            self._stale_left -= 1
        self.counts["stale"] += 1
        self._event(now, "fault", m.id, address, "stale reply repeated")
        return last[1]

    def _write(self, m: VirtualMotor, address: int, data: bytes, now: float, kind: str) -> int:
        error, written = m.write(address, data)
        if error:
            self._event(now, "refused", m.id, address, f"{kind}: error {error}")
        for a, value in written:
            self._event(now, "ignored-" + kind if a in m.ignored else kind, m.id, a, value)
            if a == 7:
                self._index()
        return error

    def _reply(self, now: float, request_len: int, replies, inst: int) -> None:
        """Schedule the status packets: after the request's and each other's wire time."""
        f = self.faults
        t = max(now, self._bus_free) + request_len * self.byte_time
        active = self._active(now)
        for m, error, data in replies:
            level = m.table[m.a_level]  # Status Return Level: 0 PING only, 1 + READ, 2 all
            if not (inst == PING or level == 2
                    or (level == 1 and inst in (READ, SYNC_READ, BULK_READ, FAST_SYNC_READ))):
                continue
            if m.hardware_error:
                error |= ALERT_BIT
            packet = proto.status(m.id, error, data)
            hit = active and (f.ids is None or m.id in f.ids)
            if hit and f.drop and self._rng.random() < f.drop:
                self.counts["dropped"] += 1
                self._event(now, "fault", m.id, -1, "reply dropped")
                continue
            if hit and f.crc and self._rng.random() < f.crc:
                packet = packet[:-2] + bytes([packet[-2] ^ 0xFF, packet[-1]])
                self.counts["corrupted"] += 1
                self._event(now, "fault", m.id, -1, "CRC corrupted")
            if self.wire_timing:
                t += m.return_delay_s
            t += len(packet) * self.byte_time
            if hit and f.late and self._rng.random() < f.late:
                t += f.late_s
                self.counts["late"] += 1
                self._event(now, "fault", m.id, -1, f"reply {f.late_s * 1e3:g} ms late")
            self._seq += 1
            heapq.heappush(self._queue, (t, self._seq, packet))
            self.counts["replies"] += 1
        self._bus_free = t


    # ---- Bring-up emulation (issue 15: cochlea-dxl scan, configure, reboot) ------------------

    def _bringup_options(self, check_baud: bool, ignore_writes) -> None:
        """``check_baud``: a motor hears only instructions sent at its Baud Rate register's
        rate (a scan at another rate finds nothing, a baud change takes effect at once).
        ``ignore_writes``: ``(id, address)`` pairs whose writes are acknowledged but do not
        take (a verify pass must catch them)."""
        self.check_baud = bool(check_baud)
        self._line_baud: int | None = None  # the rate the host's port is set to, if known
        chain = ", ".join(str(m.id) for m in self.motors)
        for motor_id, address in ignore_writes:
            m = self.by_id.get(motor_id)
            if m is None:
                raise CochleaError(f"--ignore-write {motor_id}:{address}: motor ID {motor_id} "
                                   f"is not on this chain (its motors are {chain})")
            it = m.items.get(address)
            if it is None or not it.writable:
                raise CochleaError(f"--ignore-write {motor_id}:{address}: expected the address "
                                   f"of a writable item of the {m.spec.name}")
            m.ignored = m.ignored | {address}

    #: TCGETS2 (Linux): the line settings with the rate in bits per second, custom rates too.
    _TCGETS2 = 0x802C542A

    def _read_line_baud(self) -> None:
        if not self.check_baud:
            return
        buf = bytearray(44)  # struct termios2: c_ospeed at offset 40
        try:
            fcntl.ioctl(self.master, self._TCGETS2, buf)
            self._line_baud = int.from_bytes(buf[40:44], "little")
        except OSError:
            self._line_baud = None  # not Linux: every motor hears every rate

    def _hears(self, m: VirtualMotor) -> bool:
        return (not self.check_baud or self._line_baud is None
                or BAUD_RATES.get(m.table[8]) == self._line_baud)

    # ---- bring-up (issue 15): what a hand and the mains switch do ---------------------------

    def move_joint(self, name: str, q: float) -> None:
        """A hand moves joint ``name`` to ``q`` (rad or m, the plant's true coordinate), as
        in a guided calibration with the torque off; its speed is left at zero."""
        with self._state_lock:  # not between a plant step's copy of the state and its result
            self._move_joint(name, q)

    def _move_joint(self, name: str, q: float) -> None:
        for u in self.units:
            for j, m in enumerate(u.motors):
                if m.drive.name == name:
                    u.x[j], u.x[u.n + j] = q, 0.0
                    if u.gearbox:  # the rotor with it, the teeth centred in the backlash
                        u.x[2 * u.n + j], u.x[3 * u.n + j] = q, 0.0
                    return
        raise KeyError(name)

    def power_cycle(self) -> None:
        """The motors' power off and on: RAM items back to their defaults (torque off, errors
        and the Bus Watchdog cleared), and each encoder keeps only its angle within one turn,
        as a real one does (Present Position within one turn again: 0..4095 on the X series,
        its model's counts per turn)."""
        with self._state_lock:
            self._power_cycle()

    def _power_cycle(self) -> None:
        for u in self.units:
            for j, m in enumerate(u.motors):
                offset, per_count, _ = u._scales[j]
                counts = round((u.x[j] - offset) / per_count)
                m.turn_counts = counts - counts % m.spec.counts_per_rev
                m.reboot()
        self._publish(int((time.perf_counter() - self._t0) * 1000))


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def _id_list(text: str) -> frozenset[int]:
    try:
        return frozenset(strict_int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected IDs like 1,2,3, got {text!r}") from None


def _probability(text: str) -> float:
    try:
        value = strict_float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a probability in [0, 1], got {text!r}")
    return value


def _id_bit(text: str) -> tuple[int, int]:
    try:
        motor_id, _, bit = text.partition(":")
        result = (strict_int(motor_id), strict_int(bit) if bit else 5)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID[:BIT], got {text!r}") from None
    if result[1] not in HARDWARE_ERROR_BITS:
        raise argparse.ArgumentTypeError(
            f"BIT must be one of {', '.join(f'{b} ({n})' for b, n in HARDWARE_ERROR_BITS.items())}")
    return result


def _id_count(text: str) -> tuple[int, int]:
    try:
        motor_id, _, count = text.partition(":")
        return strict_int(motor_id), strict_int(count) if count else -1
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID[:N], got {text!r}") from None


def _id_number(text: str) -> tuple[int, int]:
    try:
        motor_id, number = text.split(":")
        return strict_int(motor_id), strict_int(number)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ID:NUMBER, got {text!r}") from None


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="cochlea-emulator",
        description="A virtual Dynamixel chain: the motors of the robot description answer "
                    "Protocol 2.0 on a pseudo-terminal (or a socket: --listen), their joints "
                    "moved in real time by the scenario's plant model. Prints the "
                    "pseudo-terminal's path (the socket's address) on the first line, then runs "
                    "until Ctrl-C (or --duration).",
        epilog="Example: cochlea-emulator --robot serial, then cochlea-run ... --backend "
               "dynamixel --port PATH. Faults start at the first Torque Enable 1 plus "
               "--fault-delay.")
    p.add_argument("--robot", required=True, choices=list(ROBOTS))
    p.add_argument("--scenario", help="the scenario whose description, plant and initial state "
                   "the chain takes (default: ROBOT_joint_realistic, the geared motors; with "
                   "--plant ideal, ROBOT_joint)")
    p.add_argument("--baud", type=whole_argument, default=4_000_000,
                   help="the motors' baud rate, for "
                   "--wire-timing and their Baud Rate register (default 4000000)")
    p.add_argument("--wire-timing", action="store_true", help="bytes take the time the baud "
                   "rate gives them and each motor waits its Return Delay Time")
    p.add_argument("--plant", choices=list(PLANT_PRESETS),
                   help="the plant's preset (default: the scenario's own [plant]): ideal, the "
                        "rigid links; realistic, the geared Dynamixels (armature, friction with "
                        "sticking from the description)")
    p.add_argument("--plant-period-ms", type=number_argument, metavar="MS",
                   help="the plant's RK4 step in real time (default: the scenario's, its "
                        "control period over its plant_substeps)")
    p.add_argument("--duration", type=number_argument, metavar="S", help="stop after S seconds")
    p.add_argument("--listen", metavar="ADDRESS",
                   help="serve on a socket instead of a pseudo-terminal: unix:PATH or "
                        "socket://HOST:PORT (PORT 0: a free one); the first line is then the "
                        "address to give cochlea-run and build/cochlea-embedded as --port. The "
                        "bytes and their wire timing are the same; the kernel delivers them in "
                        "the writer's own system call (a loaded machine delays a "
                        "pseudo-terminal's)")
    p.add_argument("--log", type=Path, metavar="FILE", help="write every event to FILE")
    p.add_argument("--priority", choices=["fifo", "normal"], default="fifo",
                   help="fifo: run under SCHED_FIFO 30 when permitted (below cochlea-run's loop, "
                        "above everything else), as real motors run on their own; normal: a "
                        "plain process (default fifo)")
    f = p.add_argument_group("fault injection")
    f.add_argument("--drop-replies", type=_probability, default=0.0, metavar="P",
                   help="probability that a status packet is not sent")
    f.add_argument("--corrupt-crc", type=_probability, default=0.0, metavar="P",
                   help="probability that a status packet's CRC is wrong")
    f.add_argument("--late-replies", type=_probability, default=0.0, metavar="P",
                   help="probability that a status packet comes --late-ms late")
    f.add_argument("--late-ms", type=number_argument, default=5.0, metavar="MS")
    f.add_argument("--fault-ids", type=_id_list, metavar="IDS",
                   help="the motors the three options above hit, e.g. 1,3 (default: all)")
    f.add_argument("--hardware-error", type=_id_bit, metavar="ID[:BIT]",
                   help="motor ID latches a hardware error (bit of Hardware Error Status, "
                        "default 5 = overload): alert bit set, torque off")
    f.add_argument("--silent-motor", type=whole_argument, metavar="ID",
                   help="motor ID stops answering")
    f.add_argument("--stale-replies", type=_id_count, metavar="ID[:N]",
                   help="motor ID repeats its last status packet before the fault (a stale "
                        "packet: its Realtime Tick does not move) for its next N reads "
                        "(default: every read)")
    f.add_argument("--stale-unicast", action="store_true",
                   help="the stale packets of --stale-replies answer that motor's READs too "
                        "(cochlea-dxl's), not only its part of a SYNC_READ (the runtime's)")
    f.add_argument("--fault-delay", type=number_argument, default=0.0, metavar="S",
                   help="the faults above start S seconds after the first Torque Enable 1")
    f.add_argument("--missing-motor", type=whole_argument, action="append", default=[],
                   metavar="ID",
                   help="motor ID is not on the bus at all (repeatable)")
    f.add_argument("--model-number", type=_id_number, action="append", default=[],
                   metavar="ID:NUMBER", help="motor ID reports another model number")
    f.add_argument("--seed", type=whole_argument, default=0, help="seed of the random faults")
    b = p.add_argument_group("bring-up (cochlea-dxl)")
    b.add_argument("--check-baud", action="store_true",
                   help="a motor hears only instructions sent at the rate of its Baud Rate "
                        "register, as real motors do (default: every rate)")
    b.add_argument("--ignore-write", type=_id_number, action="append", default=[],
                   metavar="ID:ADDRESS", help="motor ID acknowledges writes to the item at "
                   "ADDRESS but keeps its value (a write that did not take; repeatable)")
    add_truth_arguments(p)
    return p


def faults_from_args(args: argparse.Namespace) -> Faults:
    return Faults(drop=args.drop_replies, crc=args.corrupt_crc, late=args.late_replies,
                  late_s=args.late_ms * 1e-3, ids=args.fault_ids,
                  hardware_error=args.hardware_error, silent=args.silent_motor,
                  missing=frozenset(args.missing_motor), model_number=dict(args.model_number),
                  delay_s=args.fault_delay, seed=args.seed, stale=args.stale_replies,
                  stale_unicast=args.stale_unicast)


def check_options(args: argparse.Namespace) -> None:
    """What the parser's types cannot see: the run's duration (the chain checks the rest)."""
    if args.duration is not None and not 0.0 < args.duration < math.inf:
        raise CochleaError(f"--duration: expected a finite number of seconds > 0, got "
                           f"{args.duration} (without --duration the chain runs until Ctrl-C)")


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    # A reader that went away (``| head -1`` took the path) does not stop the motors' service.
    tolerate_closed_stdout()
    try:
        return _main(args)
    except KeyboardInterrupt:  # Ctrl-C while the plant was being built: nothing was served
        print("cochlea-emulator: interrupted before serving", file=sys.stderr)
        return 130


def _main(args: argparse.Namespace) -> int:
    try:
        check_options(args)
        chain = VirtualChain(args.robot, args.scenario or default_scenario(args.robot, args.plant),
                             baud=args.baud,
                             wire_timing=args.wire_timing, faults=faults_from_args(args),
                             plant_period_s=None if args.plant_period_ms is None
                             else args.plant_period_ms * 1e-3, log_path=args.log,
                             max_events=1000,  # the --log file keeps them all
                             plant=args.plant, check_baud=args.check_baud,
                             ignore_writes=args.ignore_write, truth=truth_from_args(args),
                             listen=args.listen)
    except CochleaError as exc:
        print(f"cochlea-emulator: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    priority = "normal"
    if args.priority == "fifo":
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(EMULATOR_FIFO_PRIORITY))
            priority = f"SCHED_FIFO {EMULATOR_FIFO_PRIORITY}"
        except (AttributeError, PermissionError, OSError):
            priority = "normal (SCHED_FIFO not permitted)"

    def stop(signum, frame):  # noqa: ARG001
        chain._stop.set()

    # Before anything is printed: whoever reads the path may signal at once. A hang-up (SIGHUP:
    # the terminal or session that started it closed) stops serving like SIGTERM: the --log is
    # flushed and closed, not lost with the process.
    for signum in STOP_SIGNALS:
        signal.signal(signum, stop)
    try:
        path = chain.open()
    except OSError as exc:
        chain.close()
        if chain.log_path is not None:
            chain.log_path.unlink(missing_ok=True)
        what = "a pseudo-terminal" if args.listen is None else f"--listen {args.listen}"
        print(f"cochlea-emulator: cannot open {what}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    print(path, flush=True)
    ids = ", ".join(f"{m.id} ({m.drive.name}, {m.spec.name})" for m in chain.motors)
    print(f"cochlea-emulator: {args.robot} robot, scenario {chain.scenario.name}, motors {ids}; "
          f"{args.baud} baud, wire timing {'on' if args.wire_timing else 'off'}, {priority}, "
          f"plant on {chain.plant_source}; Ctrl-C stops", flush=True)
    # As in the real-time loop: no collector pauses while serving (what the chain makes per
    # request is freed by reference counting; the set-up's objects are frozen out of the way).
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        chain.serve(args.duration)
    finally:
        chain.close()
        counts = ", ".join(f"{k} {v}" for k, v in chain.counts.items())
        print(f"cochlea-emulator: stopped ({counts})", flush=True)
    if chain.log_error:
        print(f"cochlea-emulator: {chain.log_error}; stopped serving (the bridge on the other "
              "end sees its motors go silent and stops safely): free space, or choose another "
              "--log", file=sys.stderr)
        return EXIT_LOG_FAILED
    return 0


# --------------------------------------------------------------------------------------------
# Bring-up (issue 15): a chain whose motors are mounted otherwise than its description says,
# and the slider's hard stop, so that cochlea-dxl calibrate and home can be tested
# --------------------------------------------------------------------------------------------


@dataclass
class Truth:
    """How the virtual motors are really mounted, where the description only has placeholders:
    ``offset_deg`` (ID -> the motor angle at joint zero, degrees) and ``direction`` (ID -> +1 or
    -1) replace the description's ``zero_offset_deg`` and ``direction`` in the plant's mapping
    (the counts the motors report and the torque their current gives); ``hard_stop_m`` puts a
    hard stop under the prismatic joint (the slider): the plant cannot go below it (an
    inelastic stop) while the motor pushes on at the current it was given. ``fit`` (ID ->
    ``(a, b)`` in the units of the description's fit of that motor, e.g. N cm per A and N cm)
    replaces the description's current-to-torque line in the plant: the torque a current gives
    follows it (same offset rule and ramp), while the bridge still commands through the
    description's, as when a placeholder fit drives a real motor."""

    offset_deg: dict[int, float] = field(default_factory=dict)
    direction: dict[int, int] = field(default_factory=dict)
    hard_stop_m: float | None = None
    fit: dict[int, tuple[float, float]] = field(default_factory=dict)


def true_drives(drives: list[JointDrive], truth: Truth | None) -> list[JointDrive]:
    """The drives as ``truth`` mounts them (refusing IDs that are not on the chain)."""
    if truth is None:
        return drives
    ids = [d.id for d in drives]
    chain = ", ".join(str(i) for i in ids)
    for option, named in (("--true-offset", truth.offset_deg), ("--true-direction",
                                                                truth.direction),
                          ("--true-fit", truth.fit)):
        for motor_id in named:
            if motor_id not in ids:
                raise CochleaError(f"{option}: motor ID {motor_id} is not on this chain (its "
                                   f"motors are {chain})")
    for motor_id, deg in truth.offset_deg.items():
        if not math.isfinite(deg):
            raise CochleaError(f"--true-offset {motor_id}:{deg}: expected a finite angle in deg")
    for motor_id, sign in truth.direction.items():
        if sign not in (1, -1):
            raise CochleaError(f"--true-direction {motor_id}:{sign}: expected +1 or -1")
    out = []
    for d in drives:
        if d.id in truth.offset_deg or d.id in truth.direction:
            d = dataclasses.replace(
                d, zero_offset=math.radians(truth.offset_deg.get(d.id, math.degrees(
                    d.zero_offset))), direction=truth.direction.get(d.id, d.direction))
        if d.id in truth.fit:
            d = dataclasses.replace(d, fit=_true_fit(d, *truth.fit[d.id]))
        out.append(d)
    return out


def _true_fit(d: JointDrive, a: float, b: float) -> Fit:
    """The drive's fit with ``a`` and ``b`` (in its description's units) replaced, checked
    as the description loader checks a fit."""
    shown = f"--true-fit {d.id}:{a:g},{b:g}"
    fit = d.motor.fit
    if not (math.isfinite(a) and MIN_FIT_SLOPE <= a <= MAX_FIT):
        raise CochleaError(f"{shown}: expected a positive slope a in {MIN_FIT_SLOPE:g}.."
                           f"{MAX_FIT:g} ({fit.y} per {fit.x}, the units of motor {d.id}'s "
                           "fit)")
    if not (math.isfinite(b) and abs(b) <= MAX_FIT):
        raise CochleaError(f"{shown}: expected a finite offset b with |b| <= {MAX_FIT:g} "
                           f"({fit.y}, the units of motor {d.id}'s fit)")
    return Fit.from_description(dataclasses.replace(fit, a=a, b=b), DEFAULT_RAMP_NM)


def install_stops(units: list[_Unit], truth: Truth | None) -> None:
    """Put ``truth.hard_stop_m`` under every prismatic joint (one at least, else refused); a
    joint that starts below it starts resting on it."""
    if truth is None or truth.hard_stop_m is None:
        return
    low = truth.hard_stop_m
    if not math.isfinite(low):
        raise CochleaError(f"--hard-stop-m: expected a finite coordinate in m, got {low}")
    found = False
    for u in units:
        stops = tuple((j, low) for j, m in enumerate(u.motors) if m.drive.type == "prismatic")
        for j, _ in stops:
            u.x[j] = max(u.x[j], low)
        u.stops = stops
        found = found or bool(stops)
    if not found:
        raise CochleaError("--hard-stop-m: this robot has no prismatic joint (the parallel "
                           "robot's slider has one)")


def _hold_at_stops(u: _Unit) -> None:
    """A joint that went below its stop during the last step is put back on it, its speed
    down dropped; with the gearbox the rotor goes back by as much. (Put back alone, the link
    left the gear's deflection larger by its overshoot each step: energy from nowhere, which
    the gear's spring gave back by throwing the link up. A slider pushed down at its full force
    bounced up to 5 mm off its stop when the plant took uneven steps, a loaded machine's, and
    homing timed out in CI.)"""
    x, n = u.x, u.n
    for j, low in u.stops:
        below = low - x[j]
        if below > 0:
            x[j] = low
            x[n + j] = max(x[n + j], 0.0)
            if u.gearbox:
                x[2 * n + j] += below


def _id_value(kind, shape: str = "ID:VALUE"):
    def parse(text: str):
        try:
            motor_id, value = text.split(":")
            return strict_int(motor_id), kind(value)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {shape}, got {text!r}") from None
    return parse


def add_truth_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("mounting (to test calibration and homing)")
    g.add_argument("--true-offset", type=_id_value(strict_float), action="append", default=[],
                   metavar="ID:DEG", help="motor ID's angle at joint zero really is DEG "
                   "(the description's zero_offset_deg is a placeholder; repeatable)")
    g.add_argument("--true-direction", type=_id_value(strict_int), action="append", default=[],
                   metavar="ID:SIGN", help="motor ID really turns with (1) or against (-1) "
                   "its joint (repeatable)")
    g.add_argument("--hard-stop-m", type=number_argument, metavar="LOW",
                   help="a hard stop under the "
                   "slider at d1 = LOW m: the plant stops there, the motor pushes on")
    g.add_argument("--true-fit", type=_id_value(_pair, "ID:A,B"), action="append", default=[],
                   metavar="ID:A,B", help="motor ID's current-to-torque line really is "
                   "y = A x + B, in the units of its fit in the description (the description's "
                   "is a placeholder; repeatable)")


def _pair(text: str) -> tuple[float, float]:
    a, b = text.split(",")  # a ValueError: the ID:VALUE parser's message
    return strict_float(a), strict_float(b)


def truth_from_args(args: argparse.Namespace) -> Truth | None:
    if not (args.true_offset or args.true_direction or args.true_fit
            or args.hard_stop_m is not None):
        return None
    return Truth(dict(args.true_offset), dict(args.true_direction), args.hard_stop_m,
                 dict(args.true_fit))


if __name__ == "__main__":
    sys.exit(main())
