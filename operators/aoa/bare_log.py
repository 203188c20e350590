"""AoA on a bare CSI Tool log, no robot: the `aoa` operator called on a log's records, one burst per
`burst_packets` packets, stamped by the NIC's own clock. What `rover aoa` runs."""

from __future__ import annotations

from typing import Any

import numpy as np
import yaml

from rover.errors import BadInput
from rover.formats.intel5300 import CsiRecords
from rover.formats.rig import Rig, rig_from_text
from rover.messages import header, make
from rover.operators.aoa.operator import Aoa, AoaParams
from rover.pipeline.yamlpos import safe_load_limited
from rover.testing import run_operator

CLOCK_WRAP_US = 2**32
"""timestamp_low counts microseconds in 32 bits"""


def with_calibration(rig: Rig, calibration_text: str, source: str) -> Rig:
    """The rig with the `receiver.phase_offsets_rad` of a calibration file (as `rover calibrate --out` writes it)."""
    block = safe_load_limited(calibration_text, source)
    receiver = block.get("receiver") if isinstance(block, dict) else None
    offsets = receiver.get("phase_offsets_rad") if isinstance(receiver, dict) else None
    if offsets is None:
        raise BadInput(f"{source}: no receiver.phase_offsets_rad in it (write one with `rover calibrate --out`)")
    data = safe_load_limited(rig.text, "the setup")
    data.setdefault("receiver", {})["phase_offsets_rad"] = offsets
    return rig_from_text(yaml.safe_dump(data, sort_keys=False), f"{source} applied to the setup")


def log_stamps_ns(timestamp_low: np.ndarray) -> np.ndarray:
    """Nanoseconds since the first record given, from the NIC's 32-bit microsecond clock (wraps unwrapped)."""
    t = np.asarray(timestamp_low, dtype=np.int64)
    wraps = np.concatenate([[0], np.cumsum(np.diff(t) < 0)])
    return (t + wraps * CLOCK_WRAP_US - t[0]) * 1000 if len(t) else t


def log_bursts(records: CsiRecords, rig: Rig, channel: int, burst_packets: int) -> list[Any]:
    """The Aoa messages of a log's records with the rig's antenna count, `burst_packets` at a time."""
    m = len(rig.antenna_positions_m)
    usable = np.flatnonzero(records.nrx == m)
    if len(usable) == 0:
        raise BadInput(f"no beamforming record with {m} receive chains (of {len(records.nrx)})")
    stamps = log_stamps_ns(records.timestamp_low[usable])
    csi = records.csi[usable][:, :, :m, 0]
    return bursts_of(csi, stamps, rig, channel, burst_packets, rates=records.rate[usable])


def bursts_of(
    csi: np.ndarray,
    stamps_ns: np.ndarray,
    rig: Rig,
    channel: int,
    burst_packets: int,
    *,
    rates: np.ndarray | None = None,
    subcarriers: np.ndarray | None = None,
    centre_hz: float = 0.0,
    jumps: bool = True,
) -> list[Any]:
    """The Aoa messages of packets' CSI (P, K, M) of one transmit stream, `burst_packets` at a time:
    the `aoa` operator called on them as Csi records (the CSI Tool's rate flags, or another source's
    subcarriers and centre frequency)."""
    given = np.zeros(0, np.int16) if subcarriers is None else subcarriers.astype(np.int16)
    rate = np.zeros(len(csi), np.int64) if rates is None else rates
    packets = [
        make(
            "rover_msgs/msg/Csi",
            header=header(int(stamp), "base_link"),
            channel=channel,
            nrx=csi.shape[2],
            ntx=1,
            rate=int(r),
            csi_real=np.ascontiguousarray(c.real, dtype=np.float32).ravel(),
            csi_imag=np.ascontiguousarray(c.imag, dtype=np.float32).ravel(),
            subcarriers=given,
            centre_freq_hz=centre_hz,
        )
        for stamp, c, r in zip(stamps_ns, csi, rate, strict=True)
    ]
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=rig.text)
    params = AoaParams(burst_packets=burst_packets, max_burst_s=1e6, jumps=jumps)
    return [e.msg for e in run_operator(Aoa(params), {"setup": [setup], "csi": packets})]
