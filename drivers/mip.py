"""MIP, the LORD MicroStrain packet protocol of the 3DM-GX4/GX5 inertial sensors: framing only, no I/O.

A packet, as the 3DM-GX4-45 Data Communications Protocol manual describes it:

    0x75 0x65 | descriptor set | payload length | fields... | checksum MSB, LSB

Each field is [field length, field descriptor, data...], its length counting its own two header
bytes. The checksum is a 16-bit Fletcher sum over every byte before it, sync bytes included.
Multi-byte values in fields are big-endian. `MipParser` cuts a byte stream (a serial port, read in
whatever chunks it gives) into packets, skipping what is not one.
"""

from __future__ import annotations

from dataclasses import dataclass

SYNC = b"\x75\x65"
HEADER_BYTES = 4
"""sync1, sync2, descriptor set, payload length"""
CHECKSUM_BYTES = 2
FIELD_HEADER_BYTES = 2
"""field length, field descriptor"""
MAX_PAYLOAD_BYTES = 255
MAX_FIELD_DATA_BYTES = MAX_PAYLOAD_BYTES - FIELD_HEADER_BYTES


def checksum(data: bytes | bytearray) -> bytes:
    """The MIP Fletcher checksum of `data`: sum1 = running byte sum mod 256, sum2 = running sum of
    sum1 mod 256; sent sum1 first."""
    sum1 = sum2 = 0
    for byte in data:
        sum1 = (sum1 + byte) & 0xFF
        sum2 = (sum2 + sum1) & 0xFF
    return bytes((sum1, sum2))


def encode(descriptor_set: int, fields: list[tuple[int, bytes]]) -> bytes:
    """One packet of `descriptor_set` carrying `fields` ((descriptor, data) pairs), checksum included."""
    payload = bytearray()
    for descriptor, data in fields:
        if len(data) > MAX_FIELD_DATA_BYTES:
            raise ValueError(f"MIP field 0x{descriptor:02X} has {len(data)} bytes of data, over {MAX_FIELD_DATA_BYTES}")
        payload += bytes((len(data) + FIELD_HEADER_BYTES, descriptor)) + data
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ValueError(f"MIP payload of {len(payload)} bytes is longer than {MAX_PAYLOAD_BYTES}")
    packet = SYNC + bytes((descriptor_set, len(payload))) + payload
    return packet + checksum(packet)


@dataclass(frozen=True)
class Packet:
    """A packet that passed its checksum: its descriptor set and its fields, in order."""

    descriptor_set: int
    fields: list[tuple[int, bytes]]

    def field(self, descriptor: int) -> bytes | None:
        """The data of the first field with this descriptor, or None."""
        return next((data for d, data in self.fields if d == descriptor), None)


def split_fields(payload: bytes | bytearray) -> list[tuple[int, bytes]] | None:
    """The (descriptor, data) fields of a payload, or None when the field lengths do not add up to it."""
    fields = []
    pos, end = 0, len(payload)
    while pos < end:
        if end - pos < FIELD_HEADER_BYTES:
            return None
        length = payload[pos]
        if length < FIELD_HEADER_BYTES or pos + length > end:
            return None
        fields.append((payload[pos + 1], bytes(payload[pos + FIELD_HEADER_BYTES : pos + length])))
        pos += length
    return fields


class MipParser:
    """Cuts a byte stream into packets, across any chunk boundaries.

    Bytes before a sync are skipped; a candidate packet whose checksum fails is dropped and the
    search resumes one byte after its sync (a false sync inside garbage must not swallow the real
    packet after it); a packet whose checksum holds but whose fields overrun its payload is dropped
    whole. Counts: `skipped_bytes` (bytes outside any candidate packet), `bad_checksums`, `bad_fields`.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._covered = 0
        """bytes at the start of the buffer that belong to a rejected candidate (not counted as skipped)"""
        self.skipped_bytes = 0
        self.bad_checksums = 0
        self.bad_fields = 0

    def feed(self, chunk: bytes) -> list[Packet]:
        """The packets that `chunk` completes, in stream order."""
        buf = self._buf
        buf += chunk
        packets: list[Packet] = []
        pos = 0
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # keep a trailing first sync byte: its second may come in the next chunk
                keep = 1 if buf[-1:] == SYNC[:1] else 0
                self._skip(pos, len(buf) - keep)
                pos = len(buf) - keep
                break
            self._skip(pos, start)
            pos = start
            if len(buf) - pos < HEADER_BYTES:
                break
            total = HEADER_BYTES + buf[pos + 3] + CHECKSUM_BYTES
            if len(buf) - pos < total:
                break
            body_end = pos + total - CHECKSUM_BYTES
            if checksum(buf[pos:body_end]) != buf[body_end : pos + total]:
                self.bad_checksums += 1
                self._covered = max(self._covered, pos + total)
                pos += 1
                continue
            fields = split_fields(buf[pos + HEADER_BYTES : body_end])
            if fields is None:
                self.bad_fields += 1
            else:
                packets.append(Packet(buf[pos + 2], fields))
            self._covered = max(self._covered, pos + total)
            pos += total
        del buf[:pos]
        self._covered = max(0, self._covered - pos)
        return packets

    def _skip(self, start: int, end: int) -> None:
        """Count the bytes in [start, end) that no candidate packet covered."""
        self.skipped_bytes += max(0, end - max(start, self._covered))
