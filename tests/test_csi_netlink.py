"""`csi_netlink` fed through a socketpair with the connector datagrams the kernel would send, real records inside."""

from __future__ import annotations

import socket
import struct
import threading

import pytest
from helpers import reference_data

from rover.drivers.csi_netlink import (
    CN_IDX_IWLAGN,
    CsiNetlink,
    NetlinkFormatError,
    NetlinkParams,
    pack_datagram,
    parse_datagram,
)
from rover.operator import Emit


def log_records(data: bytes) -> list[bytes]:
    """The records of a CSI Tool log, split on their 2-byte big-endian lengths."""
    out, pos = [], 0
    while pos + 2 <= len(data):
        (n,) = struct.unpack_from(">H", data, pos)
        out.append(data[pos + 2 : pos + 2 + n])
        pos += 2 + n
    return out


def test_records_from_the_connector_are_published_and_logged_byte_exact(tmp_path):
    raw = (reference_data() / "csi" / "log.all_csi.6.7.6.dat").read_bytes()
    records = log_records(raw)
    kernel, ours = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    source = CsiNetlink(NetlinkParams(channel=149, log=str(tmp_path / "live.dat")), connect=lambda: ours)
    for i, record in enumerate(records):
        kernel.send(pack_datagram(record, seq=i))
        if i == 3:
            kernel.send(b"\x00" * 8)  # too short
            kernel.send(pack_datagram(record)[:-5] + b"")  # truncated
    stop = threading.Event()
    frames = []
    for item in source.run(stop):
        if isinstance(item, Emit):
            frames.append(item.msg)
            if len(frames) == len(records):
                stop.set()
    source.close()
    kernel.close()
    assert [bytes(f.bfee) for f in frames] == records
    assert all(f.channel == 149 for f in frames)
    stamps = [f.header.stamp.sec * 10**9 + f.header.stamp.nanosec for f in frames]
    assert stamps == sorted(stamps)
    assert source.drops == {"datagrams that are not CSI Tool records": 2}
    assert (tmp_path / "live.dat").read_bytes() == raw


def test_datagram_parsing_rejects_other_connectors():
    record = b"\xbb" + bytes(20)
    assert parse_datagram(pack_datagram(record)) == record
    other = bytearray(pack_datagram(record))
    struct.pack_into("=I", other, 16, CN_IDX_IWLAGN + 1)
    with pytest.raises(NetlinkFormatError, match="not the CSI Tool's 26:1"):
        parse_datagram(bytes(other))
