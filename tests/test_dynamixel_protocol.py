"""Protocol 2.0 frames: the CRC, the e-Manual's reference frames, byte stuffing both ways, and the
streaming parser's results on good, stuffed, split, corrupted and garbled input."""

from __future__ import annotations

import pytest

from cochlea.dynamixel import protocol as proto

H = bytes.fromhex


def test_crc_check_value():
    assert proto.crc16(b"123456789") == 0xFEE8
    # Chained over pieces, and over a slice of a larger buffer, without copying.
    assert proto.crc16(b"6789", crc=proto.crc16(b"12345")) == 0xFEE8
    assert proto.crc16(bytearray(b"xx123456789yy"), 2, 11) == 0xFEE8


# The examples of the e-Manual's Protocol 2.0 page (instruction and status packets).
REFERENCE = {
    "ping ID 1": (proto.ping(1), "FF FF FD 00 01 03 00 01 19 4E"),
    "sync read 132 len 4 IDs 1,2": (proto.sync_read(132, 4, [1, 2]),
                                    "FF FF FD 00 FE 09 00 82 84 00 04 00 01 02 CE FA"),
    "read 132 len 4 ID 1": (proto.read(1, 132, 4), "FF FF FD 00 01 07 00 02 84 00 04 00 1D 15"),
    "write 512 to 116 ID 1": (proto.write(1, 116, proto.le(512, 4)),
                              "FF FF FD 00 01 09 00 03 74 00 00 02 00 00 CA 89"),
    "sync write 150, 170 to 116": (
        proto.sync_write(116, 4, [(1, proto.le(150, 4)), (2, proto.le(170, 4))]),
        "FF FF FD 00 FE 11 00 83 74 00 04 00 01 96 00 00 00 02 AA 00 00 00 82 87"),
    "reboot ID 1": (proto.reboot(1), "FF FF FD 00 01 03 00 08 2F 4E"),
    "status ping ID 1": (proto.status(1, 0, H("06 04 26")),
                         "FF FF FD 00 01 07 00 55 00 06 04 26 65 5D"),
    "status ping ID 2": (proto.status(2, 0, H("06 04 26")),
                         "FF FF FD 00 02 07 00 55 00 06 04 26 6F 6D"),
    "status read ID 1": (proto.status(1, 0, proto.le(166, 4)),
                         "FF FF FD 00 01 08 00 55 00 A6 00 00 00 8C C0"),
    "status read ID 2": (proto.status(2, 0, proto.le(2079, 4)),
                         "FF FF FD 00 02 08 00 55 00 1F 08 00 00 BA BE"),
    "status write ID 1": (proto.status(1, 0), "FF FF FD 00 01 04 00 55 00 A1 0C"),
}


@pytest.mark.parametrize("name", REFERENCE)
def test_reference_frames(name):
    built, expected = REFERENCE[name]
    assert built == H(expected)


def test_stuffing_both_ways():
    assert proto.stuff(H("FF FF FD")) == H("FF FF FD FD")
    assert proto.stuff(H("01 FF FF FD 02 FF FF FD FD")) == H("01 FF FF FD FD 02 FF FF FD FD FD")
    assert proto.stuff(H("FF FD FF FF FF FD")) == H("FF FD FF FF FF FD FD")
    assert proto.stuff(H("FF FF FC FD")) == H("FF FF FC FD")  # no pattern, nothing added
    for body in (H("FF FF FD"), H("FF FF FD FD"), H("FF FF FF FD FF FF FD 00"), bytes(range(256)),
                 H("FF FF FD") * 5):
        assert proto.unstuff(proto.stuff(body)) == body
    # A sender that did not stuff: the bytes are kept as sent.
    assert proto.unstuff(H("FF FF FD 05")) == H("FF FF FD 05")


def test_a_frame_that_needs_stuffing_follows_the_specification():
    """WRITE FF FF FD to Goal PWM's neighbourhood: LEN and CRC count the stuffed byte."""
    frame = proto.write(1, 0x64, H("FF FF FD 00"))
    body = H("03 64 00 FF FF FD FD 00")  # instruction, address, stuffed data
    length = len(body) + 2
    head = H("FF FF FD 00 01") + proto.le(length, 2)
    crc = proto.crc16(head + body)
    assert frame == head + body + proto.le(crc, 2)
    parser = proto.PacketParser(status=False)
    parser.feed(frame)
    assert parser.parse() == proto.OK
    assert parser.params() == H("64 00 FF FF FD 00")


def test_parser_reads_a_stuffed_status_packet():
    """Present Current -1 (FF FF) followed by a velocity whose low byte is FD: motors stuff it."""
    data = proto.le(-1, 2) + H("FD 00 00 00") + proto.le(1234, 4)
    frame = proto.status(3, 0, data)
    assert H("FF FF FD FD") in frame and len(frame) == 11 + 10 + 1
    parser = proto.PacketParser()
    parser.feed(frame)
    assert parser.parse() == proto.OK
    assert (parser.id, parser.error, parser.params()) == (3, 0, data)


def _all(parser: proto.PacketParser) -> list[tuple]:
    out = []
    while (code := parser.parse()) != proto.NEED_MORE:
        out.append((code, parser.id, parser.params() if code == proto.OK else None))
    return out


def test_parser_resynchronises_on_garbage_and_reports_failures():
    good1 = proto.status(1, 0, proto.le(7, 2))
    good2 = proto.status(2, 0x80 | 6, proto.le(9, 2))  # hardware alert + Data Limit Error
    bad = bytearray(proto.status(3, 0, proto.le(5, 2)))
    bad[-1] ^= 0x55  # CRC corrupted
    stream = (b"\x00\xff\x12garbage\xff\xff" + good1 + bytes(bad) + b"\xff\xff\xfd" + good2
              + b"\xff\xff\xfd\x00\x04\xff\xff")  # an impossible length at the end
    parser = proto.PacketParser()
    parser.feed(stream)
    results = _all(parser)
    assert (proto.OK, 1, proto.le(7, 2)) in results
    assert (proto.CRC_FAILURE, 3, None) in results
    assert (proto.OK, 2, proto.le(9, 2)) in results
    assert results[-1][0] == proto.BAD_LENGTH
    assert [r[1] for r in results if r[0] == proto.OK] == [1, 2]
    assert parser.dropped > 0


def test_parser_error_byte_is_reported_as_a_value():
    parser = proto.PacketParser()
    parser.feed(proto.status(4, 0x80 | 4))
    assert parser.parse() == proto.OK
    assert parser.error == 0x84 and parser.params_len == 0


def test_parser_waits_for_split_packets_byte_by_byte():
    frame = proto.status(5, 0, bytes(range(10)))
    parser = proto.PacketParser()
    for i, byte in enumerate(frame):
        parser.feed(bytes([byte]))
        expected = proto.OK if i == len(frame) - 1 else proto.NEED_MORE
        assert parser.parse() == expected
    assert parser.params() == bytes(range(10))


def test_parser_kinds_and_short_packets():
    status_parser, instruction_parser = proto.PacketParser(True), proto.PacketParser(False)
    status_parser.feed(proto.ping(1))  # 3 bytes after the length: too short for a status
    assert status_parser.parse() == proto.BAD_LENGTH
    status_parser.reset()
    status_parser.feed(proto.read(1, 132, 4))
    assert status_parser.parse() == proto.WRONG_KIND
    instruction_parser.feed(proto.status(1, 0))
    assert instruction_parser.parse() == proto.WRONG_KIND
    instruction_parser.feed(proto.sync_read(126, 10, [1, 2, 3]))
    assert instruction_parser.parse() == proto.OK
    assert instruction_parser.id == 0xFE and instruction_parser.instruction == 0x82
    # A status packet with a good CRC but no error byte: its length field is too small.
    status_parser.reset()
    status_parser.feed(proto.instruction(1, 0x55))
    assert status_parser.parse() == proto.BAD_LENGTH


def test_frame_buffer_rebuilds_sync_write_in_place():
    ids = [1, 2, 3, 4, 5, 6]
    frame = proto.sync_write_buffer(102, 2, ids)
    values = [0, -1, 1941, -1941, 300, -2]
    for k, v in enumerate(values):
        frame.params[5 + 3 * k:7 + 3 * k] = proto.le(v, 2)
    n = frame.encode()
    assert bytes(frame.out[:n]) == proto.sync_write(102, 2, [(i, proto.le(v, 2))
                                                             for i, v in zip(ids, values)])
    assert n == 14 + 3 * len(ids)


def test_builders_reject_impossible_ids_and_lengths():
    with pytest.raises(ValueError):
        proto.ping(0xFD)
    with pytest.raises(ValueError):
        proto.sync_write(102, 2, [(1, b"\0")])
