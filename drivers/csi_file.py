"""`csi_file`: CSI from a CSI Tool log file (`log_to_file` output), whole or followed as it grows.

Records are sent as they are (code byte + notification) in CsiFrame messages stamped with the
time they were read, the host receive time of this source: the NIC's timestamp_low wraps every
71.6 minutes and drifts, so it is never used as time. Damaged stretches are skipped and counted.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.intel5300 import StreamDecoder
from rover.messages import header, make
from rover.operator import COMPLETE, Emit, Out, RunOutcome, Source, Watermark
from rover.pipeline.params import Checked, NonNegativeInt, PositiveFloat

CHUNK_BYTES = 1 << 16


@dataclass(frozen=True)
class CsiFileParams(Checked):
    path: str = ""
    follow: bool = False
    """Keep reading as the file grows (like `tail -f`) until the run is stopped."""
    channel: NonNegativeInt = 0
    """The channel the log was recorded on, or 0 when `channel_hop` announces the hops."""
    poll_s: PositiveFloat = 0.05


class CsiFile(Source):
    """Reads a CSI Tool log and publishes its beamforming records."""

    outputs = {"csi": Out("rover_msgs/msg/CsiFrame")}
    Params = CsiFileParams

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

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        while not stop.is_set():
            chunk = self._file.read(CHUNK_BYTES)
            if not chunk:
                if not self.params.follow:
                    break
                yield Watermark(time.time_ns())
                stop.wait(self.params.poll_s)
                continue
            for record in self._records(chunk):
                yield self._frame(record)
        for record in self._records(b"", final=True):
            yield self._frame(record)

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

    def _frame(self, record: bytes) -> Emit:
        self.count += 1
        return Emit(
            "csi",
            make(
                "rover_msgs/msg/CsiFrame",
                header=header(time.time_ns(), "base_link"),
                channel=self.params.channel,
                bfee=np.frombuffer(record, dtype=np.uint8),
            ),
        )

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        self._file.close()
