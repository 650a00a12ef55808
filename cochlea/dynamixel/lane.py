"""The period's packet work in C, at both ends of the bus: ``build/libcochlea-lane.so``
(``make lib``), for the virtual chain's requests (:class:`Lane`) and the bridge's SYNC_READ
replies (:class:`StatusBlock`).

A 1 kHz loop sends :class:`~cochlea.dynamixel.emulator.VirtualChain` a SYNC_WRITE of every
motor's Goal Current and a SYNC_READ of the per-period block each period. Their packet work in
Python (parse, CRC, the writes' checks, the status packets built) was most of the chain's time
and kept the loops against it late (issue 30, item 2). :class:`Lane` does that work in C
(``cochlea/dynamixel/c/lane.c``, with ``embedded/core/dxl.c``'s codec) on the
motors' own control tables, shared by pointer; the chain keeps the rest (plant, publication,
events, the reply queue and its timing). A receive the lane does not take entirely (anything
but those two requests, whole and clean) goes to the Python path unchanged, and so does every
receive of a chain with what the lane does not model (faults, baud checks, ignored writes):
:meth:`VirtualChain._lane_open` decides.

Without the library (a checkout before ``make lib``, a wheel built without a C compiler), or with
``COCHLEA_EMULATOR_LANE=0``, :func:`load` returns None and both ends work in Python: the
same bytes and results, slower. ``tests/test_emulator_lane.py`` checks both paths give the
same replies, tables and events on the same requests, and the bridge the same reads.
"""

from __future__ import annotations

import ctypes
import functools
import os
from importlib import resources
from pathlib import Path

from ..resources import checkout

#: Set to ``0`` to answer every request in Python (a comparison, a suspicion).
ENVIRONMENT = "COCHLEA_EMULATOR_LANE"
LIBRARY_NAME = "libcochlea-lane.so"

MAX_MOTORS = 64
MAX_PACKETS = 16
#: Action kinds (lane.c).
WRITTEN, REFUSED, READ, REPLY, CONTACT = 1, 2, 3, 4, 5


class _Motor(ctypes.Structure):
    _fields_ = [("table", ctypes.POINTER(ctypes.c_uint8)), ("table_size", ctypes.c_uint32),
                ("a_goal", ctypes.c_uint16), ("a_limit", ctypes.c_uint16),
                ("a_watchdog", ctypes.c_uint16), ("a_error", ctypes.c_uint16),
                ("a_level", ctypes.c_uint16), ("goal_lo", ctypes.c_int32),
                ("goal_hi", ctypes.c_int32), ("answering", ctypes.c_uint8),
                ("id", ctypes.c_uint8)]


class _Chain(ctypes.Structure):
    _fields_ = [("n_motors", ctypes.c_uint32), ("by_id", ctypes.c_int16 * 256),
                ("motors", _Motor * MAX_MOTORS)]


class _Packet(ctypes.Structure):
    _fields_ = [("offset", ctypes.c_uint32), ("frame_len", ctypes.c_uint32),
                ("params", ctypes.c_uint32), ("n_params", ctypes.c_uint32),
                ("instruction", ctypes.c_uint32)]


def library_path() -> Path:
    """A checkout's ``build/`` (``make lib``), else the installed package's ``lib/`` (setup.py
    compiles it into the wheel)."""
    root = checkout()
    if root is not None:
        return root / "build" / LIBRARY_NAME
    return Path(str(resources.files("cochlea") / "lib" / LIBRARY_NAME))


@functools.cache
def _library(path: str) -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL(path)
        sizes = (ctypes.c_uint32 * 7)()
        lib.lane_sizes(sizes)
    except (OSError, AttributeError):  # not a library, or not this one
        return None
    if list(sizes[:5]) != [ctypes.sizeof(_Motor), ctypes.sizeof(_Chain), ctypes.sizeof(_Packet),
                           MAX_MOTORS, MAX_PACKETS]:
        return None  # built from another version of the source: not to be trusted
    # The room one packet's actions and status packets take at most (lane.c's bounds).
    lib.max_actions, lib.out_size = sizes[5], sizes[6]
    lib.lane_scan.restype = ctypes.c_int32
    lib.lane_scan.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t,
                              ctypes.c_void_p]
    lib.lane_status_block.restype = ctypes.c_int32
    lib.lane_status_block.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p,
                                      ctypes.c_size_t, ctypes.c_size_t, ctypes.c_void_p]
    lib.lane_execute.restype = ctypes.c_int32
    lib.lane_execute.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                                 ctypes.c_void_p, ctypes.c_size_t, ctypes.c_void_p,
                                 ctypes.c_size_t]
    return lib


#: The lane's sources in a checkout (the Makefile's LANE_SRC and the header).
SOURCES = ("cochlea/dynamixel/c/lane.c", "embedded/core/dxl.c", "embedded/core/dxl.h")


def _stale(path: Path) -> bool:
    """In a checkout: the library is older than one of its sources (edited or pulled since
    ``make lib``), so it may not do what they say; it is not used until rebuilt."""
    root = checkout()
    if root is None:
        return False
    try:
        built = path.stat().st_mtime
        return any((root / name).stat().st_mtime > built for name in SOURCES)
    except OSError:
        return True


def load() -> ctypes.CDLL | None:
    """The lane's library, or None (not built or older than its sources, switched off, or from
    another source): then the emulator and the bridge do the work in Python."""
    if os.environ.get(ENVIRONMENT, "1") == "0":
        return None
    path = library_path()
    if not path.is_file() or _stale(path):
        return None
    return _library(str(path))


class Lane:
    """The C lane over ``motors`` (VirtualMotor objects, each with its Goal Current a signed
    2-byte RAM item bounded by a 2-byte unsigned Current Limit: :func:`lane_for` checks)."""

    def __init__(self, lib: ctypes.CDLL, motors, by_id: dict):
        self._lib = lib
        self.motors = list(motors)
        self._chain = c = _Chain()
        c.n_motors = len(self.motors)
        # The tables are exported to C: a bytearray cannot be resized while exported, and the
        # chain never replaces one (same-size slice assignments, as reboot's, are allowed).
        self._tables = [(ctypes.c_uint8 * len(m.table)).from_buffer(m.table)
                        for m in self.motors]
        index = {id(m): i for i, m in enumerate(self.motors)}
        for i in range(256):
            c.by_id[i] = -1
        for motor_id, m in by_id.items():
            c.by_id[motor_id] = index[id(m)]
        for i, m in enumerate(self.motors):
            goal = m.items[m.a_goal_current]
            cm = c.motors[i]
            cm.table = ctypes.cast(self._tables[i], ctypes.POINTER(ctypes.c_uint8))
            cm.table_size = len(m.table)
            cm.a_goal, cm.a_limit = m.a_goal_current, m.a_limit
            cm.a_watchdog, cm.a_error, cm.a_level = m.a_watchdog, m.a_error, m.a_level
            cm.goal_lo, cm.goal_hi = goal.lo, goal.hi
            cm.id = m.table[7]
            cm.answering = bool(m.answering)
        self._answering = [bool(m.answering) for m in self.motors]
        self._packets = (_Packet * MAX_PACKETS)()
        self._cap_actions = lib.max_actions
        self._actions = (ctypes.c_int32 * (4 * self._cap_actions))()
        self._out = ctypes.create_string_buffer(lib.out_size)
        self._out_view = memoryview(self._out).cast("B")
        self._in = ctypes.create_string_buffer(4096)

    def refresh(self) -> None:
        """Each motor's ``answering`` as the chain has it now (a fault, a test, may change it)."""
        for i, m in enumerate(self.motors):
            if m.answering != self._answering[i]:
                self._answering[i] = bool(m.answering)
                self._chain.motors[i].answering = bool(m.answering)

    def scan(self, data: bytes) -> list[tuple[int, int, int]]:
        """``[(instruction, frame length, packet index)]`` when the lane takes all of ``data``,
        else ``[]`` (nothing changed)."""
        n = len(data)
        if n > len(self._in):
            return []
        ctypes.memmove(self._in, data, n)
        count = self._lib.lane_scan(ctypes.byref(self._chain), self._in, n, self._packets)
        packets = self._packets
        return [(packets[k].instruction, packets[k].frame_len, k) for k in range(count)]

    def execute(self, k: int) -> tuple[list[int], memoryview]:
        """Packet ``k`` of the last :meth:`scan` applied: its actions, four numbers each
        ``(kind, motor index, a, b)`` (see lane.c; a reply's ``a, b`` are its status
        packet's offset and length in the returned buffer, the replies back to back)."""
        got = self._lib.lane_execute(ctypes.byref(self._chain), self._in,
                                     ctypes.byref(self._packets[k]), self._actions,
                                     self._cap_actions, self._out, len(self._out))
        if got < 0:  # cannot be: the buffers have lane.c's own sizes (lane_sizes)
            raise RuntimeError("the emulator's lane buffers are smaller than lane.c needs")
        return self._actions[:4 * got], self._out_view


class StatusBlock:
    """The bridge's side: the replies to its SYNC_READ checked and copied in one C call when
    they are what a healthy chain sends (``lane_status_block`` in lane.c): ``block(start,
    n_bytes)`` on the parser's buffer; True and the data in ``raw``, or False and nothing
    changed (the bridge then parses the same bytes in Python)."""

    def __init__(self, lib: ctypes.CDLL, buffer: bytearray, ids, length: int, raw: bytearray):
        self._call = lib.lane_status_block
        # Exported to C: neither bytearray may be resized while this lives (the parser's
        # buffer and the bridge's raw block never are).
        self._buffer = (ctypes.c_uint8 * len(buffer)).from_buffer(buffer)
        self._base = ctypes.addressof(self._buffer)
        self._ids = (ctypes.c_uint8 * len(ids))(*ids)
        self._raw = (ctypes.c_uint8 * len(raw)).from_buffer(raw)
        self.n, self.length = len(ids), length
        #: The bytes of the whole reply: n status packets of 11 + length bytes.
        self.total = len(ids) * (11 + length)

    def __call__(self, start: int, n_bytes: int) -> bool:
        return self._call(self._base + start, n_bytes, self._ids, self.n, self.length,
                          self._raw) == 1


def status_block(buffer: bytearray, ids, length: int, raw: bytearray) -> StatusBlock | None:
    """A :class:`StatusBlock`, or None without the library (the bridge parses in Python)."""
    lib = load()
    if lib is None or not ids or len(raw) != len(ids) * length:
        return None
    return StatusBlock(lib, buffer, ids, length, raw)


def lane_for(motors, by_id: dict) -> Lane | None:
    """A :class:`Lane` for the chain's motors, or None when the library is absent or a motor's
    registers are not what the lane handles (then the chain answers in Python)."""
    lib = load()
    if lib is None or not 0 < len(motors) <= MAX_MOTORS:
        return None
    for m in motors:
        goal = m.items.get(m.a_goal_current)
        limit = m.items.get(m.a_limit)
        if (goal is None or limit is None or goal.size != 2 or not goal.signed
                or not goal.writable or goal.eeprom or goal.values is not None
                or not all(isinstance(b, int) and -2**31 <= b < 2**31
                           for b in (goal.lo, goal.hi))
                or m.goal_limits.get(m.a_goal_current) != m.a_limit
                or limit.size != 2 or limit.signed):
            return None
    return Lane(lib, motors, by_id)
