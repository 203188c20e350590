"""Another tool's CSI in a dataset: WiROS's `rf_msgs/msg/Wifi` (rover.formats.csi_sources.wiros) as
`rover_msgs/msg/Csi` on `/csi/capture`, what `rover convert` writes for a WiROS bag.

Each packet keeps its CSI at the subcarriers WiROS keeps (the chip's lower bins rotated back,
compensated when given), with their indices and the channel's centre frequency; its transmitter is
the tag its MAC's last four bytes name (`wiros.tag_ids`); its stamp is its header's. The message's
RSSI (one value in dBm) has no place in the CSI Tool's three unsigned ones: they stay 0.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources import wiros
from rover.formats.csi_sources.frames import CsiFrames
from rover.formats.wifi import channel_of
from rover.messages import header, make

NOISE_UNKNOWN = -127
"""Csi.noise's value for a noise floor the source does not give"""


def capture_messages(
    bags: Sequence[Path],
    topic: str,
    compensation: str | Path | None,
    window: tuple[int | None, int | None],
    dropped: Counter[str],
) -> list[tuple[int, Any]]:
    """(stamp, Csi) of every packet on `topic` in the bags that hold it, within `window` (ns, either
    end open); what the reader left out is added to `dropped`. BadInput when no packet is left."""
    lo, hi = window
    out: list[tuple[int, Any]] = []
    read = [bag for bag in bags if topic in wiros.wifi_topics(bag)]
    for bag in read:
        frames = wiros.read(bag, topic, compensation, every_transmitter=True)
        for why, n in frames.dropped.items():
            dropped[f"csi: {why}"] += n
        inside = (frames.timestamp_ns >= (lo if lo is not None else -1)) & (
            frames.timestamp_ns <= (hi if hi is not None else np.iinfo(np.int64).max)
        )
        out += _messages(bag, frames.take(np.flatnonzero(inside), "outside --start/--end"))
    if not out:
        names = ", ".join(map(str, read or bags))
        why = ", ".join(f"{n:,} {w.removeprefix('csi: ')}" for w, n in sorted(dropped.items()) if w.startswith("csi: "))
        raise BadInput(
            f"{names}: {topic}: no packet of WiROS's {wiros.WIFI_TYPE} left to write{f' ({why})' if why else ''}: "
            "nothing written"
        )
    return out


def _messages(bag: Path, frames: CsiFrames) -> list[tuple[int, Any]]:
    """One Csi message per packet of the frames (one channel and shape)."""
    if not len(frames):
        return []
    tags = wiros.tag_ids(bag, [bytes(m) for m in frames.mac])
    centre_hz = float(frames.centre_freq_hz[0])
    channel = channel_of(centre_hz)
    if channel is None:
        raise BadInput(f"{bag}: its centre frequency {centre_hz / 1e6:g} MHz is no WiFi channel's")
    n_rx, n_tx = frames.csi.shape[2:]
    subcarriers = frames.subcarriers.astype(np.int16)
    real = frames.csi.real.astype(np.float32).reshape(len(frames), -1)
    imag = frames.csi.imag.astype(np.float32).reshape(len(frames), -1)
    stamps = frames.timestamp_ns.tolist()
    sequence = (frames.sequence % 2**32).tolist()
    return [
        (
            stamp,
            make(
                "rover_msgs/msg/Csi",
                header=header(stamp, "base_link"),
                tag_id=int(tag),
                channel=channel,
                bfee_count=seq,
                nrx=n_rx,
                ntx=n_tx,
                noise=NOISE_UNKNOWN,
                csi_real=re,
                csi_imag=im,
                subcarriers=subcarriers,
                centre_freq_hz=centre_hz,
            ),
        )
        for stamp, tag, seq, re, im in zip(stamps, tags.tolist(), sequence, real, imag, strict=True)
    ]
