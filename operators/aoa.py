"""`aoa`: the direct-path angle of arrival of each tag, from the CSI of one burst (one dwell of the sweep).

Each packet is cleaned and smoothed (rover.music); the burst's covariances are averaged (the
packets see the same paths, their random common phases cancel in the covariance), and joint
angle-delay MUSIC on that average gives the paths. Among the strong peaks, the one with the
smallest delay is the direct path (SpotFi's insight: reflections travel farther). Measured on
simulated bursts, this beats clustering per-packet peaks, whose spurious small-delay peaks
win too often. The reported standard deviation has a floor for what a burst cannot show
(multipath bias, calibration error) and grows with strong competing peaks at other angles and
where the array is nearly ambiguous.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.errors import BadInput, SpecError
from rover.messages import header, make
from rover.music import JointMusic
from rover.operator import Emit, In, Operator, Out
from rover.rig import Rig, rig_from_text
from rover.wifi import SPEED_OF_LIGHT_M_S, channel_freq_hz

log = logging.getLogger("rover.aoa")

QUALITY_GOOD = 0
QUALITY_WEAK_SUPPORT = 1
"""No cluster had the support asked for: the largest one is reported."""
QUALITY_AMBIGUOUS = 2
"""The estimate lies where the array can hardly tell it from another direction."""
AMBIGUOUS_CORRELATION = 0.9999
GEOMETRY_GRID_DEG = 0.25
NEAR_AMBIGUOUS_CORRELATION = 0.9
AMBIGUITY_SEPARATION_DEG = 10.0


@dataclass(frozen=True)
class AoaParams:
    grid_deg: float = 4.0
    """coarse angle grid; peaks are refined on a grid 8 times finer"""
    window: int = 8
    """subcarriers per smoothing window"""
    max_paths: int = 4
    min_packets: int = 3
    max_burst_s: float = 0.5
    cluster_deg: float = 15.0
    """peaks closer than this to the direct path's angle do not count as competing"""
    cluster_ns: float = 15.0
    """competing peaks count less the farther their delay is from the direct path's"""
    support: float = 0.01
    """pseudo-spectrum height, relative to the highest peak, a peak needs to be a direct-path candidate"""
    std_floor_deg: float = 4.0
    spread_weight: float = 1.0
    calibrate: bool = True
    """remove the rig's per-chain phase offsets (off only to show what calibration is worth)"""
    remove_sto: bool = True
    """remove each packet's sampling-time-offset phase slope (off only to show what it is worth)"""


def manifold_correlation(antennas_m: np.ndarray, freq_hz: float, angles: np.ndarray) -> np.ndarray:
    """|a(i)^H a(j)| / M for all pairs of the given angles."""
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    a = np.exp(2j * np.pi * freq_hz * (u @ antennas_m.T) / SPEED_OF_LIGHT_M_S)
    return np.abs(a @ a.conj().T) / len(antennas_m)


def array_axis(antennas_m: np.ndarray) -> np.ndarray | None:
    """Unit vector along a collinear array (None when the antennas span the plane)."""
    centred = antennas_m - antennas_m.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-6) >= 2:
        return None
    axis = centred[np.argmax(np.linalg.norm(centred, axis=1))]
    return axis / np.linalg.norm(axis)


def field_normal(axis: np.ndarray) -> np.ndarray:
    """The side of a collinear array's axis it reports: forward when it can, else left."""
    normal = np.array([axis[1], -axis[0]])
    if normal[0] < -1e-9 or (abs(normal[0]) <= 1e-9 and normal[1] < 0):
        normal = -normal
    return normal


def check_geometry(antennas_m: np.ndarray, max_freq_hz: float) -> str | None:
    """Refuse an array for which two directions 10 degrees apart give the same phase differences;
    warn that a collinear one resolves one side of its axis only (it is compared on that side)."""
    angles = np.radians(np.arange(0.0, 360.0, GEOMETRY_GRID_DEG))
    axis = array_axis(antennas_m)
    if axis is not None:
        normal = field_normal(axis)
        angles = angles[np.cos(angles) * normal[0] + np.sin(angles) * normal[1] >= 0]
    corr = manifold_correlation(antennas_m, max_freq_hz, angles)
    gap = np.abs(np.angle(np.exp(1j * (angles[:, None] - angles[None, :]))))
    bad = (gap >= np.radians(AMBIGUITY_SEPARATION_DEG)) & (corr >= AMBIGUOUS_CORRELATION)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise BadInput(f"aoa: the antenna array cannot tell {math.degrees(angles[i]):.0f} deg from "
                       f"{math.degrees(angles[j]):.0f} deg at {max_freq_hz / 1e6:.0f} MHz (spacing too large for "
                       "the wavelength): fix receiver.antenna_positions_m")
    if axis is not None:
        return "aoa: the antennas are collinear, so angles are resolved only on one side of the array's axis"
    return None


def choose_direct(angle: np.ndarray, delay: np.ndarray, height: np.ndarray, paths: int, p: AoaParams):
    """Direct path among one spectrum's peaks: (angle, delay, competing spread (rad), quality).

    Candidates are the `paths` highest peaks (as many as the covariance has signal eigenvalues)
    that reach `support` of the highest; the direct path is the candidate with the smallest
    delay. A candidate at another angle whose delay is hard to tell from the chosen one makes
    the choice doubtful: it widens the spread by its angular distance, weighted by its height
    and by how close its delay is."""
    top = np.argsort(-height)[:max(paths, 1)]
    candidates = top[height[top] >= p.support * height.max()] if height.max() > 0 else np.array([], int)
    if len(candidates) == 0:
        return None
    best = candidates[np.argmin(delay[candidates])]
    others = np.array([j for j in candidates if j != best], dtype=int)
    gaps = np.angle(np.exp(1j * (angle[others] - angle[best])))
    close_in_delay = np.exp(-(((delay[others] - delay[best]) / (p.cluster_ns * 1e-9)) ** 2))
    weights = height[others] / (height[best] + height[others]) * close_in_delay
    far = np.abs(gaps) > math.radians(p.cluster_deg)
    spread = float(np.sqrt(np.sum(weights[far] * gaps[far] ** 2)))
    quality = QUALITY_WEAK_SUPPORT if np.any(weights[far] > 0.25) else QUALITY_GOOD
    return float(angle[best]), float(delay[best]), spread, quality


class Aoa(Operator):
    """One Aoa message per burst of a tag's packets."""

    inputs = {"csi": In("rover_msgs/msg/Csi"), "setup": In("rover_msgs/msg/RigSetup")}
    outputs = {"aoa": Out("rover_msgs/msg/Aoa")}
    Params = AoaParams
    lateness_s = 1.0

    def __init__(self, params: AoaParams | None = None):
        super().__init__(params)
        self.rig: Rig | None = None
        self.estimators: dict[int, JointMusic] = {}
        self.waiting: list[tuple[Any, int]] = []
        self.burst: list[tuple[Any, int]] = []
        self.skipped: Counter = Counter()
        self.half_plane_normal: np.ndarray | None = None
        self._ambiguity_tables: dict[float, np.ndarray] = {}

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "setup":
            self._configure(msg.setup_yaml)
            pending, self.waiting = self.waiting, []
            for csi, stamp in pending:
                yield from self._add(csi, stamp)
        elif self.rig is None:
            self.waiting.append((msg, stamp_ns))
        else:
            yield from self._add(msg, stamp_ns)

    def _configure(self, text: str) -> None:
        try:
            self.rig = rig_from_text(text, "RigSetup")
        except SpecError as exc:
            raise BadInput(f"rig description on the setup input: {exc.diagnostics[0]}") from None
        antennas = self.rig.antenna_positions_m
        top = max((channel_freq_hz(t.channel) for t in self.rig.tags), default=5.9e9)
        warning = check_geometry(antennas, top)
        if warning:
            log.warning("%s", warning)
            self.half_plane_normal = field_normal(array_axis(antennas))

    def _estimator(self, channel: int) -> JointMusic:
        if channel not in self.estimators:
            p = self.params
            self.estimators[channel] = JointMusic(self.rig.antenna_positions_m, channel, window=p.window,
                                                  angle_step_deg=p.grid_deg, max_paths=p.max_paths)
        return self.estimators[channel]

    def _add(self, msg: Any, stamp_ns: int):
        if self.burst:
            first, last = self.burst[0], self.burst[-1]
            if (msg.tag_id != first[0].tag_id or stamp_ns - first[1] > self.params.max_burst_s * 1e9
                    or stamp_ns - last[1] > self.params.max_burst_s * 1e9 / 2):
                yield from self._flush()
        self.burst.append((msg, stamp_ns))

    def _flush(self):
        burst, self.burst = self.burst, []
        usable = [(m, s) for m, s in burst if m.nrx == len(self.rig.antenna_positions_m)]
        if len(usable) < len(burst):
            self.skipped["packets with another antenna count"] += len(burst) - len(usable)
        if len(usable) < self.params.min_packets:
            self.skipped["bursts with too few packets"] += 1
            return
        msg0 = usable[0][0]
        csi = np.stack([(m.csi_real.astype(np.float64) + 1j * m.csi_imag.astype(np.float64))
                        .reshape(30, m.nrx, m.ntx)[:, :, 0] for m, _ in usable])
        finite = np.isfinite(csi).all(axis=(1, 2)) & (np.abs(csi).sum(axis=(1, 2)) > 0)
        if finite.sum() < self.params.min_packets:
            self.skipped["bursts of empty or invalid CSI"] += 1
            return
        csi = csi[finite]
        music = self._estimator(msg0.channel)
        offsets = self.rig.phase_offsets(msg0.channel) if self.params.calibrate else None
        clean = music.clean(csi, offsets, sto=self.params.remove_sto)
        cov = music.covariance(clean).mean(axis=0, keepdims=True)
        spectrum, _paths = music.spectrum(cov)
        peaks = music.refine(music.peaks(spectrum, k=self.params.max_paths))
        angle = peaks.angle[0]
        if self.half_plane_normal is not None:
            u = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
            behind = u @ self.half_plane_normal < 0
            mirror = 2 * math.atan2(-self.half_plane_normal[0], self.half_plane_normal[1])
            angle = np.where(behind, np.angle(np.exp(1j * (mirror - angle))), angle)
        chosen = choose_direct(angle, peaks.delay[0], peaks.height[0], int(_paths[0]), self.params)
        if chosen is None:
            self.skipped["bursts without a spectrum peak"] += 1
            return
        theta, tau, spread, quality = chosen
        used = len(csi)
        std = math.sqrt((self.params.spread_weight * spread) ** 2 + math.radians(self.params.std_floor_deg) ** 2)
        std, quality = self._ambiguity(theta, std, quality, music.center_hz)
        stamps = sorted(s for _, s in usable)
        stamp = stamps[len(stamps) // 2]
        yield Emit("aoa", make("rover_msgs/msg/Aoa", header=header(stamp, "base_link"), tag_id=msg0.tag_id,
                               channel=msg0.channel, angle_rad=theta, std_rad=std, tof_s=tau, packets=used,
                               quality=quality), stamp)

    def _ambiguity(self, theta: float, std: float, quality: int, freq_hz: float) -> tuple[float, int]:
        """Inflate the std where another direction 10+ degrees away looks almost the same to the array."""
        if self.half_plane_normal is not None:
            return std, quality
        worst = self._worst_correlation(freq_hz)[int(round(math.degrees(theta))) % 360]
        if worst > NEAR_AMBIGUOUS_CORRELATION:
            std *= 1 + 10 * (worst - NEAR_AMBIGUOUS_CORRELATION)
            quality = quality or QUALITY_AMBIGUOUS
        return std, quality

    def _worst_correlation(self, freq_hz: float) -> np.ndarray:
        """Per whole degree, the highest array correlation with any direction 10+ degrees away (cached)."""
        if freq_hz not in self._ambiguity_tables:
            angles = np.radians(np.arange(360.0))
            corr = manifold_correlation(self.rig.antenna_positions_m, freq_hz, angles)
            gap = np.abs(np.angle(np.exp(1j * (angles[:, None] - angles[None, :]))))
            self._ambiguity_tables[freq_hz] = np.where(gap >= np.radians(AMBIGUITY_SEPARATION_DEG), corr, 0).max(axis=1)
        return self._ambiguity_tables[freq_hz]

    def on_end(self):
        if self.burst:
            yield from self._flush()
        if self.waiting:
            self.skipped["packets before any rig description"] += len(self.waiting)
        if self.skipped:
            log.warning("aoa: no estimate for %s", ", ".join(f"{n} {why}" for why, n in sorted(self.skipped.items())))
