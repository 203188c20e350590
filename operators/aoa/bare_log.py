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
    csi = records.csi[usable, :, :m, :1]
    rates = records.rate[usable]
    frames = [
        make(
            "rover_msgs/msg/Csi",
            header=header(int(stamp), "base_link"),
            channel=channel,
            nrx=m,
            ntx=1,
            rate=int(rate),
            csi_real=np.ascontiguousarray(c.real, dtype=np.float32).ravel(),
            csi_imag=np.ascontiguousarray(c.imag, dtype=np.float32).ravel(),
        )
        for stamp, c, rate in zip(stamps, csi, rates, strict=True)
    ]
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=rig.text)
    params = AoaParams(burst_packets=burst_packets, max_burst_s=1e6)
    return [e.msg for e in run_operator(Aoa(params), {"setup": [setup], "csi": frames})]
