"""Intel 5300 CSI Tool records: framing, bit-exact decoding and scaling, vectorized over records.

A CSI Tool log is a sequence of records, each a 2-byte big-endian length and that many bytes:
a code byte (0xBB for a beamforming report) and the notification. The notification's header
is `<IHHBBBBBbBBHH` (timestamp_low, bfee_count, reserved, Nrx, Ntx, rssi_a/b/c, noise, agc,
antenna_sel, len, fake_rate_n_flags); the CSI follows at byte 20, for each of 30 subcarriers
3 unused bits then Nrx*Ntx complex values of two int8 each, packed at arbitrary bit offsets.
The results match the tool's own `read_bf_file.m` and `get_scaled_csi.m`.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

BFEE_CODE = 0xBB
HEADER_BYTES = 20
SUBCARRIERS = 30
LENGTH_BYTES = 2
LOOKAHEAD_BYTES = LENGTH_BYTES + 1 + HEADER_BYTES
"""Bytes from a record's start needed to tell whether a valid beamforming record starts there."""
NOISE_UNKNOWN_DB = -127
NOISE_FLOOR_DB = -92
RSS_OFFSET_DB = 44
NTX_CORRECTION = {1: 1.0, 2: np.sqrt(2.0), 3: np.sqrt(10 ** (4.5 / 10))}
"""Per-stream power correction of get_scaled_csi for 2 and 3 transmit streams."""


class CsiFormatError(ValueError):
    """Bytes that cannot be CSI Tool records where records are required."""


def payload_bytes(nrx: np.ndarray | int, ntx: np.ndarray | int) -> np.ndarray | int:
    """Expected CSI payload length for Nrx x Ntx streams."""
    return (SUBCARRIERS * (nrx * ntx * 16 + 3) + 7) // 8


@dataclass
class CsiRecords:
    """Decoded beamforming records, one row per record; `csi` is (N, 30, Nrx_max, Ntx_max)."""

    timestamp_low: np.ndarray
    bfee_count: np.ndarray
    nrx: np.ndarray
    ntx: np.ndarray
    rssi: np.ndarray
    noise: np.ndarray
    agc: np.ndarray
    antenna_sel: np.ndarray
    perm: np.ndarray
    rate: np.ndarray
    csi: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """Byte offset of each record's length prefix in the log (for decode_bfee: the input's index)."""
    n_skipped: int = 0
    """Records with other codes than 0xBB (e.g. 0xC1), skipped."""
    n_corrupt: int = 0
    """Beamforming records whose length disagrees with their Nrx/Ntx, or cut short."""
    n_garbage_bytes: int = 0
    """Bytes that belonged to no record (skipped while resynchronizing)."""
    scaled: bool = True

    def __len__(self) -> int:
        return len(self.bfee_count)


@dataclass
class _Framing:
    """Where the records of a buffer are, and what was skipped."""

    bfee: list[np.ndarray] = field(default_factory=list)
    """offsets of beamforming records' code bytes, in runs"""
    skipped: int = 0
    corrupt: int = 0
    garbage: int = 0

    def offsets(self) -> np.ndarray:
        return np.concatenate(self.bfee) if self.bfee else np.zeros(0, dtype=np.int64)


_HEADER = np.dtype([("timestamp_low", "<u4"), ("bfee_count", "<u2"), ("reserved", "<u2"), ("nrx", "u1"),
                    ("ntx", "u1"), ("rssi_a", "u1"), ("rssi_b", "u1"), ("rssi_c", "u1"), ("noise", "i1"),
                    ("agc", "u1"), ("antenna_sel", "u1"), ("len", "<u2"), ("rate", "<u2")])


def _valid_starts(buf: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Offsets p in [lo, hi) where a consistent beamforming record header starts (length prefix at p)."""
    hi = min(hi, len(buf) - LOOKAHEAD_BYTES + 1)
    if hi <= lo:
        return np.zeros(0, dtype=np.int64)
    p = lo + np.flatnonzero(buf[lo + 2:hi + 2] == BFEE_CODE)
    nrx = buf[p + 3 + 8].astype(np.int64)
    ntx = buf[p + 3 + 9].astype(np.int64)
    length = (buf[p].astype(np.int64) << 8) | buf[p + 1]
    field_len = buf[p + 3 + 16].astype(np.int64) | (buf[p + 3 + 17].astype(np.int64) << 8)
    ok = (nrx >= 1) & (nrx <= 3) & (ntx >= 1) & (ntx <= 3)
    ok &= field_len == payload_bytes(nrx, ntx)
    ok &= length == 1 + HEADER_BYTES + field_len
    return p[ok]


def _frame(buf: np.ndarray, pos: int, final: bool, garbage_mode: bool, out: _Framing) -> tuple[int, bool]:
    """Walk records from `pos`; return where to resume and whether we are inside garbage.

    Each decision looks only at bytes that are present (or, when `final`, knows that nothing
    follows), so a log fed in chunks is framed exactly as the whole log at once. Runs of
    back-to-back valid records, the usual case, are taken in one step.
    """
    end = len(buf)
    starts = _valid_starts(buf, pos, end)
    nexts = starts + LENGTH_BYTES + ((buf[starts].astype(np.int64) << 8) | buf[starts + 1])
    breaks = np.flatnonzero(nexts[:-1] != starts[1:])

    def index_from(p: int) -> int:
        return int(np.searchsorted(starts, p, side="left"))

    while pos < end:
        if garbage_mode:
            k = index_from(pos)
            if k == len(starts):
                keep = end if final else max(pos, end - LOOKAHEAD_BYTES + 1)
                out.garbage += keep - pos
                pos = keep
                if not final:
                    return pos, True
                continue
            out.garbage += int(starts[k]) - pos
            pos, garbage_mode = int(starts[k]), False
            continue
        if end - pos < LOOKAHEAD_BYTES and not final:
            return pos, False
        if end - pos < LENGTH_BYTES + 1:
            garbage_mode = True
            continue
        k = index_from(pos)
        if k < len(starts) and starts[k] == pos:
            b = int(np.searchsorted(breaks, k))
            run_end = int(breaks[b]) if b < len(breaks) else len(starts) - 1
            last = k + int(np.searchsorted(nexts[k:run_end + 1], end, side="right")) - 1
            if last >= k:
                out.bfee.append(starts[k:last + 1] + LENGTH_BYTES)
                pos = int(nexts[last])
                continue
            if not final:
                return pos, False
            out.corrupt += 1
            out.garbage += 1
            pos += 1
            garbage_mode = True
            continue
        length = (int(buf[pos]) << 8) | int(buf[pos + 1])
        stop = pos + LENGTH_BYTES + length
        if stop + LOOKAHEAD_BYTES - 1 > end and not final:
            return pos, False
        clean = length >= 1 and stop <= end and (k == len(starts) or starts[k] >= stop)
        code = int(buf[pos + 2])
        if clean and code == BFEE_CODE and end - pos >= LOOKAHEAD_BYTES:
            field_len = int(buf[pos + 3 + 16]) | (int(buf[pos + 3 + 17]) << 8)
            if length == 1 + HEADER_BYTES + field_len:
                out.corrupt += 1
                pos = stop
                continue
        elif clean and code != BFEE_CODE:
            out.skipped += 1
            pos = stop
            continue
        garbage_mode = True
    return pos, garbage_mode


def _decode(buf: np.ndarray, offsets: Sequence[int], scaled: bool) -> CsiRecords:
    """Decode the beamforming records whose code bytes are at `offsets` (all consistent, all complete)."""
    offsets = np.asarray(offsets, dtype=np.int64)
    n = len(offsets)
    head_idx = offsets[:, None] + 1 + np.arange(HEADER_BYTES)
    head = np.ascontiguousarray(buf[head_idx]).view(_HEADER).reshape(n) if n else np.zeros(0, _HEADER)
    nrx = head["nrx"].astype(np.int64)
    ntx = head["ntx"].astype(np.int64)
    perm = ((head["antenna_sel"].astype(np.int64)[:, None] >> (2 * np.arange(3))) & 3) + 1
    groups = nrx * 1000 + ntx * 100 + (perm - 1) @ np.array([16, 4, 1])
    keys = np.unique(groups)
    if len(keys) == 1:
        r, t = int(nrx[0]), int(ntx[0])
        csi = _unpack(buf, offsets + 1 + HEADER_BYTES, r, t, _antenna_order(perm[0], r))
    else:
        csi = np.zeros((n, SUBCARRIERS, int(nrx.max()) if n else 1, int(ntx.max()) if n else 1), dtype=np.complex128)
    for key in keys if len(keys) > 1 else ():
        rows = np.flatnonzero(groups == key)
        r, t = int(nrx[rows[0]]), int(ntx[rows[0]])
        csi[rows, :, :r, :t] = _unpack(buf, offsets[rows] + 1 + HEADER_BYTES, r, t, _antenna_order(perm[rows[0]], r))
    rssi = np.stack([head["rssi_a"], head["rssi_b"], head["rssi_c"]], axis=1)
    if scaled and n:
        _scale(csi, rssi, head["noise"], head["agc"], nrx, ntx)
    return CsiRecords(head["timestamp_low"].copy(), head["bfee_count"].copy(), nrx.astype(np.uint8),
                      ntx.astype(np.uint8), rssi, head["noise"].copy(), head["agc"].copy(),
                      head["antenna_sel"].copy(), perm.astype(np.uint8), head["rate"].copy(), csi, scaled=scaled)


def _antenna_order(perm: np.ndarray, nrx: int) -> np.ndarray:
    """Raw chain feeding each antenna: chain k goes to antenna perm[k] (a scatter), so antenna a reads
    chain argsort(perm)[a]. As read_bf_file does, one antenna or an invalid permutation is left as is."""
    p = perm[:nrx] - 1
    if nrx == 1 or sorted(p.tolist()) != list(range(nrx)):
        return np.arange(nrx)
    return np.argsort(p)


def _unpack(buf: np.ndarray, payload_at: np.ndarray, nrx: int, ntx: int, chains: np.ndarray) -> np.ndarray:
    """(n, 30, nrx, ntx) complex values of records with one shape and permutation.

    Value (subcarrier i, raw chain c, stream t) starts at bit 3(i+1) + 16(i*Nrx*Ntx + c*Ntx + t) of
    the payload: read a little-endian 16-bit word at its byte and shift by its bit offset.
    """
    m = nrx * ntx
    i = np.arange(SUBCARRIERS)[:, None, None]
    raw_index = chains[None, :, None] * ntx + np.arange(ntx)[None, None, :]
    bits = (3 * (i + 1) + 16 * (i * m + raw_index)).ravel()
    span = int(bits.max() // 8) + 3
    rows = buf[payload_at[:, None] + np.arange(span)]
    words = rows[:, :-1].astype(np.uint16) | (rows[:, 1:].astype(np.uint16) << 8)
    both = np.concatenate([bits, bits + 8])
    values = (words[:, both >> 3] >> (both & 7)).astype(np.uint8).view(np.int8)
    out = np.empty((len(payload_at), len(bits)), dtype=np.complex128)
    out.real = values[:, :len(bits)]
    out.imag = values[:, len(bits):]
    return out.reshape(-1, SUBCARRIERS, nrx, ntx)


def _scale(csi: np.ndarray, rssi, noise, agc, nrx, ntx) -> None:
    """get_scaled_csi, in place: CSI in units of the noise, from the total RSS, AGC and noise floor."""
    rssi = rssi.astype(np.float64)
    mag = np.where(rssi != 0, 10 ** (rssi / 10), 0.0).sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        rss_db = 10 * np.log10(mag) - RSS_OFFSET_DB - agc.astype(np.float64)
        flat = csi.reshape(len(csi), -1).view(np.float64)
        csi_pwr = np.einsum("ij,ij->i", flat, flat)
        scale = 10 ** (rss_db / 10) / (csi_pwr / SUBCARRIERS)
        noise_db = np.where(noise == NOISE_UNKNOWN_DB, NOISE_FLOOR_DB, noise).astype(np.float64)
        total_noise = 10 ** (noise_db / 10) + scale * (nrx * ntx)
        factor = np.sqrt(scale / total_noise) * np.select([ntx == 2, ntx == 3], [NTX_CORRECTION[2], NTX_CORRECTION[3]],
                                                          1.0)
    csi *= factor[:, None, None, None]


def _records(buf: np.ndarray, framing: _Framing, scaled: bool) -> CsiRecords:
    offsets = framing.offsets()
    records = _decode(buf, offsets, scaled)
    records.offset = offsets - LENGTH_BYTES
    records.n_skipped, records.n_corrupt, records.n_garbage_bytes = framing.skipped, framing.corrupt, framing.garbage
    return records


def decode_log(data: bytes, scaled: bool = True) -> CsiRecords:
    """Decode a whole CSI Tool log held in memory."""
    buf = np.frombuffer(data, dtype=np.uint8)
    framing = _Framing()
    _frame(buf, 0, True, False, framing)
    return _records(buf, framing, scaled)


def read_dat(path: str | Path, scaled: bool = True) -> CsiRecords:
    """Decode a CSI Tool log file (`log_to_file` output)."""
    return decode_log(Path(path).read_bytes(), scaled)


def decode_bfee(records: Sequence[bytes], scaled: bool = True) -> CsiRecords:
    """Decode records given without their length prefix (code byte then notification, as in CsiFrame.bfee).

    `offset` of the result holds the index of the input each decoded row came from; inputs that
    are not valid beamforming records have no row (and are counted as skipped or corrupt).
    """
    records = [bytes(r) for r in records]
    starts = np.cumsum([0] + [len(r) + LENGTH_BYTES for r in records])
    out = decode_log(b"".join(len(r).to_bytes(2, "big") + r for r in records), scaled)
    out.offset = np.searchsorted(starts, out.offset)
    return out


def split_records(data: bytes) -> tuple[list[bytes], _Framing]:
    """The beamforming records of a log, each as code byte + notification, and what was skipped."""
    buf = np.frombuffer(data, dtype=np.uint8)
    framing = _Framing()
    _frame(buf, 0, True, False, framing)
    return [data[o:o + (int(buf[o - 2]) << 8 | int(buf[o - 1]))] for o in framing.offsets()], framing


class StreamDecoder:
    """Decodes a CSI Tool log arriving in chunks (a growing file, a socket) exactly as the whole would be."""

    def __init__(self, scaled: bool = True):
        self.scaled = scaled
        self._buf = bytearray()
        self._garbage = False
        self.n_skipped = self.n_corrupt = self.n_garbage_bytes = 0

    def _frame(self, chunk: bytes, final: bool) -> tuple[np.ndarray, _Framing, int]:
        self._buf += chunk
        buf = np.frombuffer(bytes(self._buf), dtype=np.uint8)
        framing = _Framing()
        pos, self._garbage = _frame(buf, 0, final, self._garbage, framing)
        self.n_skipped += framing.skipped
        self.n_corrupt += framing.corrupt
        self.n_garbage_bytes += framing.garbage
        return buf, framing, pos

    def feed(self, chunk: bytes) -> CsiRecords:
        """Add bytes; return the records they completed."""
        return self._decode(chunk, final=False)

    def close(self) -> CsiRecords:
        """The stream ended: decide on what is left (a cut-off record counts as corrupt)."""
        return self._decode(b"", final=True)

    def _decode(self, chunk: bytes, final: bool) -> CsiRecords:
        buf, framing, pos = self._frame(chunk, final)
        records = _records(buf, framing, self.scaled)
        del self._buf[:pos]
        return records

    def records(self, chunk: bytes, final: bool = False) -> list[bytes]:
        """Add bytes; return the beamforming records they completed, undecoded (code byte + notification)."""
        buf, framing, pos = self._frame(chunk, final)
        out = [bytes(self._buf[o:o + (int(buf[o - 2]) << 8 | int(buf[o - 1]))]) for o in framing.offsets()]
        del self._buf[:pos]
        return out


def concat(parts: Sequence[CsiRecords]) -> CsiRecords:
    """Join decoded batches (e.g. the chunks of a stream) into one, padding CSI to the largest shape."""
    parts = [p for p in parts]
    nrx_max = max((p.csi.shape[2] for p in parts if len(p)), default=1)
    ntx_max = max((p.csi.shape[3] for p in parts if len(p)), default=1)
    csi = [np.pad(p.csi, ((0, 0), (0, 0), (0, nrx_max - p.csi.shape[2]), (0, ntx_max - p.csi.shape[3])))
           for p in parts]
    fields = ("timestamp_low", "bfee_count", "nrx", "ntx", "rssi", "noise", "agc", "antenna_sel", "perm", "rate")
    joined = {f: np.concatenate([getattr(p, f) for p in parts]) for f in fields + ("offset",)}
    return CsiRecords(**joined, csi=np.concatenate(csi) if csi else np.zeros((0, SUBCARRIERS, 1, 1), complex),
                      n_skipped=sum(p.n_skipped for p in parts), n_corrupt=sum(p.n_corrupt for p in parts),
                      n_garbage_bytes=sum(p.n_garbage_bytes for p in parts),
                      scaled=parts[0].scaled if parts else True)


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
    """One record (code byte + notification) whose decoding gives back `csi`, shape (30, Nrx, Ntx) of
    int8-valued complex numbers after the permutation: the exact inverse of the decoder's bit layout."""
    csi = np.asarray(csi)
    _, nrx, ntx = csi.shape
    perm = ((head.antenna_sel >> (2 * np.arange(3))) & 3) + 1
    chains = _antenna_order(perm, nrx)
    raw = np.empty_like(csi)
    raw[:, chains, :] = csi
    m = nrx * ntx
    length = payload_bytes(nrx, ntx)
    bits = np.zeros(length * 8 + 16, dtype=np.uint8)
    values = np.stack([raw.real.reshape(SUBCARRIERS, m), raw.imag.reshape(SUBCARRIERS, m)], axis=-1)
    values = np.rint(values).astype(np.int64)
    if values.min() < -128 or values.max() > 127:
        raise CsiFormatError("CSI values must fit in int8")
    start = (3 * (np.arange(SUBCARRIERS)[:, None, None] + 1) + 16 * (np.arange(SUBCARRIERS)[:, None, None] * m
             + np.arange(m)[None, :, None]) + 8 * np.arange(2)[None, None, :])
    positions = start[..., None] + np.arange(8)
    bits[positions.ravel()] = ((values[..., None].astype(np.uint8) >> np.arange(8)) & 1).ravel()
    payload = np.packbits(bits[:length * 8], bitorder="little").tobytes()
    header = struct.pack("<IHHBBBBBbBBHH", head.timestamp_low & 0xFFFFFFFF, head.bfee_count & 0xFFFF, 0, nrx, ntx,
                         *head.rssi, head.noise, head.agc, head.antenna_sel, length, head.rate)
    return bytes([BFEE_CODE]) + header + payload
