"""rmw_zenoh wire bytes written by hand from its documentation, for tests: never built with
rover.drivers.rmw_zenoh, so they check it rather than agree with it."""

from __future__ import annotations

import struct


def legacy_attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """The labelled 77-byte attachment of rmw_zenoh_cpp 0.2.0-0.2.3."""
    return (
        b"\x0fsequence_number"
        + struct.pack("<q", seq)
        + b"\x10source_timestamp"
        + struct.pack("<q", stamp_ns)
        + b"\x0asource_gid\x10"
        + gid
    )
