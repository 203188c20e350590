"""`rover info` of a CSI capture of another tool (Atheros, Nexmon, PicoScenes, WiROS): what it holds, as
Rover reads it."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rover.formats.csi_sources import CsiFrames, read_capture


@dataclass(frozen=True)
class CaptureInfo:
    path: str
    source: str
    packets: int
    subcarriers: int
    receive_chains: int
    transmit_streams: int
    bandwidth_mhz: float
    centre_freqs_mhz: list[float]
    duration_s: float
    median_rssi_db: list[float | None]
    """per receive chain, as the source reports it (None: not given)"""
    median_noise_dbm: float | None
    transmitters: list[str]
    dropped: dict[str, int]

    def as_json(self) -> dict[str, Any]:
        return asdict(self)


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if len(finite) else None


def capture_info(
    path: str | Path, fmt: str | None = None, chip: str | None = None, topic: str | None = None
) -> CaptureInfo:
    """Summarize a capture (BadInput when it is not one Rover reads, or is truncated)."""
    frames: CsiFrames = read_capture(path, fmt, chip, topic=topic)
    p, k, n, t = frames.csi.shape
    stamps = frames.timestamp_ns
    macs = np.unique(frames.mac, axis=0) if p else np.zeros((0, 6), np.uint8)
    return CaptureInfo(
        path=str(path),
        source=frames.source,
        packets=p,
        subcarriers=k,
        receive_chains=n,
        transmit_streams=t,
        bandwidth_mhz=frames.bandwidth_hz / 1e6,
        centre_freqs_mhz=sorted({float(f) / 1e6 for f in np.unique(frames.centre_freq_hz) if np.isfinite(f)}),
        duration_s=float(stamps.max() - stamps.min()) / 1e9 if p else 0.0,
        median_rssi_db=[_median(frames.rssi_db[:, c]) for c in range(n)],
        median_noise_dbm=_median(frames.noise_dbm),
        transmitters=[":".join(f"{b:02x}" for b in mac) for mac in macs if mac.any()],
        dropped=frames.dropped,
    )


def render(info: CaptureInfo) -> str:
    """Text like the dataset summary's."""
    rssi = ", ".join("-" if r is None else f"{r:.0f}" for r in info.median_rssi_db)
    lines = [
        f"File:              {info.path}",
        f"Source:            {info.source}",
        f"Packets:           {info.packets:,}",
        f"CSI:               {info.subcarriers} subcarriers x {info.receive_chains} receive chains x "
        f"{info.transmit_streams} transmit streams",
        f"Bandwidth:         {info.bandwidth_mhz:g} MHz",
        f"Centre frequency:  {', '.join(f'{f:g} MHz' for f in info.centre_freqs_mhz) or 'not given'}",
        f"Duration:          {info.duration_s:.3f} s (the source's clock)",
        f"RSSI per chain:    {rssi} dB (median, as the source reports it)",
        f"Noise floor:       {'not given' if info.median_noise_dbm is None else f'{info.median_noise_dbm:.0f} dBm'}",
        f"Transmitters:      {', '.join(info.transmitters) or 'not given'}",
    ]
    lines += [f"Dropped:           {n:,} {why}" for why, n in info.dropped.items()]
    return "\n".join(lines) + "\n"
