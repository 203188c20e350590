"""Framing: where the beamforming records of a CSI Tool log are, whole or arriving in chunks, and
through damage; what it finds goes to `decoding`. The public entry points for logs live here.

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

from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from rover.formats.intel5300.decoding import _decode
from rover.formats.intel5300.records import (
    _LEN_AT,
    BFEE_CODE,
    FRAME_CODE,
    HEADER_BYTES,
    LENGTH_BYTES,
    RECORD_HEAD_BYTES,
    CsiRecords,
    LogCounts,
    _consistent_headers,
    _len_field,
)


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
