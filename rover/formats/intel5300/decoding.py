"""Decoding records already framed into CsiRecords, vectorized over records: the values' bits
unpacked in the antenna order, and get_scaled_csi's scaling. Framing (whole logs, streams) hands
its records to `_decode`; decode_bfee decodes records given one by one, without framing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from rover.formats.intel5300.records import (
    _HEADER,
    _RSSI_AT,
    BFEE_CODE,
    HEADER_BYTES,
    LENGTH_BYTES,
    NOISE_FLOOR_DB,
    NOISE_UNKNOWN_DB,
    NTX_AMPLITUDE_CORRECTION,
    RSS_OFFSET_DB,
    SUBCARRIERS,
    CsiRecords,
    _antenna_sources,
    _consistent_headers,
    _empty_records,
    _len_field,
    _value_bits,
    antenna_perm,
)

_DB = np.arange(256)
_RSSI_MW = np.where(_DB != 0, 10 ** (_DB / 10), 0.0)
"""a chain's RSSI byte (dB) as power, 0 for a chain without one: get_total_rss's terms, looked up"""
_NOISE_DB = _DB.astype(np.uint8).view(np.int8).astype(np.float64)
_NOISE_MW = 10 ** (np.where(_NOISE_DB == NOISE_UNKNOWN_DB, NOISE_FLOOR_DB, _NOISE_DB) / 10)
"""the noise byte (int8 dBm, read as uint8) as thermal noise power, the unknown value at the floor"""


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
