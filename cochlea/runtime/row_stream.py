"""The row stream of a board's firmware (embedded/ports/common/stream.c): frames that carry
its loop's log rows to the host, and a decoder that survives what a serial line does to them.

A frame (little-endian; docs/embedded.md, "The row stream")::

    C5 7E | type u8 | flags u8 | length u16 | sequence u32 | payload (length) | CRC-32 u32

The CRC is zlib's CRC-32 of type .. payload. The types: ``H`` the header (``key=value`` text,
``columns=`` last), ``R`` a row (period index i64, then ``row_length`` doubles), ``E`` the end
(``key=value`` text). The sequence is 0 for the header and one more for every frame the
firmware framed, so a gap is a lost frame and a repeat a duplicate.

:class:`Decoder` takes bytes as they come and returns whole, checked frames; whatever is not
one (a corrupted byte, a frame cut short, noise before the first sync) is counted in
:class:`Counts` and skipped by searching for the next sync word: it never raises on the bytes
it is given.
"""

from __future__ import annotations

import re
import struct
import zlib
from dataclasses import dataclass, field

SYNC = b"\xc5\x7e"
HEADER, ROW, END = ord("H"), ord("R"), ord("E")
TYPES = (HEADER, ROW, END)
#: sync, type, flags, length, sequence, then the CRC after the payload
_HEAD = struct.Struct("<2sBBHI")
OVERHEAD = _HEAD.size + 4
#: The firmware's largest payload (stream.h's STREAM_MAX_PAYLOAD).
MAX_PAYLOAD = 4096


def encode(kind: int, sequence: int, payload: bytes) -> bytes:
    """One frame, as the firmware frames it."""
    if kind not in TYPES or len(payload) > MAX_PAYLOAD:
        raise ValueError(f"frame type {kind!r} or payload of {len(payload)} bytes")
    head = _HEAD.pack(SYNC, kind, 0, len(payload), sequence & 0xFFFFFFFF)
    crc = zlib.crc32(head[2:] + payload)
    return head + payload + struct.pack("<I", crc)


def row_payload(k: int, row) -> bytes:
    """A row frame's payload: the period index, then the row's values."""
    return struct.pack(f"<q{len(row)}d", k, *row)


def chain_crc(crc: int, frame_crc: int) -> int:
    """The firmware's ``rows_crc`` after one more row frame (its CRC, 4 bytes LE)."""
    return zlib.crc32(struct.pack("<I", frame_crc), crc)


def parse_text(payload: bytes) -> dict[str, str]:
    """A header or end frame's ``key=value`` fields (``columns=`` is the rest of its line)."""
    text = payload.decode("ascii", errors="replace")
    fields = dict(re.findall(r"(\w+)=(\S+)", text))
    # A header's first word names the board that sent it (cochlea-<board>-stream).
    board = re.match(r"cochlea-(\w+)-stream ", text)
    if board and "board" not in fields:
        fields["board"] = board.group(1)
    if " columns=" in text:
        fields["columns"] = text.split(" columns=", 1)[1].strip()
    return fields


@dataclass
class Frame:
    kind: int
    sequence: int
    payload: bytes
    crc: int  # its CRC-32 (the firmware's end frame chains the row frames' CRCs: rows_crc)


@dataclass
class Counts:
    """What the decoder saw: the frames kept and everything it skipped."""
    frames: int = 0
    bad_crc: int = 0  # a sync word and a plausible length, but the CRC does not match
    bad_length: int = 0  # a length above MAX_PAYLOAD or an unknown type (noise or a torn head)
    skipped_bytes: int = 0  # bytes outside any good frame (noise, torn or corrupted frames)
    lost_frames: int = 0  # sequence numbers never seen (gaps)
    duplicates: int = 0  # a sequence number seen before (dropped)
    truncated_bytes: int = 0  # a frame begun but not finished when the stream ended

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class Decoder:
    """Frames out of a byte stream, resynchronising on the sync word after any damage."""
    counts: Counts = field(default_factory=Counts)
    _buffer: bytearray = field(default_factory=bytearray)
    _next: int | None = None  # the sequence number expected next

    def feed(self, data: bytes) -> list[Frame]:
        self._buffer += data
        out = []
        while True:
            frame = self._one()
            if frame is None:
                return out
            if self._accept(frame):
                out.append(frame)

    def finish(self) -> None:
        """The stream ended: what is left is a frame cut short (or noise)."""
        self.counts.truncated_bytes += len(self._buffer)
        self._buffer.clear()

    def _skip(self, n: int) -> None:
        del self._buffer[:n]
        self.counts.skipped_bytes += n

    def _one(self) -> Frame | None:
        buf = self._buffer
        while True:
            at = buf.find(SYNC)
            if at < 0:  # keep a last byte that may be half a sync word
                keep = 1 if buf[-1:] == SYNC[:1] else 0
                self._skip(len(buf) - keep)
                return None
            if at:
                self._skip(at)
            if len(buf) < _HEAD.size:
                return None
            _, kind, flags, length, sequence = _HEAD.unpack_from(buf)
            if kind not in TYPES or flags != 0 or length > MAX_PAYLOAD:
                self.counts.bad_length += 1
                self._skip(1)
                continue
            end = _HEAD.size + length + 4
            if len(buf) < end:
                return None
            body = bytes(buf[2:_HEAD.size + length])
            (crc,) = struct.unpack_from("<I", buf, _HEAD.size + length)
            if zlib.crc32(body) != crc:
                self.counts.bad_crc += 1
                self._skip(1)
                continue
            del buf[:end]
            return Frame(kind, sequence, bytes(buf_payload(body)), crc)

    def _accept(self, frame: Frame) -> bool:
        if frame.kind == HEADER and frame.sequence == 0:
            self._next = None  # a (re)started firmware numbers from 0 again
        if self._next is not None:
            gap = (frame.sequence - self._next) & 0xFFFFFFFF
            if gap >= 0x80000000:  # behind the expected: a repeat
                self.counts.duplicates += 1
                return False
            self.counts.lost_frames += gap
        self._next = (frame.sequence + 1) & 0xFFFFFFFF
        self.counts.frames += 1
        return True


def buf_payload(body: bytes) -> bytes:
    """The payload of a checked frame's type .. payload bytes."""
    return body[_HEAD.size - 2:]
