"""The Atheros CSI Tool's log (AR9580 and kin, up to 3x3; 56 tones at 20 MHz, 114 at 40 MHz),
read through csiread.

Each record: a 2-byte length, then a 25-byte status (timestamp in microseconds, CSI length,
channel in MHz, PHY error, noise floor, rate, bandwidth, tones, Nr, Nc, RSSI and one per chain,
payload length), the CSI (10-bit signed imaginary then real parts, least significant bit first,
per tone, receive chain, transmit stream) and the payload. The log is written in the recording
host's byte order (a router's big-endian MIPS, or a little-endian PC): which one is found from
the first record's consistency."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources.frames import CsiFrames

LENGTH_BYTES = 2
STATUS_FORMAT = "QHHBBBBBBBBBBBH"
"""timestamp, csi_len, tx_channel (MHz), err_info, noise_floor, rate, bandwidth, tones, nr, nc,
rssi, rssi of chains 0-2, payload_len"""
STATUS_BYTES = struct.calcsize("<" + STATUS_FORMAT)
TONES = {0: 56, 1: 114}
"""tones per bandwidth code (0: 20 MHz, 1: 40 MHz)"""
BANDWIDTH_HZ = {0: 20e6, 1: 40e6}
BITS_PER_VALUE = 10


def subcarriers(tones: int) -> np.ndarray:
    """The tones' subcarrier indices, in increasing frequency as the standard orders them (the tool
    documents no other order): -28..28 without 0 at 20 MHz, -58..58 without -1, 0, 1 at 40."""
    half = tones // 2
    if tones == 56:
        return np.array([*range(-half, 0), *range(1, half + 1)])
    return np.array([*range(-half - 1, -1), *range(2, half + 2)])


def _status(head: bytes, endian: str) -> tuple[int, ...] | None:
    """The first record's status in this byte order, if it is consistent: its length, tones,
    chains and CSI length agree (None: not this order, or not an Atheros log)."""
    if len(head) < LENGTH_BYTES + STATUS_BYTES:
        return None
    (length,) = struct.unpack_from(endian + "H", head)
    s = struct.unpack_from(endian + STATUS_FORMAT, head, LENGTH_BYTES)
    _ts, csi_len, channel, _err, _noise, _rate, bw, tones, nr, nc, *_rssi, payload_len = s
    values = tones * nr * nc * 2
    ok = (
        bw in TONES
        and tones == TONES[bw]
        and 1 <= nr <= 3
        and 1 <= nc <= 3
        and csi_len == math.ceil(values * BITS_PER_VALUE / 8)
        and length == STATUS_BYTES + csi_len + payload_len
        and 2400 <= channel <= 6000
    )
    return s if ok else None


def looks_like(head: bytes) -> bool:
    """Whether these first bytes start an Atheros CSI Tool log (either byte order)."""
    return _status(head, "<") is not None or _status(head, ">") is not None


def read(path: Path) -> CsiFrames:
    """The log's records (all of the first record's shape; others are counted in `dropped`)."""
    import csiread

    data = path.read_bytes()
    head = data[: LENGTH_BYTES + STATUS_BYTES]
    endian = "<" if _status(head, "<") is not None else ">"
    first = _status(head, endian)
    if first is None:
        raise BadInput(f"{path}: not an Atheros CSI Tool log (its first record's header is not consistent)")
    tones, nr, nc = first[7], first[8], first[9]
    log = csiread.Atheros(str(path), nr, nc, tones=tones, if_report=False)
    log.read(endian="little" if endian == "<" else "big")
    count = int(log.count)
    consumed = int(np.sum(LENGTH_BYTES + STATUS_BYTES + log.csi_len[:count].astype(np.int64) + log.payload_len[:count]))
    if consumed != len(data):
        raise BadInput(
            f"{path}: truncated: record {count + 1} starts at byte {consumed:,} and the file ends "
            f"{len(data) - consumed:,} bytes into it"
        )
    same = (log.num_tones[:count] == tones) & (log.nr[:count] == nr) & (log.nc[:count] == nc)
    keep = np.flatnonzero(same)
    dropped = {f"records of another shape than the first's ({tones} tones, {nr}x{nc})": int(count - len(keep))}
    noise = log.noise_floor[keep].astype(np.int8).astype(np.float64)  # 0: the driver did not fill it in
    rssi = np.stack([log.rssi_1, log.rssi_2, log.rssi_3], axis=1)[keep, :nr].astype(np.float64)
    return CsiFrames(
        source="atheros",
        csi=np.asarray(log.csi[keep], dtype=np.complex128),
        subcarriers=subcarriers(tones),
        bandwidth_hz=BANDWIDTH_HZ[first[6]],
        centre_freq_hz=log.tx_channel[keep].astype(np.float64) * 1e6,
        timestamp_ns=log.timestamp[keep].astype(np.int64) * 1000,
        rssi_db=rssi,
        noise_dbm=np.where(noise == 0, np.nan, noise),
        mac=np.zeros((len(keep), 6), np.uint8),
        sequence=np.full(len(keep), -1),
        dropped={why: n for why, n in dropped.items() if n},
    )
