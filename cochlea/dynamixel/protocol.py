"""Dynamixel Protocol 2.0 frames: CRC-16, byte stuffing, instruction builders, a packet parser.

Frame layout (little-endian)::

    instruction:  FF FF FD 00 | ID | LEN_L LEN_H | INST | params...      | CRC_L CRC_H
    status:       FF FF FD 00 | ID | LEN_L LEN_H | 0x55 | ERR | params... | CRC_L CRC_H

``LEN`` counts the bytes after it (instruction, error, parameters, CRC) *after* byte stuffing:
from the instruction byte to the last parameter, every ``FF FF FD`` gets an extra ``FD``. The
CRC (polynomial 0x8005, initial value 0, no reflection, no final XOR) covers the whole stuffed
frame from the header on. A receiver checks the CRC, then removes the stuffing.

The builders (:func:`ping`, :func:`read`, :func:`write`, :func:`sync_read`, :func:`sync_write`,
:func:`fast_sync_read`, :func:`bulk_read`, :func:`bulk_write`, ...) return ``bytes`` and are
for set-up code. The per-period path uses :class:`FrameBuffer` (a frame rebuilt in place in a
preallocated buffer) and :class:`PacketParser` (a streaming parser over a preallocated buffer
that returns a result code, never raises).
"""

from __future__ import annotations

import struct
from array import array
from collections.abc import Iterable, Sequence

from .control_table import (
    BROADCAST_ID,
    BULK_READ,
    BULK_WRITE,
    FAST_SYNC_READ,
    MAX_ID,
    PING,
    READ,
    REBOOT,
    STATUS,
    SYNC_READ,
    SYNC_WRITE,
    WRITE,
)

HEADER = b"\xff\xff\xfd\x00"
#: The bytes after which a sender stuffs an extra FD.
_STUFF_AFTER = HEADER[:3]
#: Bytes before the instruction: header (4), ID, LEN_L, LEN_H.
PREFIX = 7
#: Largest frame the parser accepts (the official SDK uses the same bound).
MAX_FRAME = 1024


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


CRC_TABLE = _crc_table()
#: The CRC after two bytes at once: ``CRC_TABLE2[crc ^ (b0 << 8 | b1)]`` (a 16-bit register
#: shifts both bytes through, so the pair and the register combine into one index). Half the
#: interpreted steps of the byte table (a 27-byte status packet: about 8 us -> 4.5 us here), on
#: the emulator's and the bridge's per-period path; 128 KiB.
CRC_TABLE2 = array("H", [((CRC_TABLE[hi] << 8) & 0xFFFF) ^ CRC_TABLE[(CRC_TABLE[hi] >> 8) ^ lo]
                         for hi in range(256) for lo in range(256)])


def crc16(data, start: int = 0, end: int | None = None, crc: int = 0) -> int:
    """CRC-16 of ``data[start:end]`` as Protocol 2.0 defines it (``crc16(b"123456789")`` is
    0xFEE8), continuing from ``crc``. Works on bytes, bytearray and memoryview without
    copying."""
    pairs = CRC_TABLE2
    stop = len(data) if end is None else end
    crc &= 0xFFFF
    n = (stop - start) >> 1 if stop > start else 0
    if n:
        # The byte pairs as big-endian 16-bit numbers, unpacked in one call: the loop is then
        # one table look-up per pair (148 bytes: 8.7 -> 4.8 us here, on the emulator's and the
        # bridge's per-period path).
        for pair in _pairs(n).unpack_from(data, start):
            crc = pairs[crc ^ pair]
    if start + 2 * n < stop:
        crc = ((crc << 8) & 0xFFFF) ^ CRC_TABLE[(crc >> 8) ^ data[stop - 1]]
    return crc


def _pairs(n: int, cache: dict = {}) -> struct.Struct:  # noqa: B006 (a cache, on purpose)
    """``>nH``, made once per length."""
    s = cache.get(n)
    if s is None:
        s = cache[n] = struct.Struct(f">{n}H")
    return s


def stuff(body: bytes | bytearray) -> bytes:
    """Byte stuffing of the instruction-to-parameters part: ``FF FF FD`` -> ``FF FF FD FD``."""
    out = bytearray()
    last1 = last2 = 0
    for x in body:
        out.append(x)
        if x == 0xFD and last1 == 0xFF and last2 == 0xFF:
            out.append(0xFD)
        last2, last1 = last1, x
    return bytes(out)


def unstuff(body: bytes | bytearray) -> bytes:
    """The inverse of :func:`stuff`. A missing stuffing byte (a sender that does not stuff) is
    tolerated: the data are kept as sent."""
    buf = bytearray(body)
    n = _unstuff_in_place(buf, 0, len(buf))
    return bytes(buf[:n])


def _unstuff_in_place(buf: bytearray, start: int, end: int) -> int:
    """Remove stuffing from ``buf[start:end]`` in place; returns the end of the result."""
    w = start
    last1 = last2 = 0
    skip = False
    for r in range(start, end):
        x = buf[r]
        if skip:
            skip = False
            if x == 0xFD:
                continue
        buf[w] = x
        w += 1
        if x == 0xFD and last1 == 0xFF and last2 == 0xFF:
            skip = True
        last2, last1 = last1, x
    return w


def encode_into(out: bytearray, packet_id: int, first: int, params, n_params: int) -> int:
    """Write a whole frame into ``out`` (header, ID, length, stuffed ``first`` byte and
    parameters, CRC) and return its length. ``first`` is the instruction (instruction packets)
    or ``0x55`` followed by the error byte as the first parameter (status packets). Allocates
    nothing; ``out`` must hold the stuffed frame (at most ``PREFIX + 2 * (1 + n_params) + 2``)."""
    out[0] = 0xFF
    out[1] = 0xFF
    out[2] = 0xFD
    out[3] = 0x00
    out[4] = packet_id
    w = PREFIX
    out[w] = first
    w += 1
    if isinstance(params, (bytes, bytearray)) and params.find(_STUFF_AFTER, 0, n_params) < 0 \
            and not (first == 0xFF and n_params >= 2 and params[0] == 0xFF
                     and params[1] == 0xFD):
        # Nothing to stuff (the usual case): the parameters in one copy, not byte by byte.
        out[w:w + n_params] = memoryview(params)[:n_params]
        w += n_params
        n_params = 0  # the loop below has nothing left to do
    last1, last2 = first, 0
    for i in range(n_params):
        x = params[i]
        out[w] = x
        w += 1
        if x == 0xFD and last1 == 0xFF and last2 == 0xFF:
            out[w] = 0xFD
            w += 1
        last2, last1 = last1, x
    length = w - PREFIX + 2
    out[5] = length & 0xFF
    out[6] = length >> 8
    crc = crc16(out, 0, w)
    out[w] = crc & 0xFF
    out[w + 1] = crc >> 8
    return w + 2


def _frame(packet_id: int, first: int, params: bytes | bytearray) -> bytes:
    out = bytearray(PREFIX + 2 * (1 + len(params)) + 2)
    n = encode_into(out, packet_id, first, params, len(params))
    return bytes(out[:n])


def instruction(packet_id: int, instruction_code: int, params: bytes | bytearray = b"") -> bytes:
    """Any instruction packet."""
    if not 0 <= packet_id <= BROADCAST_ID or packet_id == 0xFD:
        raise ValueError(f"packet ID {packet_id} is not 0..{MAX_ID} or broadcast (254)")
    return _frame(packet_id, instruction_code, params)


def status(packet_id: int, error: int = 0, params: bytes | bytearray = b"") -> bytes:
    """A status packet (what a motor answers)."""
    params = bytes(params)
    if params.find(_STUFF_AFTER) >= 0 or (error == 0xFF and params[:2] == b"\xff\xfd"):
        return _frame(packet_id, STATUS, bytes([error]) + params)
    # Nothing to stuff (0x55 cannot start an FF FF FD): the frame in one piece, its CRC
    # continued from its head's, which a motor repeats. The emulator answers six of these a
    # period (7 -> 2.5 us each here).
    key = (packet_id, len(params), error)
    known = _STATUS_HEADS.get(key)
    if known is None:
        length = len(params) + 4  # 0x55, error, the parameters, the CRC
        head = bytes((0xFF, 0xFF, 0xFD, 0x00, packet_id, length & 0xFF, length >> 8, STATUS,
                      error))
        if len(_STATUS_HEADS) >= 4096:  # every ID, length and error seen: a bound, not a leak
            _STATUS_HEADS.clear()
        known = _STATUS_HEADS[key] = head, crc16(head)
    head, crc = known
    crc = crc16(params, crc=crc)
    return b"".join((head, params, bytes((crc & 0xFF, crc >> 8))))


#: ``(ID, parameter count, error) -> (status packet head, its CRC)`` (see :func:`status`).
_STATUS_HEADS: dict[tuple[int, int, int], tuple[bytes, int]] = {}


def le(value: int, size: int) -> bytes:
    """``value`` as ``size`` little-endian bytes (negative values in two's complement)."""
    return (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def from_le(data, signed: bool) -> int:
    return int.from_bytes(bytes(data), "little", signed=signed)


def ping(motor_id: int) -> bytes:
    return instruction(motor_id, PING)


def read(motor_id: int, address: int, length: int) -> bytes:
    return instruction(motor_id, READ, le(address, 2) + le(length, 2))


def write(motor_id: int, address: int, data: bytes | bytearray) -> bytes:
    return instruction(motor_id, WRITE, le(address, 2) + bytes(data))


def reboot(motor_id: int) -> bytes:
    return instruction(motor_id, REBOOT)


def sync_read(address: int, length: int, ids: Iterable[int]) -> bytes:
    return instruction(BROADCAST_ID, SYNC_READ, le(address, 2) + le(length, 2) + bytes(ids))


def fast_sync_read(address: int, length: int, ids: Iterable[int]) -> bytes:
    """FAST_SYNC_READ (0x8A): the SYNC_READ request with another instruction code; the motors
    answer with one combined status packet (:func:`fast_sync_status`, :func:`split_fast_sync`)."""
    return instruction(BROADCAST_ID, FAST_SYNC_READ,
                       le(address, 2) + le(length, 2) + bytes(ids))


def bulk_read(reads: Sequence[tuple[int, int, int]]) -> bytes:
    """BULK_READ (0x92): ``reads`` is one ``(id, address, length)`` per motor; each motor
    answers with its own status packet, in list order."""
    params = bytearray()
    for motor_id, address, length in reads:
        params.append(motor_id)
        params += le(address, 2) + le(length, 2)
    return instruction(BROADCAST_ID, BULK_READ, params)


def bulk_write(writes: Sequence[tuple[int, int, bytes]]) -> bytes:
    """BULK_WRITE (0x93): ``writes`` is one ``(id, address, data)`` per motor (no reply)."""
    params = bytearray()
    for motor_id, address, data in writes:
        params.append(motor_id)
        params += le(address, 2) + le(len(data), 2) + bytes(data)
    return instruction(BROADCAST_ID, BULK_WRITE, params)


def bulk_write_buffer(writes: Sequence[tuple[int, int, int]]) -> tuple[FrameBuffer, list[int]]:
    """A BULK_WRITE frame rebuilt in place each period: ``writes`` is one ``(id, address,
    length)`` per motor; returns the buffer and, per motor, where its data start in
    ``params``."""
    params = bytearray()
    starts = []
    for motor_id, address, length in writes:
        params.append(motor_id)
        params += le(address, 2) + le(length, 2)
        starts.append(len(params))
        params += bytes(length)
    return FrameBuffer(BROADCAST_ID, BULK_WRITE, params), starts


def fast_sync_status(blocks: Sequence[tuple[int, int, bytes]]) -> bytes:
    """The combined status packet of a FAST_SYNC_READ (what the motors send together):
    ``blocks`` is one ``(id, error, data)`` per answering motor, in request order.

    One header with ID 0xFE and instruction 0x55; then per motor ``ERR ID DATA CRC``, where
    each motor's CRC is that of the packet from its header up to the end of its own data (a
    running CRC: each motor appends its block to what the previous ones sent); the last
    motor's CRC is the packet's own. LEN counts from the instruction to that last CRC. The
    stuffing is applied to the whole body, as in every packet; the intermediate CRCs here are
    computed over the stuffed bytes sent so far."""
    if not blocks:
        raise ValueError("a FAST_SYNC_READ status needs at least one motor")
    body = bytearray([STATUS])
    marks = []  # end (in body) of each motor's data but the last's, where its CRC goes
    last = len(blocks) - 1
    for k, (motor_id, error, data) in enumerate(blocks):
        body.append(error)
        body.append(motor_id)
        body += data
        if k < last:
            marks.append(len(body))
            body += b"\0\0"  # this motor's CRC, filled in below
    if _STUFF_AFTER in body:
        # Stuff the body (the CRC slots still zero), noting where the slots went.
        stuffed = bytearray()
        slots = []
        ends = set(marks)
        last1 = last2 = 0
        for i, x in enumerate(body):
            stuffed.append(x)
            if x == 0xFD and last1 == 0xFF and last2 == 0xFF:
                stuffed.append(0xFD)
            last2, last1 = last1, x
            if i + 1 in ends:
                slots.append(len(stuffed))
    else:  # nothing to stuff (the usual case): the body as it is
        stuffed, slots = body, marks
    frame = bytearray(HEADER)
    length = len(stuffed) + 2
    frame += bytes([BROADCAST_ID, length & 0xFF, length >> 8])
    frame += stuffed
    # The running CRCs over the stuffed stream, each continuing the previous one (each motor's
    # covers the packet up to its data, the CRCs before it included).
    crc = done = 0
    for slot in slots:
        at = PREFIX + slot
        crc = crc16(frame, done, at, crc)
        frame[at], frame[at + 1] = crc & 0xFF, crc >> 8
        done = at
    crc = crc16(frame, done, len(frame), crc)
    frame.append(crc & 0xFF)
    frame.append(crc >> 8)
    return bytes(frame)


#: What :func:`check_fast_sync` reports besides OK (a motor's block and where it went wrong).
FAST_MISSING, FAST_WRONG_ID, FAST_BLOCK_CRC = 1, 2, 3


def check_fast_sync(parser: PacketParser, ids: Sequence[int], length: int) -> tuple[int, int]:
    """Check the combined FAST_SYNC_READ status the parser has just returned OK (ID 0xFE):
    ``(0, -1)`` when every motor ``ids[k]`` has its block, in order, of ``length`` data bytes,
    its running CRC right; else ``(code, k)`` for the first motor at fault: ``FAST_MISSING``
    (the packet holds fewer blocks than motors asked), ``FAST_WRONG_ID`` (another ID where its
    block should be), ``FAST_BLOCK_CRC`` (its running CRC does not match). Motor k's error
    byte is ``parser.buf[fast_block(parser, k, length)]``, its ID one byte later, its data two.

    The running CRCs are checked over the header and the unstuffed body (the parser removed
    the stuffing): the bytes on the wire unless a ``FF FF FD`` was stuffed, in which case
    only the packet's own CRC (already checked by the parser) is relied on."""
    b = parser.buf
    block = length + 4
    n = len(ids)
    present = (parser.params_len + 3) // block if parser.params_len + 3 >= block else 0
    whole = parser.params_len + 3 == present * block
    frame = parser.params_start - 2 - PREFIX  # where the frame starts in the buffer
    stuffed = parser.frame_len != PREFIX + 2 + parser.params_len + 2
    crc, done = 0, frame  # the running CRC, continued block by block (each covers the last)
    for k in range(min(n, present)):
        at = parser.params_start - 1 + k * block
        if b[at + 1] != ids[k]:
            return FAST_WRONG_ID, k
        if k < n - 1 and k < present - 1 and not stuffed:
            crc_at = at + 2 + length
            crc = crc16(b, done, crc_at, crc)
            if crc != (b[crc_at] | (b[crc_at + 1] << 8)):
                return FAST_BLOCK_CRC, k
            done = crc_at
    if present < n:
        return FAST_MISSING, present
    if present > n or not whole:
        return FAST_WRONG_ID, min(present, n) - 1
    return 0, -1


def fast_block(parser: PacketParser, k: int, length: int) -> int:
    """Where motor k's block (its error byte) starts in ``parser.buf`` (see check_fast_sync)."""
    return parser.params_start - 1 + k * (length + 4)


def sync_write(address: int, length: int, data: Sequence[tuple[int, bytes]]) -> bytes:
    """``data``: one ``(id, bytes)`` per motor, each ``length`` bytes long."""
    params = bytearray(le(address, 2) + le(length, 2))
    for motor_id, values in data:
        if len(values) != length:
            raise ValueError(f"SYNC_WRITE data of ID {motor_id} has {len(values)} bytes, "
                             f"not {length}")
        params.append(motor_id)
        params += values
    return instruction(BROADCAST_ID, SYNC_WRITE, params)


class FrameBuffer:
    """An instruction frame rebuilt in place each period: the parameters live in ``params``
    (change them in place), :meth:`encode` writes the frame into ``out`` and returns its
    length. Nothing is allocated after construction."""

    def __init__(self, packet_id: int, instruction_code: int, params: bytes | bytearray):
        self.packet_id = packet_id
        self.instruction = instruction_code
        self.params = bytearray(params)
        self.out = bytearray(PREFIX + 2 * (1 + len(self.params)) + 2)
        self.view = memoryview(self.out)

    def encode(self) -> int:
        return encode_into(self.out, self.packet_id, self.instruction, self.params,
                           len(self.params))


def sync_write_buffer(address: int, length: int, ids: Sequence[int]) -> FrameBuffer:
    """A SYNC_WRITE frame whose data start at ``params[5 + k * (1 + length)]`` for motor k."""
    params = bytearray(le(address, 2) + le(length, 2))
    for motor_id in ids:
        params.append(motor_id)
        params += bytes(length)
    return FrameBuffer(BROADCAST_ID, SYNC_WRITE, params)


# --------------------------------------------------------------------------------------------
# Streaming parser
# --------------------------------------------------------------------------------------------

#: Result codes of :meth:`PacketParser.parse`.
OK = 0  # a whole packet with a good CRC: see id, instruction, error, params_*
NEED_MORE = 1  # no whole packet in the buffer yet
CRC_FAILURE = 2  # a packet whose CRC does not match (``id`` is its ID field, maybe corrupted)
BAD_LENGTH = 3  # a header whose length field is impossible (dropped one byte to resynchronise)
BAD_ID = 4  # a header whose ID field is impossible (dropped one byte)
WRONG_KIND = 5  # a good packet of the other kind (an instruction where a status was expected)
SHORT = 6  # a good packet too short for its kind (a status without error byte)
RESULT_NAMES = {OK: "ok", NEED_MORE: "need more", CRC_FAILURE: "CRC failure",
                BAD_LENGTH: "bad length", BAD_ID: "bad ID", WRONG_KIND: "wrong packet kind",
                SHORT: "short packet"}


class PacketParser:
    """Finds packets in a byte stream, resynchronising on garbage.

    Bytes go in through :meth:`feed` (a copy) or :meth:`space` + :meth:`commit` (read straight
    into the buffer). Each :meth:`parse` call returns one result code; on ``OK`` the packet's
    fields are ``id``, ``instruction``, ``error`` (status packets) and the unstuffed
    parameters ``buf[params_start:params_start + params_len]``, valid until the next call.
    ``status=True`` parses status packets (what the bridge reads), ``False`` instruction
    packets (what the emulator reads). Every call either consumes at least one byte or returns
    ``NEED_MORE``, so a loop of calls ends; nothing raises, whatever the bytes.
    """

    def __init__(self, status: bool = True, capacity: int = 2 * MAX_FRAME):
        self.status = status
        self.capacity = capacity
        self.buf = bytearray(capacity)
        self.view = memoryview(self.buf)
        self.start = 0
        self.end = 0
        self.id = 0
        self.instruction = 0
        self.error = 0
        self.params_start = 0
        self.params_len = 0
        self.frame_len = 0  # stuffed length of the last packet returned (OK or CRC_FAILURE)
        self.dropped = 0  # garbage bytes skipped since construction

    def reset(self) -> None:
        """Forget buffered bytes (start of a new transaction)."""
        self.start = self.end = 0

    @property
    def pending(self) -> int:
        return self.end - self.start

    def _compact(self) -> None:
        n = self.end - self.start
        if n and self.start:
            self.buf[0:n] = bytes(self.view[self.start:self.end])
        self.start, self.end = 0, n

    def space(self) -> memoryview:
        """Free room at the end of the buffer to read into (then :meth:`commit`)."""
        if self.start == self.end:
            self.start = self.end = 0
        elif self.end >= self.capacity - 64:
            self._compact()
        return self.view[self.end:]

    def commit(self, n: int) -> None:
        self.end = min(self.end + max(n, 0), self.capacity)

    def feed(self, data) -> int:
        """Copy bytes in; returns how many fitted (the rest must be fed again after parsing)."""
        room = self.space()
        n = min(len(data), len(room))
        room[:n] = data[:n]
        self.commit(n)
        return n

    def params(self) -> bytes:
        """The last packet's parameters as bytes (a copy: for set-up code, not the loop)."""
        return bytes(self.view[self.params_start:self.params_start + self.params_len])

    def parse(self) -> int:
        b = self.buf
        s, e = self.start, self.end
        if e - s < 4:
            return NEED_MORE
        i = b.find(HEADER, s, e)
        if i < 0:
            keep = max(s, e - 3)  # a header may be split across reads
            self.dropped += keep - s
            self.start = keep
            return NEED_MORE
        if i > s:
            self.dropped += i - s
            s = self.start = i
        if e - s < PREFIX:
            return NEED_MORE
        packet_id = b[s + 4]
        length = b[s + 5] | (b[s + 6] << 8)
        if self.status:
            # 0xFE: the one combined status packet of a FAST_SYNC_READ.
            if packet_id > MAX_ID and packet_id != BROADCAST_ID:
                self.start = s + 1
                self.dropped += 1
                return BAD_ID
            shortest = 4  # 0x55, error, CRC
        else:
            if packet_id == 0xFD or packet_id == 0xFF:
                self.start = s + 1
                self.dropped += 1
                return BAD_ID
            shortest = 3  # instruction, CRC
        total = PREFIX + length
        if length < shortest or total > self.capacity:
            self.start = s + 1
            self.dropped += 1
            return BAD_LENGTH
        if e - s < total:
            if total > self.capacity - s:
                self._compact()
            return NEED_MORE
        crc_end = s + total - 2
        self.id = packet_id
        self.frame_len = total
        if crc16(b, s, crc_end) != (b[crc_end] | (b[crc_end + 1] << 8)):
            self.start = s + 1  # resynchronise inside: the next header may be real
            self.dropped += 1
            return CRC_FAILURE
        self.start = s + total
        body = s + PREFIX
        # Unstuffed in place only where a stuffing can be (an FF FF FD in the body): the byte
        # loop costs about 25 us on a 148-byte packet, the search well under 1.
        body_end = (crc_end if b.find(_STUFF_AFTER, body, crc_end) < 0
                    else _unstuff_in_place(b, body, crc_end))
        self.instruction = b[body]
        if self.status:
            if self.instruction != STATUS:
                return WRONG_KIND
            if body_end - body < 2:
                return SHORT
            self.error = b[body + 1]
            self.params_start = body + 2
        else:
            if self.instruction == STATUS:
                return WRONG_KIND
            self.error = 0
            self.params_start = body + 1
        self.params_len = body_end - self.params_start
        return OK
