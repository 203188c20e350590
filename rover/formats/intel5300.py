"""Intel 5300 CSI Tool records: framing, bit-exact decoding and scaling, vectorized over records.

A CSI Tool log (`log_to_file` output) is a sequence of records, each a 2-byte big-endian length
and that many bytes: a code byte (0xBB for a beamforming report) and the notification. The
notification's header is little-endian `<IHHBBBBBbBBHH` (timestamp_low, bfee_count, reserved,
Nrx, Ntx, rssi_a/b/c, noise, agc, antenna_sel, len, fake_rate_n_flags); the CSI follows at byte
20, for each of 30 subcarriers 3 unused bits then Nrx*Ntx complex values (rx-major, tx fastest),
each an int8 real and an int8 imaginary part, packed at arbitrary bit offsets.

The results equal those of the tool's own `read_bf_file.m` (raw CSI, antenna permutation) and
`get_scaled_csi.m` (CSI in units of the noise). Nothing decoded here raises on bad bytes:
records with other codes, corrupt records and garbage are skipped and counted, and framing
resynchronizes on the next consistent beamforming header, the same whether a log is decoded
whole or fed in chunks (StreamDecoder).

A record cut short (bytes lost from its end or middle) still claims its full length, so it would
take the first bytes of what follows as its tail and decode to plausible, wrong CSI. Framing
tells it by what lies at its claimed end: the record is whole when a record provably starts there
(a consistent beamforming header, a 0xC1 record ending where the next such header starts, or the
end of the log); when instead one provably starts inside it, it was cut short, counts as corrupt,
and framing resumes there; one that runs past the end of the log is corrupt too. What framing
cannot tell, and takes as it is (counted valid, header intact): a record cut short and followed
by bytes that start no provable record (garbage, a record that lost its own head, a 0xC1 record
not followed by a beamforming one), or one that lost exactly as many bytes as the 0xC1 record
after it holds (its claimed end lands on the next record). Its tail is then those bytes: within
22 bytes that alters the last 1-2 of 30 subcarriers of a 3x2 or 3x3 record (4 of 3x1, 9 of 1x1),
beyond that as many subcarriers as the bytes replaced carried; what followed it is skipped up to
the next record. Streams pay a delay: a record is handed out once the 23 bytes after it (after a
0xC1 record following it, 23 more) are present, or when the stream ends.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from enum import Enum
from functools import lru_cache
from pathlib import Path
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
_DB = np.arange(256)
_RSSI_MW = np.where(_DB != 0, 10 ** (_DB / 10), 0.0)
"""a chain's RSSI byte (dB) as power, 0 for a chain without one: get_total_rss's terms, looked up"""
_NOISE_DB = _DB.astype(np.uint8).view(np.int8).astype(np.float64)
_NOISE_MW = 10 ** (np.where(_NOISE_DB == NOISE_UNKNOWN_DB, NOISE_FLOOR_DB, _NOISE_DB) / 10)
"""the noise byte (int8 dBm, read as uint8) as thermal noise power, the unknown value at the floor"""
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


# ---------------------------------------------------------------------------------------------
# Decoding records already framed (all vectorized over records)


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


def _windows(buf: np.ndarray, width: int) -> np.ndarray:
    """Every `width` consecutive bytes of `buf`, one row per start: a read-only view, no copy
    (what sliding_window_view gives, at a tenth of its cost: a log decodes a few groups per call)."""
    return np.ndarray((max(len(buf) - width + 1, 0), width), np.uint8, buf, 0, (1, 1))


@lru_cache(maxsize=1)
def _layout_tables() -> tuple[np.ndarray, np.ndarray]:
    """perm (256, 3) of every antenna_sel, and the sources (1024, 3) of every antenna_sel x 4 + Nrx:
    what antenna_perm and _antenna_sources give, looked up per record instead of computed."""
    sel = np.arange(256)
    perm = antenna_perm(sel).astype(np.uint8)
    nrx = np.tile(np.arange(4), 256)
    sources = _antenna_sources(np.repeat(perm, 4, axis=0), np.maximum(nrx, 1))
    for table in (perm, sources):
        table.setflags(write=False)
    return perm, sources


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


@dataclass(frozen=True)
class _ByteLayout:
    """Where _unpack finds each value of one record shape in a record's payload bytes."""

    span: int
    """payload bytes read"""
    byte: np.ndarray
    """the byte each value starts in"""
    down: np.ndarray
    """bits to shift the pair of that byte and the next right by (uint16: the offset's remainder)"""


@lru_cache(maxsize=256)
def _byte_layout(nrx: int, ntx: int, sources: tuple[int, ...]) -> _ByteLayout:
    """The layout for one record shape and antenna order (cached: a log has a handful)."""
    bit = _value_bits(nrx, ntx, sources)
    byte = bit >> 3
    down = (bit & 7).astype(np.uint16)
    for array in (byte, down):
        array.setflags(write=False)
    return _ByteLayout(int(byte.max()) + 2, byte, down)


UNPACK_BLOCK_BYTES = 1 << 19
"""values unpacked per step: the step's intermediates stay in the CPU's cache (a whole 50,000-record
log at once went through memory several times: 3x2 records took 60% longer)"""


def _pairs(buf: np.ndarray, width: int) -> np.ndarray:
    """Every `width` consecutive little-endian byte pairs of `buf` (pair j of row p: bytes p + j and
    p + j + 1), one row per start: an unaligned read-only view, no copy."""
    return np.ndarray((max(len(buf) - width, 0), width), "<u2", buf, 0, (1, 1))


def _unpack(
    out: np.ndarray,
    rows: np.ndarray | None,
    buf: np.ndarray,
    payload_at: np.ndarray,
    nrx: int,
    ntx: int,
    sources: tuple[int, ...],
) -> None:
    """Write the 30 * nrx * ntx * 2 CSI values (float64) of the records of one shape and antenna order
    whose payloads start at `payload_at` into out[rows] (out[:n] when `rows` is None).

    Each value is the byte at its bit offset shifted right by the offset's remainder, with the
    next byte's low bits above it, cut to int8 (what read_bfee.c does per value): the two bytes
    are read as one little-endian pair, shifted, and its low byte kept. Only the final store is
    float64.
    """
    layout = _byte_layout(nrx, ntx, sources)
    pairs = _pairs(buf, layout.span - 1)
    n, width = len(payload_at), len(layout.byte)
    block = max(1, min(n, UNPACK_BLOCK_BYTES // width))
    values = np.empty((block, width), "<u2")
    for i in range(0, n, block):
        payloads = pairs[payload_at[i : i + block]]
        v = values[: len(payloads)]
        np.take(payloads, layout.byte, axis=1, out=v)
        np.right_shift(v, layout.down, out=v)
        target = slice(i, i + len(payloads)) if rows is None else rows[i : i + len(payloads)]
        out[target] = v.view(np.uint8)[:, 0::2].view(np.int8)


def _scale_factors(
    power: np.ndarray, rssi: np.ndarray, noise: np.ndarray, agc: np.ndarray, nrx: np.ndarray, ntx: np.ndarray
) -> np.ndarray:
    """get_scaled_csi's factor per record, given the raw CSI power sum(|csi|^2) of each record.

    Total RSS (dBm) = 10 log10(sum of 10^(rssi/10) over the nonzero rssi_a/b/c) - 44 - AGC; the
    CSI is scaled so its mean power per subcarrier matches it, then divided by the noise: thermal
    (10^(noise/10), noise -127 read as -92) plus quantization error (that scale x Nrx x Ntx).
    Records with zero RSSI or zero CSI give 0 or NaN, as in MATLAB.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        rssi_mw = _RSSI_MW[rssi].sum(axis=1)
        rss_dbm = 10 * np.log10(rssi_mw) - RSS_OFFSET_DB - agc.astype(np.float64)
        scale = 10 ** (rss_dbm / 10) / (power / SUBCARRIERS)
        total_noise = _NOISE_MW[noise.view(np.uint8)] + scale * (nrx.astype(np.float64) * ntx)
        amplitude: np.ndarray = np.sqrt(scale / total_noise) * NTX_AMPLITUDE_CORRECTION[ntx]
        return amplitude


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


def _decode(buf: np.ndarray, code_at: np.ndarray, scaled: bool) -> CsiRecords:
    """Decode the beamforming records whose code bytes are at `code_at` (consistent and complete).

    Records are grouped by antenna_sel, Nrx and Ntx (their values' layout), a handful of groups
    at most, each unpacked straight into its rows of the result; the scaling is over all records.
    """
    n = len(code_at)
    if n == 0:
        return _empty_records(scaled)
    head_bytes = _windows(buf, HEADER_BYTES)[code_at + 1]
    head = head_bytes.view(_HEADER).reshape(n)
    nrx, ntx = head["nrx"], head["ntx"]
    perm_table, source_table = _layout_tables()
    perm = perm_table[head["antenna_sel"]]
    # records of one (antenna_sel, Nrx, Ntx) share their layout: a small integer per record
    layout = (head["antenna_sel"].astype(np.int64) * 4 + nrx) * 4 + ntx
    kinds = layout[:1] if np.all(layout == layout[0]) else np.flatnonzero(np.bincount(layout, minlength=256 * 16))
    rssi = head_bytes[:, _RSSI_AT : _RSSI_AT + 3].copy()  # rssi_a, rssi_b, rssi_c
    shape = (int(nrx.max()), int(ntx.max()))
    csi = np.zeros((n, SUBCARRIERS, *shape), dtype=np.complex128)
    flat = csi.reshape(n, -1).view(np.float64)
    for kind in kinds.tolist():
        r, t = (kind >> 2) & 3, kind & 3
        rows = None if len(kinds) == 1 else np.flatnonzero(layout == kind)
        payload_at = (code_at if rows is None else code_at[rows]) + 1 + HEADER_BYTES
        sources = tuple(source_table[kind >> 2].tolist())
        if (r, t) == shape:
            _unpack(flat, rows, buf, payload_at, r, t, sources)
        else:  # a smaller shape goes into the corner of each record's (30, Nrx, Ntx)
            values = np.empty((len(payload_at), SUBCARRIERS * r * t * 2))
            _unpack(values, None, buf, payload_at, r, t, sources)
            csi[rows, :, :r, :t] = values.view(np.complex128).reshape(-1, SUBCARRIERS, r, t)
    if scaled:
        flat *= _scale_factors(np.einsum("ij,ij->i", flat, flat), rssi, head["noise"], head["agc"], nrx, ntx)[:, None]
    return CsiRecords(
        head["timestamp_low"].copy(),
        head["bfee_count"].copy(),
        nrx.copy(),
        ntx.copy(),
        rssi,
        head["noise"].copy(),
        head["agc"].copy(),
        head["antenna_sel"].copy(),
        perm,
        head["rate"].copy(),
        csi,
        offset=code_at - LENGTH_BYTES,
        scaled=scaled,
    )


# ---------------------------------------------------------------------------------------------
# Framing: where the records of a byte stream are


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


def _valid_starts(buf: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Offsets p in [lo, hi) where a complete-headed, consistent beamforming record starts: its
    length prefix at p, code 0xBB, a decodable header and a length that fits the header."""
    hi = min(hi, len(buf) - RECORD_HEAD_BYTES + 1)
    if hi <= lo:
        return np.zeros(0, dtype=np.int64)
    p = lo + np.flatnonzero(buf[lo + LENGTH_BYTES : hi + LENGTH_BYTES] == BFEE_CODE)
    # the length prefix agreeing with `len` first: it leaves about one in 65,536 of the 0xBB bytes
    # inside payloads, so the header's other checks look at records only
    length = (buf[p].astype(np.int32) << 8) | buf[p + 1]
    field = buf[p + LENGTH_BYTES + _LEN_AT].astype(np.int32) | (
        buf[p + LENGTH_BYTES + _LEN_AT + 1].astype(np.int32) << 8
    )
    p = p[length == 1 + HEADER_BYTES + field]
    found: np.ndarray = p[_consistent_headers(buf, p + LENGTH_BYTES)]
    return found


@dataclass
class _Cursor:
    """Where framing stands between calls, so a log fed in chunks is framed as the whole log.

    `pending` is set after a record is framed that was not proven whole yet: it ends at `pos`,
    and the bytes after `pos` decide whether it was whole or cut short (_FramingPass._settle).
    """

    pos: int = 0
    scanning: bool = False
    """Inside garbage: look for the next consistent beamforming header."""
    pending: int | None = None
    """Start of the record framed last, still to settle; it ends at `pos`."""
    pending_kind: _Kind | None = None

    def keep_from(self) -> int:
        """First byte still needed."""
        return self.pos if self.pending is None else min(self.pos, self.pending)

    def rebase(self, shift: int) -> None:
        self.pos -= shift
        if self.pending is not None:
            self.pending -= shift


@dataclass
class _Framing:
    """Records found by one framing pass, and what was skipped."""

    bfee_runs: list[np.ndarray] = field(default_factory=list)
    """offsets of beamforming records' length prefixes, in runs"""
    skipped: int = 0
    corrupt: int = 0
    garbage: int = 0

    def offsets(self) -> np.ndarray:
        return np.concatenate(self.bfee_runs) if self.bfee_runs else np.zeros(0, dtype=np.int64)


class _Kind(Enum):
    """What the bytes at a record boundary frame as."""

    BFEE = "a consistent beamforming record"
    CORRUPT = "a 0xBB record whose len disagrees with Nrx/Ntx"
    OTHER = "a record with another code"
    NONE = "no record: garbage"


class _FramingPass:
    """One pass of framing over the bytes present, from a cursor.

    At a record boundary the next bytes are taken as a record if they frame as one (see _Kind).
    A record is refused when a consistent beamforming header lies wholly inside it: it was cut
    short, and the one inside is what follows. One cut short by fewer bytes than a header is
    settled by what follows its claimed end (_settle) before it is counted or handed out.
    Anything else starts garbage, skipped up to the next consistent beamforming header, so no
    valid record after damage is lost. Every decision uses only bytes present (or knows, when
    `final`, that none follow), so chunking never changes the result. Runs of back-to-back
    valid records, the usual case, are taken in one step, and so are runs whose beamforming
    records are each followed by one record of FRAME_CODE (real logs of the CSI Tool interleave
    them: LGTM's alternate 0xBB and 0xC1), so the Python loop turns once per damage, not per record.
    """

    def __init__(self, buf: np.ndarray, cur: _Cursor, final: bool):
        self.buf, self.cur, self.final = buf, cur, final
        self.end = len(buf)
        self.decided = self.end if final else self.end - RECORD_HEAD_BYTES + 1
        """Positions below this are known to start a valid record or not."""
        self.starts = _valid_starts(buf, cur.keep_from(), self.decided)
        stops = self.starts + LENGTH_BYTES + ((buf[self.starts].astype(np.int64) << 8) | buf[self.starts + 1])
        gaps = np.flatnonzero(stops[:-1] != self.starts[1:])
        bridged = self._bridged(stops[gaps], self.starts[gaps + 1])
        self.breaks = gaps[~bridged]
        """i where record i does not end where record i + 1 starts, nor where one FRAME_CODE record
        that ends there starts"""
        self.bridges = gaps[bridged]
        """i where one FRAME_CODE record lies between record i and record i + 1"""
        self.out = _Framing()

    def _bridged(self, stop: np.ndarray, nxt: np.ndarray) -> np.ndarray:
        """Whether a FRAME_CODE record starts at each `stop` and ends at the matching `nxt`.

        Framed one by one, such a record proves the beamforming record before it whole (_chains)
        and is then skipped as a record of another code, proven whole by the start at `nxt`: in a
        run it counts as one skipped record and changes nothing else. No valid start lies between
        `stop` and `nxt` (they are consecutive starts' neighbours) and both are decided."""
        buf = self.buf
        fits = stop + LENGTH_BYTES + 1 <= nxt
        at = np.where(fits, stop, 0)
        length = (buf[at].astype(np.int64) << 8) | buf[at + 1]
        found: np.ndarray = fits & (buf[at + LENGTH_BYTES] == FRAME_CODE) & (at + LENGTH_BYTES + length == nxt)
        return found

    def run(self) -> _Framing:
        """Advance the cursor as far as the bytes present decide."""
        cur = self.cur
        while True:
            if cur.pending is not None and not self._settle():
                return self.out
            if cur.scanning and not self._scan():
                return self.out
            k = int(self.starts.searchsorted(cur.pos))
            is_start = k < len(self.starts) and self.starts[k] == cur.pos
            if is_start:
                b = int(self.breaks.searchsorted(k))
                last = int(self.breaks[b]) if b < len(self.breaks) else len(self.starts) - 1
                if last > k:
                    self.out.bfee_runs.append(self.starts[k:last])
                    self.out.skipped += int(np.searchsorted(self.bridges, last) - np.searchsorted(self.bridges, k))
                    cur.pos = int(self.starts[last])
            if not self._one(is_start):
                return self.out

    def _first_start(self, at: int) -> int | None:
        k = int(self.starts.searchsorted(at))
        return int(self.starts[k]) if k < len(self.starts) else None

    def _is_start(self, at: int) -> bool:
        """Whether a consistent beamforming record starts at `at` (decided: `at` below self.decided)."""
        return self._first_start(at) == at

    def _chains(self, at: int) -> bool | None:
        """Whether the framing of what follows proves a record starts at `at`; None when that needs
        bytes not present yet.

        Proof is the end of the log, a consistent beamforming header at `at`, or a frame record
        (FRAME_CODE) at `at` that ends where the first such header after it starts, or where the
        log ends with none in between.
        """
        if self.final and at == self.end:
            return True
        if not (self.final or at < self.decided):
            return None
        if self._is_start(at):
            return True
        buf = self.buf
        if self.end - at < LENGTH_BYTES + 1 or buf[at + LENGTH_BYTES] != FRAME_CODE:
            return False
        length = (int(buf[at]) << 8) | int(buf[at + 1])
        stop = at + LENGTH_BYTES + length
        if length < 1 or stop > self.end:
            return False if self.final or length < 1 else None
        if self.final and stop == self.end:
            return self._first_start(at + 1) is None
        if not (self.final or stop < self.decided):
            return None
        return self._first_start(at + 1) == stop

    def _settle(self) -> bool:
        """Count or hand out the pending record, once the bytes after it tell whether it was whole;
        False when that needs bytes not present yet.

        A record cut short still claims its full length, so it seems to end inside what follows
        it. It was whole when a record provably starts
        where it ends (_chains). Otherwise, when one provably starts inside it (a beamforming
        header, then within its last RECORD_HEAD_BYTES - 1 bytes, else _one refused it already),
        it was cut short: it counts as corrupt (garbage if not a beamforming record) and framing
        resumes at the first such start. When neither, nothing tells, and it is taken as it is.
        """
        cur, out, buf = self.cur, self.out, self.buf
        p, kind, stop = cur.pending, cur.pending_kind, cur.pos
        assert p is not None
        whole = self._chains(stop)
        if whole is None:
            return False
        resume = None
        if not whole:
            codes = buf[p + 1 + LENGTH_BYTES : min(stop + LENGTH_BYTES, self.end)]
            for q in (p + 1 + np.flatnonzero((codes == BFEE_CODE) | (codes == FRAME_CODE))).tolist():
                proven = self._chains(q)
                if proven is None:
                    return False
                if proven:
                    resume = q
                    break
        cur.pending = cur.pending_kind = None
        if resume is not None:
            if kind is _Kind.OTHER:
                out.garbage += resume - p
            else:
                out.corrupt += 1
            cur.pos = resume
        elif kind is _Kind.BFEE:
            out.bfee_runs.append(np.array([p], dtype=np.int64))
        elif kind is _Kind.CORRUPT:
            out.corrupt += 1
        else:
            out.skipped += 1
        return True

    def _scan(self) -> bool:
        """Skip garbage up to the next valid record; False when none is in the bytes present."""
        cur = self.cur
        nxt = self._first_start(cur.pos)
        if nxt is None:
            to = self.end if self.final else max(cur.pos, self.decided)
            self.out.garbage += to - cur.pos
            cur.pos = to
            return False
        self.out.garbage += nxt - cur.pos
        cur.pos, cur.scanning = nxt, False
        return True

    def _kind(self, p: int, is_start: bool) -> _Kind | None:
        """What the bytes at p frame as; None when that needs bytes not present yet."""
        buf = self.buf
        if self.end - p < LENGTH_BYTES + 1:
            return _Kind.NONE if self.final else None
        length = (int(buf[p]) << 8) | int(buf[p + 1])
        if buf[p + 2] != BFEE_CODE:
            return _Kind.OTHER if length >= 1 else _Kind.NONE
        if is_start:
            return _Kind.BFEE
        if self.end - p < RECORD_HEAD_BYTES:
            return _Kind.NONE if self.final else None
        field_len = int(_len_field(buf, p + LENGTH_BYTES))
        return _Kind.CORRUPT if length == 1 + HEADER_BYTES + field_len else _Kind.NONE

    def _one(self, is_start: bool) -> bool:
        """Decide on the record at the cursor; False when that needs bytes not present (or none are left)."""
        cur, out = self.cur, self.out
        p = cur.pos
        if p >= self.end:
            return False
        kind = self._kind(p, is_start)
        if kind is None:
            return False
        if kind is _Kind.NONE:
            cur.scanning = True
            return True
        stop = p + LENGTH_BYTES + ((int(self.buf[p]) << 8) | int(self.buf[p + 1]))
        inner = self._first_start(p + 1)
        cut_short = inner is not None and inner + RECORD_HEAD_BYTES <= stop
        if cut_short or stop > self.end:
            if not cut_short and not self.final:
                return False
            resume = inner if cut_short and inner is not None else self.end
            if kind is _Kind.OTHER:
                out.garbage += resume - p
            else:
                out.corrupt += 1
            cur.pos = resume
            return cut_short
        cur.pos, cur.pending, cur.pending_kind = stop, p, kind
        return True


def _frame(buf: np.ndarray, cur: _Cursor, final: bool) -> _Framing:
    """Frame the records of `buf` from `cur`, advancing it as far as the bytes present decide."""
    return _FramingPass(buf, cur, final).run()


def _records_of(buf: np.ndarray, framing: _Framing, scaled: bool, base: int = 0) -> CsiRecords:
    """Decode what a framing pass found; offsets are shifted by `base` (the bytes dropped before `buf`)."""
    records = _decode(buf, framing.offsets() + LENGTH_BYTES, scaled)
    records.offset += base
    records.n_skipped, records.n_corrupt, records.n_garbage_bytes = framing.skipped, framing.corrupt, framing.garbage
    return records


def _record_bytes(buf: np.ndarray, starts: np.ndarray) -> list[bytes]:
    """Each record at `starts` as code byte + notification."""
    data = buf.tobytes()
    return [data[s + LENGTH_BYTES : s + LENGTH_BYTES + ((data[s] << 8) | data[s + 1])] for s in starts.tolist()]


# ---------------------------------------------------------------------------------------------
# Public entry points


def decode_log(data: bytes, scaled: bool = True) -> CsiRecords:
    """Decode a whole CSI Tool log held in memory."""
    buf = np.frombuffer(data, dtype=np.uint8)
    return _records_of(buf, _frame(buf, _Cursor(), final=True), scaled)


def read_dat(path: str | Path, scaled: bool = True) -> CsiRecords:
    """Decode a CSI Tool log file (raises FileNotFoundError etc. as opening it does)."""
    return decode_log(Path(path).read_bytes(), scaled)


def split_records(data: bytes) -> tuple[list[bytes], LogCounts]:
    """The beamforming records of a log, each as code byte + notification, and what was skipped."""
    buf = np.frombuffer(data, dtype=np.uint8)
    framing = _frame(buf, _Cursor(), final=True)
    return _record_bytes(buf, framing.offsets()), LogCounts(framing.skipped, framing.corrupt, framing.garbage)


def decode_bfee(records: Sequence[bytes], scaled: bool = True) -> CsiRecords:
    """Decode records given one by one as code byte + notification (a CsiFrame's `bfee` field).

    Each input is judged on its own, no resynchronization across inputs: one that is not a
    beamforming record counts as skipped, one that is but does not decode (empty, cut short,
    trailing bytes, a `len` that disagrees) as corrupt. `offset` holds each row's input index.
    """
    parts = [bytes(r) for r in records]
    sizes = np.array([len(r) for r in parts], dtype=np.int64)
    code_at = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) if parts else sizes
    buf = np.frombuffer(b"".join(parts) + bytes(1 + HEADER_BYTES), dtype=np.uint8)
    bfee = (sizes >= 1) & (buf[code_at] == BFEE_CODE)
    ok = bfee & (sizes >= 1 + HEADER_BYTES)
    ok[ok] = _consistent_headers(buf, code_at[ok])
    ok[ok] = sizes[ok] == 1 + HEADER_BYTES + _len_field(buf, code_at[ok])
    rows = np.flatnonzero(ok)
    out = _decode(buf, code_at[rows], scaled)
    out.offset = rows
    out.n_skipped = int(np.count_nonzero((sizes >= 1) & ~bfee))
    out.n_corrupt = len(parts) - len(rows) - out.n_skipped
    return out


class StreamDecoder:
    """Decodes a CSI Tool log arriving in chunks (a growing file, a socket) exactly as the whole.

    Every record is handed out by the call that brings the bytes proving it whole (what follows
    it: the next record's header, see the module docstring) or by close(); `offset` is counted
    from the start of the stream. Counts of skipped, corrupt and garbage bytes accumulate on the
    decoder.
    """

    def __init__(self, scaled: bool = True):
        self.scaled = scaled
        self.n_skipped = self.n_corrupt = self.n_garbage_bytes = 0
        self._buf = bytearray()
        self._dropped = 0
        """bytes of the stream already discarded from `_buf`"""
        self._cursor = _Cursor()

    def feed(self, chunk: bytes) -> CsiRecords:
        """Add bytes; return the records they completed."""
        return self._records(chunk, final=False)

    def close(self) -> CsiRecords:
        """The stream ended: decide on what is left (a record cut off counts as corrupt)."""
        return self._records(b"", final=True)

    def records(self, chunk: bytes, final: bool = False) -> list[bytes]:
        """Like feed (or close, when `final`), but the records undecoded: code byte + notification."""
        buf, framing = self._frame(chunk, final)
        out = _record_bytes(buf, framing.offsets())
        self._trim()
        return out

    def _records(self, chunk: bytes, final: bool) -> CsiRecords:
        buf, framing = self._frame(chunk, final)
        out = _records_of(buf, framing, self.scaled, base=self._dropped)
        self._trim()
        return out

    def _frame(self, chunk: bytes, final: bool) -> tuple[np.ndarray, _Framing]:
        self._buf += chunk
        buf = np.frombuffer(bytes(self._buf), dtype=np.uint8)
        framing = _frame(buf, self._cursor, final)
        self.n_skipped += framing.skipped
        self.n_corrupt += framing.corrupt
        self.n_garbage_bytes += framing.garbage
        return buf, framing

    def _trim(self) -> None:
        """Drop the bytes framing no longer needs."""
        keep = self._cursor.keep_from()
        del self._buf[:keep]
        self._dropped += keep
        self._cursor.rebase(keep)


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


# ---------------------------------------------------------------------------------------------
# Encoding (the exact inverse, for simulation and tests)


@dataclass(frozen=True)
class RecordHeader:
    """Header fields of one beamforming record to encode (antenna_sel gives the permutation)."""

    timestamp_low: int
    bfee_count: int
    rssi: tuple[int, int, int]
    noise: int
    agc: int
    antenna_sel: int
    rate: int


def encode_record(head: RecordHeader, csi: np.ndarray) -> bytes:
    """One record (code byte + notification) that decodes to `csi`.

    `csi` is (30, Nrx, Ntx) of int8-valued complex numbers, antennas after the permutation, so
    the chains are written in the order the decoder reads them back. Raises CsiFormatError for a
    shape the 5300 cannot report, values outside int8, or an antenna_sel that maps two chains to
    one antenna (not invertible).
    """
    csi = np.asarray(csi)
    if csi.ndim != 3 or csi.shape[0] != SUBCARRIERS or not (1 <= csi.shape[1] <= 3 and 1 <= csi.shape[2] <= 3):
        raise CsiFormatError(f"CSI must be (30, Nrx, Ntx) with 1..3 chains and streams, not {csi.shape}")
    _, nrx, ntx = csi.shape
    values = np.rint(np.stack([csi.real, csi.imag], axis=-1)).astype(np.int64)
    if values.min() < -128 or values.max() > 127:
        raise CsiFormatError("CSI values must fit in int8")
    sources = _antenna_sources(antenna_perm([head.antenna_sel]), np.array([nrx]))[0, :nrx]
    if sorted(sources.tolist()) != list(range(nrx)):
        raise CsiFormatError(f"antenna_sel {head.antenna_sel:#x} maps two chains to one antenna for Nrx={nrx}")
    bit = _value_bits(nrx, ntx, tuple(sources.tolist()))[:, None] + np.arange(8)
    length = payload_bytes(nrx, ntx)
    bits = np.zeros(length * 8, dtype=np.uint8)
    bits[bit.ravel()] = ((values.ravel().astype(np.uint8)[:, None] >> np.arange(8, dtype=np.uint8)) & 1).ravel()
    payload = np.packbits(bits, bitorder="little").tobytes()
    header = struct.pack(
        "<IHHBBBBBbBBHH",
        head.timestamp_low & 0xFFFFFFFF,
        head.bfee_count & 0xFFFF,
        0,
        nrx,
        ntx,
        *head.rssi,
        head.noise,
        head.agc,
        head.antenna_sel,
        length,
        head.rate,
    )
    return bytes([BFEE_CODE]) + header + payload
