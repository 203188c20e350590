"""`aoa`: the direct-path angle of arrival of each tag, from the CSI of one burst (one dwell of the sweep).

Each packet is cleaned and smoothed (rover.operators.aoa.music); the burst's covariances are averaged (the
packets see the same paths, their random common phases cancel in the covariance), and joint
angle-delay MUSIC on that average gives the paths. The strongest peak is the direct path unless
a weaker one clearly arrives earlier (SpotFi's insight: reflections travel farther). Measured on
simulated bursts, this beats clustering per-packet peaks, whose spurious small-delay peaks win
too often. The choice is checked against the power each direction explains, and the reported
standard deviation comes from what a single plane wave from the reported angle leaves
unexplained and from the strongest rival direction (see `burst_std`).
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass
from typing import Any

import numpy as np

from rover.errors import BadInput, SpecError
from rover.formats.rig import Rig, rig_from_text
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, channel_freq_hz
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.operators.aoa.music import JointMusic, parabola_offset

log = logging.getLogger("rover.aoa")

QUALITY_GOOD = 0
QUALITY_RIVAL = 1
"""A direction outside the reported one's main lobe explains nearly as much power (more than RIVAL_SHARE of it)."""
QUALITY_AMBIGUOUS = 2
"""The estimate lies where the array can hardly tell it from another direction."""
QUALITY_SWITCHED = 3
"""The MUSIC choice held clearly less power than a direction outside its main lobe: that one is reported."""
RIVAL_SHARE = 0.9
MAX_STD_RAD = math.pi
"""an angle known to be nowhere in particular"""
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
    support: float = 0.01
    """pseudo-spectrum height, relative to the highest peak, a peak needs to be a direct-path candidate"""
    delay_margin_ns: float = 5.0
    """a weaker candidate replaces a stronger one only when it arrives more than this much earlier"""
    energy_ratio: float = 1.2
    """report the strongest direction instead when it holds this many times the chosen one's power"""
    resolved_ns: float = 25.0
    """...unless MUSIC sees a path there arriving this much later than its choice"""
    std_floor_deg: float = 2.0
    """what no burst shows: calibration error, noise"""
    multipath_std_deg: float = 30.0
    """std per unit of sqrt(unexplained / explained power) at the reported angle (coherent multipath)"""
    doubt_sharpness: float = 60.0
    """how fast a rival direction's chance grows with its power relative to the reported one"""
    calibrate: bool = True
    """remove the rig's per-chain phase offsets (off only to show what calibration is worth)"""
    remove_sto: bool = True
    """remove each packet's sampling-time-offset phase slope (off only to show what it is worth)"""


def steering(antennas_m: np.ndarray, freq_hz: float, angles: np.ndarray) -> np.ndarray:
    """Antenna phases (N, M) of a plane wave from each angle."""
    u = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return np.exp(2j * np.pi * freq_hz * (u @ antennas_m.T) / SPEED_OF_LIGHT_M_S)


def manifold_correlation(antennas_m: np.ndarray, freq_hz: float, angles: np.ndarray) -> np.ndarray:
    """|a(i)^H a(j)| / M for all pairs of the given angles."""
    a = steering(antennas_m, freq_hz, angles)
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
        raise BadInput(
            f"aoa: the antenna array cannot tell {math.degrees(angles[i]):.0f} deg from "
            f"{math.degrees(angles[j]):.0f} deg at {max_freq_hz / 1e6:.0f} MHz (spacing too large for "
            "the wavelength): fix receiver.antenna_positions_m"
        )
    if axis is not None:
        return "aoa: the antennas are collinear, so angles are resolved only on one side of the array's axis"
    return None


class ArrayResponse:
    """The array at one frequency, per whole degree: its steering vectors, and how alike it sees a
    direction j outside direction i's main lobe, sidelobe[i, j] (0 inside it; the main lobe ends
    at the first minimum on each side)."""

    def __init__(self, antennas_m: np.ndarray, freq_hz: float):
        self.steering = steering(antennas_m, freq_hz, np.radians(np.arange(360.0)))  # (360, M)
        corr = np.abs(self.steering @ self.steering.conj().T) / len(antennas_m)
        rows = np.arange(360)[:, None]
        index = (rows + np.arange(360)[None, :]) % 360
        by_offset = corr[rows, index]  # [i, d] = corr(i, i + d)

        def lobe_edge(side: np.ndarray) -> np.ndarray:
            """Offset of the first minimum along one side (offsets 0..180)."""
            rising = np.diff(side, axis=1) > 0
            return np.where(rising.any(axis=1), np.argmax(rising, axis=1), 180)

        ccw = lobe_edge(by_offset[:, :181])
        cw = lobe_edge(by_offset[:, (360 - np.arange(181)) % 360])
        d = np.arange(360)[None, :]
        outside = np.zeros((360, 360), dtype=bool)
        outside[rows, index] = ((d <= 180) & (d > ccw[:, None])) | ((d > 180) & (360 - d > cw[:, None]))
        self.sidelobe = np.where(outside, corr, 0.0)

    @staticmethod
    def degree(angle) -> np.ndarray:
        return np.rint(np.degrees(angle)).astype(int) % 360

    def worst(self, a) -> np.ndarray:
        return self.sidelobe[self.degree(a)].max(axis=-1)

    def energy(self, spatial: np.ndarray) -> np.ndarray:
        """Fraction of the power a plane wave from each whole degree explains (Bartlett), from the (M, M) covariance."""
        a = self.steering
        return np.einsum("am,mn,an->a", a.conj(), spatial, a).real / (a.shape[1] * np.trace(spatial).real)


def choose_direct(delay: np.ndarray, height: np.ndarray, paths: int, p: AoaParams) -> int | None:
    """Index of the direct path among one spectrum's peaks (None without any).

    Candidates are the `paths` highest peaks (as many as the covariance has signal eigenvalues)
    that reach `support` of the highest. Reflections travel farther, so a weaker candidate wins
    over a stronger one when it arrives earlier, but only by more than `delay_margin_ns`: at
    20 MHz smaller delay differences are within the estimates' scatter, and picking by them
    picks spurious peaks."""
    top = np.argsort(-height)[: max(paths, 1)]
    candidates = top[height[top] >= p.support * height.max()] if height.max() > 0 else np.array([], int)
    if len(candidates) == 0:
        return None
    best = candidates[0]
    for j in candidates[1:]:
        if delay[j] < delay[best] - p.delay_margin_ns * 1e-9:
            best = j
    return int(best)


@dataclass(frozen=True)
class Direction:
    """The reported angle, the power share a plane wave from it explains, and its strongest rival
    outside its main lobe (power share, angular distance)."""

    angle_rad: float
    power: float
    rival_power: float
    rival_gap_rad: float
    switched: bool


def check_energy(
    angle: np.ndarray,
    delay: np.ndarray,
    height: np.ndarray,
    best: int,
    energy: np.ndarray,
    response: ArrayResponse,
    field: np.ndarray,
    p: AoaParams,
) -> Direction:
    """Compare the MUSIC choice (peak `best` of the peaks `angle`, `delay`, `height`) with the power
    each direction explains (Bartlett, whole degrees; only directions in `field` compete).

    The triangle's back lobe is strong (correlation 0.92 at lambda/2): a reflection or noise
    turns the true direction's mirror into a MUSIC peak with a small delay. When a direction
    outside the chosen one's main lobe explains `energy_ratio` times more power, and MUSIC does
    not resolve a path there (a peak of `support`) arriving clearly later (by `resolved_ns`: a
    real, stronger reflection), the strongest such direction is reported instead (on the
    simulator this removes a third of the gross errors, LOS and NLOS). An array whose main lobe
    covers every direction in the field has no rival."""
    theta = float(angle[best])
    peaks = height >= p.support * height.max()

    def rival(angle: float) -> int | None:
        rivals = np.where(field & (response.sidelobe[response.degree(angle)] > 0), energy, -np.inf)
        alt = int(np.argmax(rivals))
        return alt if np.isfinite(rivals[alt]) else None

    power = float(energy[response.degree(theta)])
    alt = rival(theta)
    switched = alt is not None and energy[alt] > p.energy_ratio * power
    if switched:
        near_rival = response.sidelobe[response.degree(np.radians(alt)), response.degree(angle)] == 0
        switched = not np.any(near_rival & peaks & (delay >= delay[best] + p.resolved_ns * 1e-9))
    if switched:
        left, right = energy[alt - 1], energy[(alt + 1) % 360]
        top = energy[alt] >= max(left, right)
        offset = float(parabola_offset(left, energy[alt], right)) if top else 0.0
        theta = float(np.angle(np.exp(1j * np.radians(alt + offset))))
        power = float(energy[alt])
        alt = rival(theta)
    if alt is None:
        return Direction(theta, max(power, 0.0), 0.0, 0.0, bool(switched))
    gap = abs(float(np.angle(np.exp(1j * (np.radians(alt) - theta)))))
    return Direction(theta, max(power, 0.0), max(float(energy[alt]), 0.0), gap, bool(switched))


def burst_std(d: Direction, p: AoaParams) -> float:
    """Standard deviation of the reported angle (rad).

    Three parts, added as variances: a floor; coherent multipath, which bends the angle by
    roughly the beamwidth times the amplitude ratio of what one plane wave cannot explain,
    sqrt((1 - power) / power); and the rival direction, counted with its angular distance and a
    chance that grows steeply with its power relative to the reported one's (the mixture's
    variance). Constants fitted on simulated bursts (paper scenario) and checked on the
    independent recording; see bench/bench_aoa.py. At most MAX_STD_RAD."""
    unexplained = (1 - min(d.power, 1.0)) / max(d.power, 1e-6)
    ratio = d.rival_power / max(d.power, 1e-6)
    chance = 0.5 * (1 + math.tanh(0.5 * p.doubt_sharpness * math.log(ratio))) if ratio > 0 else 0.0
    variance = (
        math.radians(p.std_floor_deg) ** 2
        + math.radians(p.multipath_std_deg) ** 2 * unexplained
        + chance * d.rival_gap_rad**2
    )
    return min(math.sqrt(variance), MAX_STD_RAD) if math.isfinite(variance) else MAX_STD_RAD


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
        self._responses: dict[float, ArrayResponse] = {}
        self.field = np.ones(360, dtype=bool)

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
        self.estimators, self._responses = {}, {}
        self.half_plane_normal, self.field = None, np.ones(360, dtype=bool)
        if warning:
            log.warning("%s", warning)
            self.half_plane_normal = field_normal(array_axis(antennas))
            degrees = np.radians(np.arange(360.0))
            self.field = np.cos(degrees) * self.half_plane_normal[0] + np.sin(degrees) * self.half_plane_normal[1] >= 0

    def _estimator(self, channel: int) -> JointMusic:
        if channel not in self.estimators:
            p = self.params
            self.estimators[channel] = JointMusic(
                self.rig.antenna_positions_m, channel, window=p.window, angle_step_deg=p.grid_deg, max_paths=p.max_paths
            )
        return self.estimators[channel]

    def _add(self, msg: Any, stamp_ns: int):
        if self.burst:
            first, last = self.burst[0], self.burst[-1]
            if (
                msg.tag_id != first[0].tag_id
                or stamp_ns - first[1] > self.params.max_burst_s * 1e9
                or stamp_ns - last[1] > self.params.max_burst_s * 1e9 / 2
            ):
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
        csi = np.stack(
            [
                (m.csi_real.astype(np.float64) + 1j * m.csi_imag.astype(np.float64)).reshape(30, m.nrx, m.ntx)[:, :, 0]
                for m, _ in usable
            ]
        )
        finite = np.isfinite(csi).all(axis=(1, 2)) & (np.abs(csi).sum(axis=(1, 2)) > 0)
        if finite.sum() < self.params.min_packets:
            self.skipped["bursts of empty or invalid CSI"] += 1
            return
        csi = csi[finite]
        music = self._estimator(msg0.channel)
        offsets = self.rig.phase_offsets(msg0.channel) if self.params.calibrate else None
        clean = music.clean(csi, offsets, sto=self.params.remove_sto)
        cov = music.covariance(clean).mean(axis=0, keepdims=True)
        spectrum, paths = music.spectrum(cov)
        if paths[0] == 0:
            self.skipped["bursts too noisy (no path above the noise)"] += 1
            return
        peaks = music.refine(music.peaks(spectrum, k=self.params.max_paths))
        angle = peaks.angle[0]
        if self.half_plane_normal is not None:
            u = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
            behind = u @ self.half_plane_normal < 0
            mirror = 2 * math.atan2(-self.half_plane_normal[0], self.half_plane_normal[1])
            angle = np.where(behind, np.angle(np.exp(1j * (mirror - angle))), angle)
        best = choose_direct(peaks.delay[0], peaks.height[0], int(paths[0]), self.params)
        if best is None:
            self.skipped["bursts without a spectrum peak"] += 1
            return
        response = self._response(music.center_hz)
        energy = response.energy(np.einsum("pfm,pfn->mn", clean, clean.conj()))
        direction = check_energy(
            angle, peaks.delay[0], peaks.height[0], best, energy, response, self.field, self.params
        )
        theta, tau, used = direction.angle_rad, float(peaks.delay[0, best]), len(csi)
        if direction.switched:
            distance = np.where(peaks.height[0] > 0, np.abs(np.angle(np.exp(1j * (angle - theta)))), np.inf)
            tau = float(peaks.delay[0, np.argmin(distance)])
        quality = QUALITY_SWITCHED if direction.switched else QUALITY_GOOD
        if direction.rival_power > direction.power * RIVAL_SHARE:
            quality = quality or QUALITY_RIVAL
        std, quality = self._ambiguity(theta, burst_std(direction, self.params), quality, response)
        stamps = sorted(s for _, s in usable)
        stamp = stamps[len(stamps) // 2]
        yield Emit(
            "aoa",
            make(
                "rover_msgs/msg/Aoa",
                header=header(stamp, "base_link"),
                tag_id=msg0.tag_id,
                channel=msg0.channel,
                angle_rad=theta,
                std_rad=std,
                tof_s=tau,
                packets=used,
                quality=quality,
            ),
            stamp,
        )

    def _ambiguity(self, theta: float, std: float, quality: int, response: ArrayResponse) -> tuple[float, int]:
        """Inflate the std where a direction outside the main lobe looks almost the same to the array."""
        if self.half_plane_normal is not None:
            return std, quality
        worst = float(response.worst(theta))
        if worst > NEAR_AMBIGUOUS_CORRELATION:
            std = min(std * (1 + 10 * (worst - NEAR_AMBIGUOUS_CORRELATION)), MAX_STD_RAD)
            quality = quality or QUALITY_AMBIGUOUS
        return std, quality

    def _response(self, freq_hz: float) -> ArrayResponse:
        if freq_hz not in self._responses:
            self._responses[freq_hz] = ArrayResponse(self.rig.antenna_positions_m, freq_hz)
        return self._responses[freq_hz]

    def on_end(self):
        if self.burst:
            yield from self._flush()
        if self.waiting:
            self.skipped["packets before any rig description"] += len(self.waiting)
        if self.skipped:
            log.warning("aoa: no estimate for %s", ", ".join(f"{n} {why}" for why, n in sorted(self.skipped.items())))
