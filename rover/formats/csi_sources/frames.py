"""One CSI frame for every source: packets x subcarriers x receive chains x transmit streams, with
the subcarriers' indices, the bandwidth and centre frequency, and what the source gives besides."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rover.formats.wifi import SUBCARRIER_SPACING_HZ


@dataclass(frozen=True)
class CsiFrames:
    """The packets of one capture, all of one shape (a capture mixing shapes keeps its commonest and
    counts the others in `dropped`). Per-packet arrays have P rows; NaN, -1 or zeros where the
    source does not say."""

    source: str
    """the format: "atheros", "nexmon", "picoscenes" (and the device where the file names it)"""
    csi: np.ndarray
    """(P, K, N, T) complex128: P packets, K subcarriers, N receive chains, T transmit streams"""
    subcarriers: np.ndarray
    """(K,) int: each column's subcarrier index (spacing SUBCARRIER_SPACING_HZ from the centre)"""
    bandwidth_hz: float
    centre_freq_hz: np.ndarray
    """(P,) float: the channel's centre frequency (NaN where the file does not say)"""
    timestamp_ns: np.ndarray
    """(P,) int64: the source's own clock (the NIC's for Atheros and PicoScenes, the capture's for Nexmon)"""
    rssi_db: np.ndarray
    """(P, N) float: per receive chain as the source reports it (Atheros: dB over the noise floor;
    PicoScenes: dBm), NaN where it does not"""
    noise_dbm: np.ndarray
    """(P,) float: the noise floor, NaN where not given"""
    mac: np.ndarray
    """(P, 6) uint8: the transmitter's address (zeros where not given)"""
    sequence: np.ndarray
    """(P,) int: the 802.11 sequence number (-1 where not given)"""
    dropped: dict[str, int]
    """records left out, by why"""

    def __len__(self) -> int:
        return len(self.csi)

    @property
    def offsets_hz(self) -> np.ndarray:
        """(K,) each subcarrier's offset from the centre frequency."""
        return self.subcarriers * SUBCARRIER_SPACING_HZ

    def take(self, rows: np.ndarray, why: str) -> CsiFrames:
        """These packets only; the others counted in `dropped` as `why`."""
        left = len(self) - len(rows)
        dropped = {**self.dropped, why: self.dropped.get(why, 0) + left} if left else dict(self.dropped)
        return replace(
            self,
            csi=self.csi[rows],
            centre_freq_hz=self.centre_freq_hz[rows],
            timestamp_ns=self.timestamp_ns[rows],
            rssi_db=self.rssi_db[rows],
            noise_dbm=self.noise_dbm[rows],
            mac=self.mac[rows],
            sequence=self.sequence[rows],
            dropped=dropped,
        )

    def __post_init__(self) -> None:
        p, k, n, _t = self.csi.shape
        shapes = {
            "subcarriers": (self.subcarriers.shape, (k,)),
            "centre_freq_hz": (self.centre_freq_hz.shape, (p,)),
            "timestamp_ns": (self.timestamp_ns.shape, (p,)),
            "rssi_db": (self.rssi_db.shape, (p, n)),
            "noise_dbm": (self.noise_dbm.shape, (p,)),
            "mac": (self.mac.shape, (p, 6)),
            "sequence": (self.sequence.shape, (p,)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"CsiFrames.{name}: shape {got}, expected {want}")
