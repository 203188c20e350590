"""`csi_file`: CSI from a CSI Tool log file (`log_to_file` output), whole or followed as it grows.

Records are sent as they are (code byte + notification) in CsiFrame messages. Damaged stretches
are skipped and counted.

Stamps (`stamps`): a log replayed whole (`follow: false`) is stamped from the log itself, by
default: `start_ns` plus the time since its first record on the NIC's clock, each record header's
`timestamp_low` (microseconds, u32), unwrapped by counting its wraps (every 2^32 us, 71.6 min).
With `start_ns: 0` the stamps are the time since the log's first record. That clock drifts against
the host's (so these stamps do not line up with other sources' host time) and restarts with the
driver (a restart mid-log counts as a wrap: split such a log). A followed log (`follow: true`) is
stamped with the time each record was read, the host receive time, as live sources are, by default.
Watermarks, sent while a followed log has nothing new, keep to the same clock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from rover.errors import BadInput
from rover.formats.intel5300 import StreamDecoder, decode_bfee
from rover.messages import header, make
from rover.operator import COMPLETE, Emit, Out, RunOutcome, Source, Watermark
from rover.pipeline.params import Checked, NonNegativeInt, PositiveFloat

CHUNK_BYTES = 1 << 16
TIMESTAMP_WRAP_US = 1 << 32
"""timestamp_low counts microseconds in a u32: it wraps every 2^32 us (71.6 min)"""


@dataclass(frozen=True)
class CsiFileParams(Checked):
    path: str = ""
    follow: bool = False
    """Keep reading as the file grows (like `tail -f`) until the run is stopped."""
    channel: NonNegativeInt = 0
    """The channel the log was recorded on, or 0 when `channel_hop` announces the hops."""
    poll_s: PositiveFloat = 0.05
    stamps: Literal["log", "receive"] | None = None
    """`log`: start_ns + the NIC's time since the log's first record; `receive`: the host time each
    record was read. Default: `log` for a whole log (`follow: false`), `receive` when following."""
    start_ns: NonNegativeInt = 0
    """With `log` stamps, the stamp of the log's first record (0: stamps are the time since it)."""


class CsiFile(Source):
    """Reads a CSI Tool log and publishes its beamforming records."""

    outputs = {"csi": Out("rover_msgs/msg/CsiFrame")}
    Params = CsiFileParams

    @classmethod
    def is_live(cls, params: CsiFileParams) -> bool:
        """A followed log grows as the NIC writes it: live; a whole log is a file."""
        return params.follow

    def __init__(self, params: CsiFileParams | None = None):
        super().__init__(params)
        if not self.params.path:
            raise BadInput("csi_file: no log file given (params.path)")
        self.path = Path(self.params.path)
        try:
            self._file = self.path.open("rb")
        except OSError as exc:
            raise BadInput(f"{self.path}: cannot read: {exc.strerror or exc}") from None
        self.stream = StreamDecoder(scaled=False)
        self.count = 0
        self.stamps = self.params.stamps or ("receive" if self.params.follow else "log")
        self._first_low: int | None = None
        """timestamp_low of the log's first record"""
        self._last_low = 0
        self._wraps = 0
        self._last_stamp = self.params.start_ns

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        while not stop.is_set():
            chunk = self._file.read(CHUNK_BYTES)
            if not chunk:
                if not self.params.follow:
                    break
                yield Watermark(time.time_ns() if self.stamps == "receive" else self._last_stamp)
                stop.wait(self.params.poll_s)
                continue
            yield from self._frames(self._records(chunk))
        yield from self._frames(self._records(b"", final=True))

    def _records(self, chunk: bytes, final: bool = False) -> list[bytes]:
        """The records `chunk` completes; what the decoder skipped on the way counts as dropped at once,
        so a run stopped while following the file still reports it."""
        records = self.stream.records(chunk, final)
        s = self.stream
        for reason, total in (
            (f"records with other codes in {self.path}", s.n_skipped),
            (f"corrupt records in {self.path}", s.n_corrupt),
            (f"bytes of garbage in {self.path}", s.n_garbage_bytes),
        ):
            self.drop(reason, total - self.drops[reason])
        return records

    def _frames(self, records: list[bytes]) -> Iterator[Emit]:
        if self.stamps == "receive":
            for record in records:
                yield self._frame(record, time.time_ns())
        else:
            for record, stamp in zip(records, self._log_stamps(records), strict=True):
                yield self._frame(record, stamp)

    def _log_stamps(self, records: list[bytes]) -> list[int]:
        """Each record's stamp from its timestamp_low, unwrapped: one wrap more each time it decreases,
        counted across calls (the log's records, in order, come in batches)."""
        if not records:
            return []
        low = decode_bfee(records, scaled=False).timestamp_low.astype(np.int64)
        assert len(low) == len(records), "framing hands out only records that decode"
        if self._first_low is None:
            self._first_low = self._last_low = int(low[0])
        wraps = self._wraps + np.cumsum(np.diff(low, prepend=self._last_low) < 0)
        self._wraps, self._last_low = int(wraps[-1]), int(low[-1])
        stamps = self.params.start_ns + (low + wraps * TIMESTAMP_WRAP_US - self._first_low) * 1000
        self._last_stamp = int(stamps[-1])
        return [int(s) for s in stamps]

    def _frame(self, record: bytes, stamp_ns: int) -> Emit:
        self.count += 1
        return Emit(
            "csi",
            make(
                "rover_msgs/msg/CsiFrame",
                header=header(stamp_ns, "base_link"),
                channel=self.params.channel,
                bfee=np.frombuffer(record, dtype=np.uint8),
            ),
        )

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        self._file.close()
