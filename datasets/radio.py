"""The backscatter radio channel and the Intel 5300's view of it.

CSI follows DESIGN.md's convention, `H_m(f) = sum_k g_k exp(-j 2 pi f tau_km)` with
`tau_km = tau_k - (p_m . u(theta_k)) / c`, over two hops: the access point to the tag (at the
excitation channel's frequencies) and the tag to the robot (at the tag's channel), each with
its line-of-sight path and the four first-order wall reflections of a rectangular room (image
method, amplitude reflection coefficient per bounce, 1/distance amplitudes), and on the second hop
the paths via the room's clutter (rover.datasets.clutter) and the direct path's shadowing. Every
pair of paths is one virtual path whose angle is the second hop's. Then the receiver's impairments:
sampling-time offset, common phase, per-chain phase offsets, noise, AGC and int8 quantization.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rover.datasets.clutter import Scatterers
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, SUBCARRIER_SPACING_HZ, SUBCARRIERS_20MHZ, channel_freq_hz
from rover.geometry import wrap_angle


@dataclass(frozen=True)
class Paths:
    """Propagation paths from a source to receiver points: lengths and unit directions toward the source."""

    length_m: np.ndarray  # (N, P)
    gain: np.ndarray  # (N, P) real amplitude
    direction: np.ndarray  # (N, P, 2) unit vectors from the receiver toward where the path arrives from


def images(source: np.ndarray, room_m: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The source and its first-order images in the four walls, and their bounce counts."""
    w, h = room_m
    x, y = source
    points = np.array([[x, y], [-x, y], [2 * w - x, y], [x, -y], [x, 2 * h - y]])
    return points, np.array([0, 1, 1, 1, 1])


def paths(source: np.ndarray, receivers: np.ndarray, room_m: tuple[float, float], reflection: float) -> Paths:
    """Line of sight and first-order reflections from `source` to each receiver point (N, 2)."""
    points, bounces = images(source, room_m)
    delta = points[None, :, :] - receivers[:, None, :]
    length = np.linalg.norm(delta, axis=-1)
    gain = reflection ** bounces[None, :] / np.maximum(length, 0.05)
    return Paths(length, gain, delta / np.maximum(length, 1e-9)[..., None])


def scattered_paths(source: np.ndarray, receivers: np.ndarray, scatterers: Scatterers) -> Paths:
    """The paths from `source` via each scatterer to each receiver point (N, 2)."""
    to_scatterer = np.linalg.norm(scatterers.xy - source[None, :], axis=1)  # (S,)
    delta = scatterers.xy[None, :, :] - receivers[:, None, :]
    out = np.linalg.norm(delta, axis=-1)  # (N, S)
    gain = scatterers.reflectivity_m[None, :] / (np.maximum(to_scatterer, 0.05)[None, :] * np.maximum(out, 0.05))
    return Paths(to_scatterer[None, :] + out, gain, delta / np.maximum(out, 1e-9)[..., None])


def subcarrier_offsets_hz() -> np.ndarray:
    return SUBCARRIERS_20MHZ * SUBCARRIER_SPACING_HZ


def backscatter_csi(
    ap: np.ndarray,
    tag: np.ndarray,
    robot_xy: np.ndarray,
    robot_yaw: np.ndarray,
    antennas_m: np.ndarray,
    excitation_channel: int,
    tag_channel: int,
    room_m: tuple[float, float],
    reflection: float,
    direct_attenuation_db: float | np.ndarray = 0.0,
    scatterers: Scatterers | None = None,
    offsets_hz: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free CSI (N, K, M) at N robot poses (K: the subcarriers `offsets_hz` from the channels'
    centres, the CSI Tool's 30 unless given), and the direct-to-multipath power ratio (N,) in dB of the
    tag-to-robot link: the first hop's paths share one angle, so only the second hop's set the AoA's difficulty.
    The direct path loses `direct_attenuation_db` (a wall between, shadowing: one value, or one per pose)."""
    n = len(robot_xy)
    offsets = subcarrier_offsets_hz() if offsets_hz is None else offsets_hz
    f1 = channel_freq_hz(excitation_channel) + offsets  # first hop, AP -> tag
    f2 = channel_freq_hz(tag_channel) + offsets  # second hop, tag -> robot
    hop1 = paths(ap, tag[None, :], room_m, reflection)
    hop2 = paths(tag, robot_xy, room_m, reflection)
    if scatterers is not None and len(scatterers.xy):
        via = scattered_paths(tag, robot_xy, scatterers)
        hop2 = Paths(
            np.concatenate([hop2.length_m, via.length_m], axis=1),
            np.concatenate([hop2.gain, via.gain], axis=1),
            np.concatenate([hop2.direction, via.direction], axis=1),
        )
    g2 = hop2.gain.copy()
    g2[:, 0] *= 10 ** (-np.asarray(direct_attenuation_db) / 20)
    cos, sin = np.cos(robot_yaw), np.sin(robot_yaw)
    d = hop2.direction
    body = np.stack(
        [cos[:, None] * d[..., 0] + sin[:, None] * d[..., 1], -sin[:, None] * d[..., 0] + cos[:, None] * d[..., 1]],
        axis=-1,
    )  # (N, P2, 2) robot frame
    projection = body @ antennas_m.T  # (N, P2, M)
    h1 = (
        hop1.gain[0][:, None] * np.exp(-2j * np.pi * f1[None, :] * hop1.length_m[0][:, None] / SPEED_OF_LIGHT_M_S)
    ).sum(axis=0)  # (K,)
    tau2 = (hop2.length_m[:, :, None] - projection) / SPEED_OF_LIGHT_M_S  # (N, P2, M)
    h2 = np.einsum("np,npfm->nfm", g2, np.exp(-2j * np.pi * f2[None, None, :, None] * tau2[:, :, None, :]))
    csi = h1[None, :, None] * h2
    ratio_db = 10 * np.log10(g2[:, 0] ** 2 / np.maximum((g2[:, 1:] ** 2).sum(axis=1), 1e-30))
    return csi.reshape(n, len(offsets), len(antennas_m)), ratio_db


def true_aoa(tag: np.ndarray, robot_xy: np.ndarray, robot_yaw: np.ndarray) -> np.ndarray:
    """Direct-path angle of arrival in the robot frame, CCW from forward, in (-pi, pi]."""
    d = tag[None, :] - robot_xy
    angle = np.arctan2(d[:, 1], d[:, 0]) - robot_yaw
    return wrap_angle(angle)


@dataclass(frozen=True)
class Impairments:
    """Per-packet receiver effects (all arrays per packet) and the constant per-chain offsets."""

    sampling_offset_s: np.ndarray
    common_phase: np.ndarray
    snr_db: np.ndarray
    peak: np.ndarray
    chain_offsets_rad: np.ndarray
    """(M,) for all packets, or (N, M) per packet (phase jumps)"""


def impair(
    csi: np.ndarray,
    imp: Impairments,
    rng: np.random.Generator,
    offsets_hz: np.ndarray | None = None,
    int8: bool = True,
) -> np.ndarray:
    """Apply the receiver's effects to CSI (N, K, M) at the subcarriers `offsets_hz` (the CSI Tool's
    30 unless given) and, for the Intel 5300 (`int8`), its AGC and quantization to int8 values."""
    offsets = subcarrier_offsets_hz() if offsets_hz is None else offsets_hz
    phase = -2 * np.pi * offsets[None, :] * imp.sampling_offset_s[:, None] + imp.common_phase[:, None]
    chains = np.exp(1j * np.asarray(imp.chain_offsets_rad))
    out = csi * np.exp(1j * phase)[:, :, None] * (chains[:, None, :] if chains.ndim == 2 else chains[None, None, :])
    power = np.mean(np.abs(out) ** 2, axis=(1, 2))
    sigma = np.sqrt(power / 10 ** (imp.snr_db / 10) / 2)
    out = out + sigma[:, None, None] * (rng.standard_normal(out.shape) + 1j * rng.standard_normal(out.shape))
    if not int8:
        return out
    largest = np.maximum(np.abs(out.real), np.abs(out.imag)).max(axis=(1, 2))
    out = out * (imp.peak / np.maximum(largest, 1e-30))[:, None, None]
    return np.clip(np.rint(out.real), -128, 127) + 1j * np.clip(np.rint(out.imag), -128, 127)
