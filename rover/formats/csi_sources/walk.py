"""Records that each start with a header giving the length of what follows it (an Atheros log's
2-byte prefix, a pcap record's 16-byte header, a PicoScenes frame's 4-byte length): where they
start, and a file cut in the middle of its last one refused naming where."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from rover.errors import BadInput


def record_starts(
    path: Path, data: bytes, start: int, header: struct.Struct, length_field: int, unit: str
) -> np.ndarray:
    """The offsets of the records' headers from `start` on (field `length_field` of `header`: the
    bytes after the header); BadInput when the last runs past the end of `data`. A walk over the
    lengths, once per file: a length is known only once the record before it is."""
    starts = []
    at = start
    while at + header.size <= len(data):
        after = at + header.size + header.unpack_from(data, at)[length_field]
        if after > len(data):
            break
        starts.append(at)
        at = after
    if at != len(data):
        raise BadInput(
            f"{path}: truncated: {unit} {len(starts) + 1} starts at byte {at:,} and the file ends "
            f"{len(data) - at:,} bytes into it"
        )
    return np.array(starts, dtype=np.int64)
