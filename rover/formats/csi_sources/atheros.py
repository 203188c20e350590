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
from rover.formats.csi_sources.walk import record_starts

LENGTH_BYTES = 2
STATUS_FORMAT = "QHHBBBBBBBBBBBH"
"""timestamp, csi_len, tx_channel (MHz), err_info, noise_floor, rate, bandwidth, tones, nr, nc,
rssi, rssi of chains 0-2, payload_len"""
STATUS_BYTES = struct.calcsize("<" + STATUS_FORMAT)
TONES = {0: 56, 1: 114}
"""tones per bandwidth code (0: 20 MHz, 1: 40 MHz)"""
BANDWIDTH_HZ = {0: 20e6, 1: 40e6}
BITS_PER_VALUE = 10
MAX_FIELD_BYTES = 4096
"""the largest CSI or payload of a record csiread holds (its buffers)"""


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


def _statuses(data: bytes, offsets: np.ndarray, endian: str) -> np.ndarray:
    """Every record's length prefix and status, as one structured array."""
    fields = [("length", "H"), ("timestamp", "Q"), ("csi_len", "H"), ("tx_channel", "H")]
    fields += [(name, "B") for name in ("err", "noise", "rate", "bw", "tones", "nr", "nc", "rssi", "r0", "r1", "r2")]
    fields += [("payload_len", "H")]
    dtype = np.dtype([(name, ("<" if endian == "<" else ">") + code) for name, code in fields])
    buf = np.frombuffer(data, np.uint8)
    raw = buf[offsets[:, None] + np.arange(dtype.itemsize)] if len(offsets) else np.zeros((0, dtype.itemsize), np.uint8)
    return np.ascontiguousarray(raw).view(dtype).ravel()


def _check(path: Path, status: np.ndarray, offsets: np.ndarray) -> None:
    """BadInput naming the first record whose status is not consistent, or whose sizes csiread
    cannot hold (CSI or payload over MAX_FIELD_BYTES: an A-MSDU's payload, say)."""
    tones_of_bw = np.where(status["bw"] == 0, TONES[0], TONES[1])
    need = np.ceil(status["tones"].astype(np.int64) * status["nr"] * status["nc"] * 2 * BITS_PER_VALUE / 8)
    bad = (
        (status["bw"] > 1)
        | (status["tones"] != tones_of_bw)
        | (status["nr"] < 1) | (status["nr"] > 3) | (status["nc"] < 1) | (status["nc"] > 3)
        | (status["csi_len"] != need)
        | (status["length"] != STATUS_BYTES + status["csi_len"].astype(np.int64) + status["payload_len"])
    )  # fmt: skip
    big = (status["csi_len"] > MAX_FIELD_BYTES) | (status["payload_len"] > MAX_FIELD_BYTES)
    if bad.any() or big.any():
        k = int(np.flatnonzero(bad | big)[0])
        why = "its header is not consistent" if bad[k] else f"its payload or CSI is over {MAX_FIELD_BYTES:,} bytes"
        raise BadInput(f"{path}: record {k + 1} (at byte {int(offsets[k]):,}): {why}")
    if len(np.unique(status["tones"])) > 1:
        raise BadInput(f"{path}: its records mix 56 and 114 tones (20 and 40 MHz): split the log by bandwidth")


def read(path: Path) -> CsiFrames:
    """The log's records of its commonest chains and streams (the others counted in `dropped`: the
    transmitter's streams follow its rate)."""
    import csiread

    data = path.read_bytes()
    head = data[: LENGTH_BYTES + STATUS_BYTES]
    endian = "<" if _status(head, "<") is not None else ">"
    if _status(head, endian) is None:
        raise BadInput(f"{path}: not an Atheros CSI Tool log (its first record's header is not consistent)")
    offsets = record_starts(path, data, 0, struct.Struct(endian + "H"), 0, "record")
    status = _statuses(data, offsets, endian)
    _check(path, status, offsets)
    shapes, counts = np.unique(np.stack([status["nr"], status["nc"]], axis=1), axis=0, return_counts=True)
    nr, nc = (int(v) for v in shapes[np.lexsort((shapes[:, 0], counts))[-1]])  # the commonest; more chains on a tie
    tones = int(status["tones"][0])
    log = csiread.Atheros(str(path), 3, 3, tones=tones, if_report=False, bufsize=len(offsets))
    log.read(endian="little" if endian == "<" else "big")
    if int(log.count) != len(offsets):
        raise BadInput(f"{path}: csiread read {log.count} of its {len(offsets)} records")
    keep = np.flatnonzero((status["nr"] == nr) & (status["nc"] == nc))
    dropped = {f"records of other chains or streams than the commonest ({nr}x{nc})": len(offsets) - len(keep)}
    noise = status["noise"][keep].astype(np.int8).astype(np.float64)  # 0: the driver did not fill it in
    rssi = np.stack([status["r0"], status["r1"], status["r2"]], axis=1)[keep, :nr].astype(np.float64)
    return CsiFrames(
        source="atheros",
        csi=np.asarray(log.csi[keep][:, :, :nr, :nc], dtype=np.complex128),
        subcarriers=subcarriers(tones),
        bandwidth_hz=BANDWIDTH_HZ[int(status["bw"][0])],
        centre_freq_hz=status["tx_channel"][keep].astype(np.float64) * 1e6,
        timestamp_ns=status["timestamp"][keep].astype(np.int64) * 1000,
        rssi_db=rssi,
        noise_dbm=np.where(noise == 0, np.nan, noise),
        mac=np.zeros((len(keep), 6), np.uint8),
        sequence=np.full(len(keep), -1),
        dropped={why: n for why, n in dropped.items() if n},
    )
