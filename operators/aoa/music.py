"""Joint angle-delay MUSIC for small arrays of any 2-D geometry, vectorized over packets.

The CSI of one packet, H[subcarrier, antenna], is cleaned (per-chain calibration removed, the
sampling-time offset's phase slope fitted and removed), then turned into a covariance by
smoothing along subcarriers: windows of L consecutive subcarriers from the runs that are evenly
spaced (the 20 MHz set is not: -28..-2 and 1..27 step by 625 kHz, -1 and 28 do not), all three
antennas in every window. Shifting along frequency keeps each window's array manifold the same,
which is what smoothing needs; shifting along antennas (SpotFi's smoothing) needs an array whose
subarrays are translates of each other, which a triangle is not. No forward-backward averaging:
on a non-centro-symmetric array it mirrors the angles by 180 degrees.

Of the peaks of a burst's spectrum, `choose_direct` picks the direct path, `check_energy` checks
that choice against the power each direction explains (Bartlett, rover.operators.aoa.array) and
`burst_std` gives the reported angle's standard deviation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from rover.formats.wifi import SUBCARRIER_SPACING_HZ, SUBCARRIERS_20MHZ, channel_freq_hz
from rover.geometry import wrap_angle
from rover.operators.aoa.array import ArrayResponse, steering

if TYPE_CHECKING:
    from rover.operators.aoa.operator import AoaParams

NOISE_FACTOR = 10.0
"""An eigenvalue counts as a path when it is this many times the noise level (median of the lower half)..."""
PATH_FLOOR = 10**-2.5
"""...and within 25 dB of the strongest: weaker ones are model mismatch (the antenna phases change a
little across the 20 MHz band), not paths."""
MAX_STD_RAD = math.pi
"""an angle known to be nowhere in particular"""


def run_step(indices: np.ndarray) -> int:
    """Subcarrier index step inside an evenly spaced run: 2 at 20 MHz (625 kHz), 4 at 40 MHz (1.25 MHz)."""
    return int(np.bincount(np.diff(indices)).argmax())  # the commonest step (20 MHz has a few odd ones at DC)


def even_runs(indices: np.ndarray) -> list[np.ndarray]:
    """Positions of the maximal runs of subcarriers spaced `run_step` apart."""
    breaks = np.flatnonzero(np.diff(indices) != run_step(indices)) + 1
    return [run for run in np.split(np.arange(len(indices)), breaks) if len(run) > 1]


@dataclass(frozen=True)
class Peaks:
    """Up to `k` spectrum peaks per packet: angle (rad, robot frame), delay (s), normalized height."""

    angle: np.ndarray  # (P, k)
    delay: np.ndarray  # (P, k)
    height: np.ndarray  # (P, k), 0 where there is no peak


class JointMusic:
    """Estimator for one array and one channel: build once, apply to many packets."""

    def __init__(
        self,
        antennas_m: np.ndarray,
        channel: int,
        window: int = 8,
        angle_step_deg: float = 4.0,
        delay_range_s: tuple[float, float] = (-100e-9, 200e-9),
        delay_step_s: float = 10e-9,
        max_paths: int = 4,
        refine_steps: int = 8,
        subcarriers: np.ndarray = SUBCARRIERS_20MHZ,
        center_hz: float | None = None,
    ):
        self.antennas = np.asarray(antennas_m, dtype=np.float64)
        self.channel = channel
        self.center_hz = channel_freq_hz(channel) if center_hz is None else center_hz
        self.offsets_hz = subcarriers * SUBCARRIER_SPACING_HZ
        runs = even_runs(subcarriers)
        self.windows = np.array([run[i : i + window] for run in runs for i in range(len(run) - window + 1)])
        if len(self.windows) == 0:
            raise ValueError(f"smoothing window {window} is longer than every evenly spaced run of subcarriers")
        self.window = window
        self.step_hz = run_step(subcarriers) * SUBCARRIER_SPACING_HZ
        self.max_paths = max_paths
        self.angles = np.radians(np.arange(-180.0, 180.0, angle_step_deg))
        self.delays = np.arange(delay_range_s[0], delay_range_s[1] + delay_step_s / 2, delay_step_s)
        self.angle_manifold = self.steer_angle(self.angles)  # (Na, M)
        pairs = self.angle_manifold[:, None, :] * self.angle_manifold[:, :, None].conj()  # [a, m, n] = conj(a_m) a_n
        self._pairs_real = np.ascontiguousarray(pairs.real.reshape(len(self.angles), -1))
        self._pairs_imag = np.ascontiguousarray(pairs.imag.reshape(len(self.angles), -1))
        self.delay_manifold = self.steer_delay(self.delays)  # (Nd, L)
        self.refine_offsets = np.linspace(-1.0, 1.0, 2 * refine_steps + 1)

    def steer_angle(self, angles: np.ndarray) -> np.ndarray:
        """Antenna phases of a plane wave from each angle, at the channel's centre frequency."""
        return steering(self.antennas, self.center_hz, angles)

    def steer_delay(self, delays: np.ndarray) -> np.ndarray:
        """Phases along one smoothing window of a path with each delay: exp(-j 2 pi l step tau)."""
        return np.exp(-2j * np.pi * self.step_hz * np.arange(self.window)[None, :] * delays[:, None])

    def clean(self, csi: np.ndarray, phase_offsets_rad: np.ndarray | None = None, sto: bool = True) -> np.ndarray:
        """Remove the per-chain phase offsets and each packet's sampling-time-offset slope. csi: (P, K, M)."""
        h = np.asarray(csi, dtype=np.complex128)
        if phase_offsets_rad is not None:
            h = h * np.exp(-1j * np.asarray(phase_offsets_rad))[None, None, :]
        if not sto:
            return h
        phase = np.unwrap(np.angle(h), axis=1)
        f = self.offsets_hz - self.offsets_hz.mean()
        centred = phase - phase.mean(axis=1, keepdims=True)
        slope = np.einsum("n,pnm->p", f, centred) / (h.shape[2] * np.sum(f * f))
        return h * np.exp(-1j * slope[:, None, None] * f[None, :, None])

    def covariance(self, clean: np.ndarray) -> np.ndarray:
        """Subcarrier-smoothed covariance per packet, (P, M*L, M*L), element order antenna-major."""
        snapshots = clean[:, self.windows, :]  # (P, W, L, M)
        x = snapshots.transpose(0, 1, 3, 2).reshape(clean.shape[0], len(self.windows), -1)
        return np.einsum("pwi,pwj->pij", x, x.conj()) / len(self.windows)

    def spectrum(self, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """MUSIC pseudo-spectrum over the (angle, delay) grid, (P, Na, Nd), and the number of paths found
        above the noise (0: noise only; the spectrum then uses one)."""
        values, vectors = np.linalg.eigh(cov)  # ascending
        values = np.maximum(values[:, ::-1], 0)
        vectors = vectors[:, :, ::-1]
        lower = np.sort(values[:, values.shape[1] // 2 :], axis=1)  # np.median is slow on small arrays
        half = lower.shape[1] // 2
        noise = 0.5 * (lower[:, half - 1 + lower.shape[1] % 2] + lower[:, half])[:, None] + 1e-30
        floor = np.maximum(NOISE_FACTOR * noise, values[:, :1] * PATH_FLOOR)
        found = np.minimum(np.sum(values > floor, axis=1), self.max_paths)
        paths = np.maximum(found, 1)
        signal = vectors[:, :, : self.max_paths] * (np.arange(self.max_paths)[None, :] < paths[:, None])[:, None, :]
        m, w = len(self.antennas), self.window
        e = signal.reshape(signal.shape[0], m, w, self.max_paths).transpose(0, 3, 1, 2).conj()  # (P, K, M, L)
        along_delay = e @ self.delay_manifold.T  # (P, K, M, Nd)
        # captured(a, d) = sum_k |a^H E_k b_d|^2 = a^H G_d a with G_d = sum_k (E_k b_d)(E_k b_d)^H: real GEMMs
        gram = np.einsum("pkmd,pknd->pdmn", along_delay.conj(), along_delay).reshape(len(cov), -1, m * m)
        captured = self._pairs_real @ gram.real.transpose(2, 0, 1).reshape(m * m, -1)
        captured -= self._pairs_imag @ gram.imag.transpose(2, 0, 1).reshape(m * m, -1)  # (Na, P * Nd)
        captured = captured.reshape(len(self.angles), len(cov), -1).transpose(1, 0, 2)
        out = 1.0 / np.maximum(m * w - captured, 1e-9 * m * w)
        self._signal = e
        return out, found

    def refine(self, peaks: Peaks) -> Peaks:
        """Search a fine grid (one coarse step either side) around each peak, with the signal subspace
        of the last `spectrum` call: coarse-to-fine, so the whole grid never has to be fine."""
        e = self._signal  # (P, K, M, L)
        angle_step = self.angles[1] - self.angles[0]
        delay_step = self.delays[1] - self.delays[0]
        angles = peaks.angle[..., None] + self.refine_offsets * angle_step  # (P, J, F)
        delays = peaks.delay[..., None] + self.refine_offsets * delay_step
        a = self.steer_angle(angles)  # (P, J, F, M)
        b = self.steer_delay(delays.reshape(-1)).reshape(*delays.shape, self.window)  # (P, J, F, L)
        t = e[:, None] @ b.transpose(0, 1, 3, 2)[:, :, None]  # (P, J, K, M, F)
        proj = a[:, :, None] @ t  # (P, J, K, Fa, Fd)
        captured = np.sum(proj.real**2 + proj.imag**2, axis=2)  # (P, J, Fa, Fd)
        n = captured.shape[-1]
        best = np.argmax(captured.reshape(*captured.shape[:2], -1), axis=-1)
        ia, idl = np.unravel_index(best, (n, n))

        def pick(grid: np.ndarray, index: np.ndarray) -> np.ndarray:
            return np.take_along_axis(grid, index[..., None], axis=-1)[..., 0]

        angle = wrap_angle(pick(angles, ia))
        return Peaks(
            np.where(peaks.height > 0, angle, peaks.angle),
            np.where(peaks.height > 0, pick(delays, idl), peaks.delay),
            peaks.height,
        )

    def peaks(self, spectrum: np.ndarray, k: int = 3) -> Peaks:
        """The k highest local maxima per packet, refined by parabolic interpolation on the grid."""
        s = spectrum
        padded = np.concatenate([s[:, -1:], s, s[:, :1]], axis=1)  # angles wrap around
        padded = np.pad(padded, ((0, 0), (0, 0), (1, 1)), constant_values=-np.inf)  # delays do not
        na, nd = s.shape[1:]
        local = np.ones(s.shape, dtype=bool)
        for shift_a in (0, 1, 2):
            for shift_d in (0, 1, 2):
                if (shift_a, shift_d) != (1, 1):
                    local &= s >= padded[:, shift_a : shift_a + na, shift_d : shift_d + nd]
        flat_local = local.reshape(len(s), -1)
        flat = s.reshape(len(s), -1)
        top = np.zeros((len(s), k), dtype=np.int64)
        height = np.zeros((len(s), k))
        for row in range(len(s)):
            found = np.flatnonzero(flat_local[row])
            best = found[np.argsort(flat[row, found])[::-1][:k]]
            top[row, : len(best)] = best
            height[row, : len(best)] = flat[row, best]
        ia, idl = np.unravel_index(top, s.shape[1:])
        p = np.arange(len(s))[:, None]
        centre = s[p, ia, idl]
        da = parabola_offset(s[p, (ia - 1) % na, idl], centre, s[p, (ia + 1) % na, idl])
        inner = (idl > 0) & (idl < nd - 1)
        dd = np.where(
            inner, parabola_offset(s[p, ia, np.maximum(idl - 1, 0)], centre, s[p, ia, np.minimum(idl + 1, nd - 1)]), 0
        )
        angle_step = self.angles[1] - self.angles[0]
        delay_step = self.delays[1] - self.delays[0]
        angle = wrap_angle(self.angles[ia] + da * angle_step)
        delay = self.delays[idl] + dd * delay_step
        norm = height / np.maximum(height.max(axis=1, keepdims=True), 1e-30)
        return Peaks(angle, delay, np.where(height > 0, norm, 0.0))


def parabola_offset(left: np.ndarray, centre: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Offset in grid steps of the vertex of the parabola through three equally spaced points."""
    denom = left - 2 * centre + right
    return np.where(
        np.abs(denom) > 1e-30, np.clip(0.5 * (left - right) / np.where(denom == 0, 1, denom), -0.5, 0.5), 0.0
    )


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
    if switched and alt is not None:
        near_rival = response.sidelobe[response.degree(np.radians(alt)), response.degree(angle)] == 0
        switched = not np.any(near_rival & peaks & (delay >= delay[best] + p.resolved_ns * 1e-9))
    if switched and alt is not None:
        left, right = energy[alt - 1], energy[(alt + 1) % 360]
        top = energy[alt] >= max(left, right)
        offset = float(parabola_offset(left, energy[alt], right)) if top else 0.0
        theta = float(wrap_angle(np.radians(alt + offset)))
        power = float(energy[alt])
        alt = rival(theta)
    if alt is None:
        return Direction(theta, max(power, 0.0), 0.0, 0.0, bool(switched))
    gap = abs(float(wrap_angle(np.radians(alt) - theta)))
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
