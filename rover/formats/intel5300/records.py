"""The CSI Tool record format, what decoding, framing and encoding share: its constants, the header
layout and consistency, the antenna permutation, where each value's bits lie, and CsiRecords.

A CSI Tool log (`log_to_file` output) is a sequence of records, each a 2-byte big-endian length
and that many bytes: a code byte (0xBB for a beamforming report) and the notification. The
notification's header is little-endian `<IHHBBBBBbBBHH` (timestamp_low, bfee_count, reserved,
Nrx, Ntx, rssi_a/b/c, noise, agc, antenna_sel, len, fake_rate_n_flags); the CSI follows at byte
20, for each of 30 subcarriers 3 unused bits then Nrx*Ntx complex values (rx-major, tx fastest),
each an int8 real and an int8 imaginary part, packed at arbitrary bit offsets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

BFEE_CODE = 0xBB
"""Code byte of a beamforming report, the only record that carries CSI."""
FRAME_CODE = 0xC1
"""Code byte of a received frame's header and payload, the other record real logs interleave
with beamforming reports; framing trusts it as a record start only when the next one follows it."""
LENGTH_BYTES = 2
HEADER_BYTES = 20
"""Notification header; the CSI payload follows it."""
RECORD_HEAD_BYTES = LENGTH_BYTES + 1 + HEADER_BYTES
"""Bytes from a record's start that tell whether a consistent beamforming record starts there."""
SUBCARRIERS = 30
MAX_CHAINS = 3
"""The Intel 5300 has three receive chains and sends at most three streams."""
NOISE_UNKNOWN_DB = -127
"""Noise value the firmware reports when it has no estimate..."""
NOISE_FLOOR_DB = -92
"""...which get_scaled_csi replaces by this floor (dBm)."""
RSS_OFFSET_DB = 44
"""get_total_rss: RSS (dBm) = power sum of the chains' RSSI (dB) - 44 - AGC (dB)."""
NTX_AMPLITUDE_CORRECTION = np.array([1.0, 1.0, np.sqrt(2.0), np.sqrt(10 ** (4.5 / 10))])
"""get_scaled_csi's correction by Ntx (index): 3 dB in power for two streams, 4.5 dB for three."""
_PERM_SUM_BY_NRX = np.array([0, 1, 3, 6])
"""What read_bf_file expects the three perm entries to sum to for 1, 2, 3 receive chains."""

_HEADER = np.dtype(
    [
        ("timestamp_low", "<u4"),
        ("bfee_count", "<u2"),
        ("reserved", "<u2"),
        ("nrx", "u1"),
        ("ntx", "u1"),
        ("rssi_a", "u1"),
        ("rssi_b", "u1"),
        ("rssi_c", "u1"),
        ("noise", "i1"),
        ("agc", "u1"),
        ("antenna_sel", "u1"),
        ("len", "<u2"),
        ("rate", "<u2"),
    ]
)
assert _HEADER.itemsize == HEADER_BYTES and _HEADER.fields is not None
_NRX_AT, _NTX_AT, _LEN_AT = (1 + _HEADER.fields[name][1] for name in ("nrx", "ntx", "len"))
"""Offsets of header fields from a record's code byte."""
_RSSI_AT = _HEADER.fields["rssi_a"][1]
"""Offset of rssi_a (rssi_b and rssi_c follow it) in the header."""


class CsiFormatError(ValueError):
    """Values that cannot be written as a CSI Tool record (encoding).

    Decoding never raises on malformed bytes: they are skipped and counted instead.
    """


@dataclass
class CsiRecords:
    """Decoded beamforming records, one row per record.

    `csi` is complex128 of shape (N, 30, Nrx_max, Ntx_max), antennas in the order the permutation
    gives them, zero where a record has fewer chains or streams than the largest one.
    """

    timestamp_low: np.ndarray
    """(N,) uint32, microseconds, the NIC's clock (wraps)."""
    bfee_count: np.ndarray
    """(N,) uint16"""
    nrx: np.ndarray
    """(N,) uint8"""
    ntx: np.ndarray
    """(N,) uint8"""
    rssi: np.ndarray
    """(N, 3) uint8, rssi_a/b/c in dB (0: chain not measured)."""
    noise: np.ndarray
    """(N,) int8, dBm, as in the header (-127: unknown; the scaling then takes -92)."""
    agc: np.ndarray
    """(N,) uint8, dB"""
    antenna_sel: np.ndarray
    """(N,) uint8"""
    perm: np.ndarray
    """(N, 3) uint8, 1-based: raw chain k goes to antenna perm[k], as read_bfee reports it."""
    rate: np.ndarray
    """(N,) uint16, fake_rate_n_flags"""
    csi: np.ndarray
    """(N, 30, Nrx_max, Ntx_max) complex128: subcarrier, receive antenna, transmit stream."""
    offset: np.ndarray
    """(N,) int64: byte offset of each record's length prefix in the log; for decode_bfee the index
    of the input each row came from."""
    scaled: bool
    """csi as get_scaled_csi gives it (SNR units), else the raw int8 values."""
    n_skipped: int = 0
    """Records with other codes than 0xBB (e.g. 0xC1), skipped."""
    n_corrupt: int = 0
    """Beamforming records not decoded: `len` disagrees with Nrx/Ntx, Nrx or Ntx out of range, or
    the record was cut short."""
    n_garbage_bytes: int = 0
    """Bytes that belonged to no record, skipped while resynchronizing."""

    def __len__(self) -> int:
        return len(self.bfee_count)


@dataclass(frozen=True)
class LogCounts:
    """What framing a log skipped, besides the beamforming records it found."""

    n_skipped: int
    n_corrupt: int
    n_garbage_bytes: int


def payload_bytes(nrx: np.ndarray | int, ntx: np.ndarray | int) -> np.ndarray | int:
    """CSI payload length (`len`) that Nrx x Ntx streams take: 30 x (3 + 16 Nrx Ntx) bits, in bytes."""
    return (SUBCARRIERS * (nrx * ntx * 16 + 3) + 7) // 8


def antenna_perm(antenna_sel: ArrayLike) -> np.ndarray:
    """perm (..., 3), 1-based, as read_bfee derives it: two bits of antenna_sel per chain."""
    sel = np.asarray(antenna_sel, dtype=np.int64)[..., None]
    return ((sel >> (2 * np.arange(MAX_CHAINS))) & 3) + 1


def _antenna_sources(perm: np.ndarray, nrx: np.ndarray) -> np.ndarray:
    """(N, 3): the raw chain each antenna reads, as read_bf_file arranges the chains.

    read_bf_file scatters chain k to antenna perm[k] (`csi(:, perm(1:Nrx), :) = csi(:, 1:Nrx, :)`)
    when the three perm entries sum to 1+..+Nrx. Otherwise it repairs perm first: for two chains
    to [1 2] or [2 1] by the order of the first two entries, for three to [1 2 3] if all entries are
    1, else the third entry becomes 6 minus the other two. Where two chains go to one antenna the
    later one wins (MATLAB's assignment order) and an antenna no chain goes to keeps its own.
    One chain is never permuted; a perm that would reach outside antennas 1..Nrx (MATLAB would
    widen the matrix or fail) leaves the chains in order.
    """
    p = perm.astype(np.int64)
    n = len(p)
    nrx = nrx.astype(np.int64)
    trusted = p.sum(axis=1) == _PERM_SUM_BY_NRX[nrx]
    two = np.where((p[:, 1] >= p[:, 0])[:, None], [1, 2, 3], [2, 1, 3])
    three = np.stack([p[:, 0], p[:, 1], 6 - p[:, 0] - p[:, 1]], axis=1)
    three[(p == 1).all(axis=1)] = [1, 2, 3]
    target = np.where(trusted[:, None], p, np.where((nrx == 2)[:, None], two, three)) - 1
    used = np.arange(MAX_CHAINS) < nrx[:, None]
    permuted = (nrx > 1) & ((~used | ((target >= 0) & (target < nrx[:, None]))).all(axis=1))
    sources = np.tile(np.arange(MAX_CHAINS), (n, 1))
    for chain in range(MAX_CHAINS):
        rows = np.flatnonzero(permuted & used[:, chain])
        sources[rows, target[rows, chain]] = chain
    return sources


def _value_bits(nrx: int, ntx: int, sources: tuple[int, ...]) -> np.ndarray:
    """Payload bit offset of every int8 of one record shape, in output order.

    Output order is (subcarrier, antenna, stream, real/imaginary). The value of raw chain c,
    stream t on subcarrier i starts at bit 3(i+1) + 16(i*Nrx*Ntx + c*Ntx + t); its imaginary
    part 8 bits later. Reading antenna a from chain sources[a] applies the permutation for free.
    """
    i = np.arange(SUBCARRIERS)[:, None, None, None]
    chain = np.array(sources[:nrx])[None, :, None, None]
    stream = np.arange(ntx)[None, None, :, None]
    part = np.arange(2)[None, None, None, :]
    bits: np.ndarray = (3 * (i + 1) + 16 * (i * nrx * ntx + chain * ntx + stream) + 8 * part).ravel()
    return bits


def _consistent_headers(buf: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Whether the beamforming header whose code byte is at each of `at` (all in range) is decodable:
    1..3 chains and streams, and `len` equal to what they take."""
    nrx = buf[at + _NRX_AT].astype(np.int64)
    ntx = buf[at + _NTX_AT].astype(np.int64)
    in_range = (nrx >= 1) & (nrx <= MAX_CHAINS) & (ntx >= 1) & (ntx <= MAX_CHAINS)
    consistent: np.ndarray = in_range & (_len_field(buf, at) == payload_bytes(nrx, ntx))
    return consistent


def _len_field(buf: np.ndarray, at: np.ndarray | int) -> np.ndarray:
    """The `len` header field of the records whose code bytes are at `at`."""
    value: np.ndarray = buf[at + _LEN_AT].astype(np.int64) | (buf[at + _LEN_AT + 1].astype(np.int64) << 8)
    return value


def _empty_records(scaled: bool) -> CsiRecords:
    """No records: every array with length 0 and its usual dtype; csi (0, 30, 0, 0)."""

    def none(name: str) -> np.ndarray:
        return np.zeros(0, dtype=_HEADER[name])

    return CsiRecords(
        none("timestamp_low"),
        none("bfee_count"),
        none("nrx"),
        none("ntx"),
        np.zeros((0, 3), np.uint8),
        none("noise"),
        none("agc"),
        none("antenna_sel"),
        np.zeros((0, 3), np.uint8),
        none("rate"),
        np.zeros((0, SUBCARRIERS, 0, 0), np.complex128),
        offset=np.zeros(0, np.int64),
        scaled=scaled,
    )


def concat(parts: Sequence[CsiRecords]) -> CsiRecords:
    """Join decoded batches (e.g. the chunks of a stream) into one, padding CSI to the largest shape."""
    parts = list(parts)
    if not parts:
        return _empty_records(scaled=True)
    nrx_max = max(p.csi.shape[2] for p in parts)
    ntx_max = max(p.csi.shape[3] for p in parts)
    csi = [np.pad(p.csi, ((0, 0), (0, 0), (0, nrx_max - p.csi.shape[2]), (0, ntx_max - p.csi.shape[3]))) for p in parts]
    joined: dict[str, Any] = {
        f.name: np.concatenate([getattr(p, f.name) for p in parts])
        for f in fields(CsiRecords)
        if f.name not in ("csi", "scaled") and not f.name.startswith("n_")
    }
    counts = {name: sum(getattr(p, name) for p in parts) for name in ("n_skipped", "n_corrupt", "n_garbage_bytes")}
    return CsiRecords(**joined, csi=np.concatenate(csi), scaled=parts[0].scaled, **counts)
