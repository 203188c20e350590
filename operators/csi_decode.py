"""`csi_decode`: Intel 5300 CSI Tool records of labelled frames into complex CSI per tag.

Bit extraction, the antenna permutation and the scaling are the decoder's (rover.formats.intel5300),
bit-exact with the CSI Tool's own MATLAB code. Records that are not beamforming reports or whose
length disagrees with their antenna counts are counted and dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.formats.intel5300 import decode_bfee
from rover.messages import make
from rover.operator import Emit, In, Operator, Out


@dataclass(frozen=True)
class DecodeParams:
    scaled: bool = True
    """Scale to SNR units as the CSI Tool's get_scaled_csi does (false: raw int8 values)."""


class CsiDecode(Operator):
    """Decodes labelled frames; one Csi message per valid record.

    Frames are decoded in batches (a run of frames on one channel, as a dwell of the sweep
    delivers them), which is what makes vectorized decoding pay off. A batch never spans more
    than `BATCH_SPAN_S` of event time, and is decoded as soon as no frame waits (`on_idle`: live,
    frames trickle in); the runtime promises downstream the batch's first stamp (`held_since_ns`).
    """

    cpu_weight = 0.9

    inputs = {"frames": In("rover_msgs/msg/LabelledCsiFrame")}
    outputs = {"csi": Out("rover_msgs/msg/Csi")}
    Params = DecodeParams
    BATCH_SPAN_S = 0.25
    BATCH_FRAMES = 64

    def __init__(self, params: DecodeParams | None = None):
        super().__init__(params)
        self.batch: list[tuple[Any, int]] = []

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if self.batch and (
            msg.channel != self.batch[0][0].channel or stamp_ns - self.batch[0][1] >= self.BATCH_SPAN_S * 1e9
        ):
            yield from self._flush()
        self.batch.append((msg, stamp_ns))
        if len(self.batch) >= self.BATCH_FRAMES:
            yield from self._flush()

    def held_since_ns(self) -> float:
        """The batch's first frame's stamp: no output comes before it."""
        return self.batch[0][1] if self.batch else math.inf

    def on_idle(self):
        """Nothing more has come: decode what the batch holds (live, a batch would otherwise wait for
        the next dwell's frames; each record decodes the same in any batch)."""
        return self._flush()

    def _flush(self):
        frames, self.batch = self.batch, []
        if not frames:
            return
        records = decode_bfee([bytes(msg.bfee) for msg, _ in frames], scaled=self.params.scaled)
        lost = len(frames) - len(records)
        self.drop("frames that are not beamforming records", records.n_skipped)
        self.drop("frames with a corrupt record", lost - records.n_skipped)
        for row, index in enumerate(records.offset):
            msg, stamp_ns = frames[index]
            yield self._message(msg, stamp_ns, records, row)

    def _message(self, msg: Any, stamp_ns: int, records, i: int) -> Emit:
        nrx, ntx = int(records.nrx[i]), int(records.ntx[i])
        csi = records.csi[i, :, :nrx, :ntx]
        return Emit(
            "csi",
            make(
                "rover_msgs/msg/Csi",
                header=msg.header,
                tag_id=msg.tag_id,
                channel=msg.channel,
                bfee_count=int(records.bfee_count[i]),
                nrx=nrx,
                ntx=ntx,
                rssi=records.rssi[i].astype(np.uint8),
                noise=int(records.noise[i]),
                agc=int(records.agc[i]),
                perm=records.perm[i].astype(np.uint8),
                rate=int(records.rate[i]),
                scaled=self.params.scaled,
                csi_real=np.ascontiguousarray(csi.real, dtype=np.float32).ravel(),
                csi_imag=np.ascontiguousarray(csi.imag, dtype=np.float32).ravel(),
            ),
            stamp_ns,
        )

    def on_end(self):
        yield from self._flush()


def csi_array(msg: Any) -> np.ndarray:
    """The complex CSI of a Csi message, shape (30, nrx, ntx)."""
    shape = (-1, msg.nrx, msg.ntx)
    return (msg.csi_real.astype(np.float64) + 1j * msg.csi_imag.astype(np.float64)).reshape(shape)
