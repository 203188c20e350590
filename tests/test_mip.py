"""MIP framing against byte vectors written out by hand from the LORD MicroStrain protocol manuals."""

from __future__ import annotations

import pytest

from rover.drivers.mip import MipParser, Packet, checksum, encode

PING = bytes.fromhex("75 65 01 02 02 01 E0 C6")
"""3DM-GX4-45 DCP manual, Ping (0x01, 0x01), example command"""
GET_IMU_BASE_RATE = bytes.fromhex("75 65 0C 02 02 06 F0 F7")
"""3DM-GX5-45 DCP manual, Get IMU Data Base Rate (0x0C, 0x06), example command"""
BASE_RATE_REPLY = bytes.fromhex("75 65 0C 08 04 F1 06 00 04 83 00 64 D4 6B")
"""the same page's example reply: ACK/NACK field echoing 0x06 with error 0, then field 0x83 = 100 Hz"""
IMU_STREAM_ON = bytes.fromhex("75 65 0C 05 05 11 01 01 01 04 1A")
"""3DM-GX5-35 DCP manual, Enable/Disable Continuous Data Stream (0x0C, 0x11): apply, IMU, on"""
IMU_DATA = bytes.fromhex(
    "75 65 80 1C"
    "0E 04 3F000000 00000000 BF800000"  # scaled accel (0.5, 0, -1) g
    "0E 05 00000000 00000000 3F800000"  # scaled gyro (0, 0, 1) rad/s
    "D8 D0"
)
"""an IMU data packet (set 0x80) written out field by field; checksum by hand"""
FIELDS_OVERRUN = bytes.fromhex("75 65 80 06 0A 04 00 00 00 00 6E 99")
"""a good checksum, but the one field claims 10 bytes of a 6-byte payload"""
FIELD_TOO_SHORT = bytes.fromhex("75 65 80 04 01 04 00 00 63 8F")
"""a good checksum, but a field length of 1 (a field has at least its length and descriptor bytes)"""

ACCEL = (0x04, bytes.fromhex("3F000000 00000000 BF800000"))
GYRO = (0x05, bytes.fromhex("00000000 00000000 3F800000"))

STREAM = PING + BASE_RATE_REPLY + IMU_DATA + IMU_STREAM_ON + IMU_DATA
EXPECTED = [
    Packet(0x01, [(0x01, b"")]),
    Packet(0x0C, [(0xF1, b"\x06\x00"), (0x83, b"\x00\x64")]),
    Packet(
        0x80, [(0x04, bytes.fromhex("3F000000 00000000 BF800000")), (0x05, bytes.fromhex("00000000 00000000 3F800000"))]
    ),
    Packet(0x0C, [(0x11, b"\x01\x01\x01")]),
    Packet(
        0x80, [(0x04, bytes.fromhex("3F000000 00000000 BF800000")), (0x05, bytes.fromhex("00000000 00000000 3F800000"))]
    ),
]


def counts(parser: MipParser) -> tuple[int, int, int]:
    return parser.skipped_bytes, parser.bad_checksums, parser.bad_fields


@pytest.mark.parametrize("raw", [PING, GET_IMU_BASE_RATE, BASE_RATE_REPLY, IMU_STREAM_ON, IMU_DATA])
def test_the_checksum_of_the_manuals_examples(raw):
    assert checksum(raw[:-2]) == raw[-2:]


def test_encode_gives_the_manuals_commands():
    assert encode(0x01, [(0x01, b"")]) == PING
    assert encode(0x0C, [(0x06, b"")]) == GET_IMU_BASE_RATE
    assert encode(0x0C, [(0x11, b"\x01\x01\x01")]) == IMU_STREAM_ON
    assert encode(0x0C, [(0xF1, b"\x06\x00"), (0x83, b"\x00\x64")]) == BASE_RATE_REPLY


def test_encode_refuses_what_does_not_fit_a_packet():
    with pytest.raises(ValueError, match="field 0x04"):
        encode(0x80, [(0x04, bytes(254))])
    with pytest.raises(ValueError, match="payload of 300 bytes"):
        encode(0x80, [(0x04, bytes(148)), (0x05, bytes(148))])


def test_a_stream_parses_into_its_packets():
    parser = MipParser()
    packets = parser.feed(STREAM)
    assert packets == EXPECTED
    assert packets[1].field(0x83) == b"\x00\x64"
    assert packets[1].field(0x84) is None
    assert counts(parser) == (0, 0, 0)


@pytest.mark.parametrize("cut", range(len(STREAM) + 1))
def test_a_stream_split_anywhere_gives_the_same_packets(cut):
    parser = MipParser()
    assert parser.feed(STREAM[:cut]) + parser.feed(STREAM[cut:]) == EXPECTED
    assert counts(parser) == (0, 0, 0)


def test_a_stream_fed_byte_by_byte_gives_the_same_packets():
    parser = MipParser()
    packets = [p for i in range(len(STREAM)) for p in parser.feed(STREAM[i : i + 1])]
    assert packets == EXPECTED
    assert counts(parser) == (0, 0, 0)


def test_garbage_between_packets_is_skipped_and_counted():
    parser = MipParser()
    packets = parser.feed(b"\x00\x75\x11\x65" + PING + b"\xff\x65" + IMU_DATA + b"\x75")
    assert packets == [EXPECTED[0], EXPECTED[2]]
    assert counts(parser) == (6, 0, 0)  # the trailing 0x75 may start a sync: kept
    assert parser.feed(b"\x00") == []
    assert counts(parser) == (8, 0, 0)
    assert parser.feed(b"\x75") == [] and parser.feed(b"\x65" + PING[2:]) == [EXPECTED[0]]
    assert counts(parser) == (8, 0, 0)


def test_a_false_sync_in_garbage_does_not_swallow_the_packet_after_it():
    parser = MipParser()
    # a sync, set 0x80 and a length that reaches into the real packet: its checksum fails
    assert parser.feed(b"\x75\x65\x80\x05\x01" + IMU_DATA + PING) == [EXPECTED[2], EXPECTED[0]]
    assert counts(parser) == (0, 1, 0)


def test_a_bad_checksum_drops_that_packet_only():
    parser = MipParser()
    corrupt = IMU_DATA[:-1] + bytes([IMU_DATA[-1] ^ 0xFF])
    assert parser.feed(PING + corrupt + IMU_DATA + corrupt[:10]) == [EXPECTED[0], EXPECTED[2]]
    assert parser.feed(corrupt[10:] + PING) == [EXPECTED[0]]
    assert counts(parser) == (0, 2, 0)


@pytest.mark.parametrize("bad", [FIELDS_OVERRUN, FIELD_TOO_SHORT])
def test_a_field_table_that_does_not_add_up_drops_the_packet(bad):
    parser = MipParser()
    assert checksum(bad[:-2]) == bad[-2:]
    assert parser.feed(bad + PING) == [EXPECTED[0]]
    assert counts(parser) == (0, 0, 1)


def test_an_empty_payload_is_a_packet_without_fields():
    parser = MipParser()
    raw = encode(0x80, [])
    assert raw == bytes.fromhex("75 65 80 00 5A 03")
    assert parser.feed(raw) == [Packet(0x80, [])]
