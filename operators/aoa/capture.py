"""AoA on a CSI capture of another tool (rover.formats.csi_sources), no robot: the `aoa` operator
called on its packets, one burst per `burst_packets` packets, stamped by the source's clock, with
the capture's own subcarriers and centre frequency. What `rover aoa CAPTURE` runs."""

from __future__ import annotations

from typing import Any

import numpy as np

from rover.errors import BadInput
from rover.formats.csi_sources import CsiFrames
from rover.formats.rig import Rig
from rover.formats.wifi import channel_of
from rover.operators.aoa.bare_log import bursts_of

EMPTY_POWER = 1e-4
"""a subcarrier whose median power over the capture is below this share of the strongest's carries
no channel estimate (DC, guard bands): it is left out"""


def occupied(frames: CsiFrames) -> np.ndarray:
    """The columns (indices into frames.subcarriers) that carry a channel estimate."""
    power = np.median(np.abs(frames.csi) ** 2, axis=(0, 2, 3))
    return np.flatnonzero(power > EMPTY_POWER * power.max()) if power.max() > 0 else np.zeros(0, int)


def capture_channel(frames: CsiFrames, given: int | None) -> tuple[int, float]:
    """The channel number and centre frequency of the capture's first packet (the file's, else `given`)."""
    freq = float(frames.centre_freq_hz[0]) if len(frames) else float("nan")
    if np.isfinite(freq):
        channel = channel_of(freq)
        if channel is None:
            raise BadInput(f"its centre frequency {freq / 1e6:g} MHz is no WiFi channel's")
        return channel, freq
    if given is None:
        raise BadInput("it does not say its channel: give --channel N")
    return given, 0.0


def capture_bursts(frames: CsiFrames, rig: Rig, channel: int, centre_hz: float, burst_packets: int) -> list[Any]:
    """The Aoa messages of a capture's packets (first transmit stream, the occupied subcarriers), with
    the rig's antennas, `burst_packets` at a time; no chain phase jumps (they are the Intel 5300's)."""
    m = len(rig.antenna_positions_m)
    if frames.csi.shape[2] != m:
        raise BadInput(f"its packets have {frames.csi.shape[2]} receive chains, the setup {m} antennas")
    columns = occupied(frames)
    if len(columns) == 0:
        raise BadInput("its CSI is zero on every subcarrier")
    stamps = frames.timestamp_ns - frames.timestamp_ns.min()
    return bursts_of(
        frames.csi[..., 0][:, columns], stamps, rig, channel, burst_packets,
        subcarriers=frames.subcarriers[columns], centre_hz=centre_hz, jumps=False,
    )  # fmt: skip
