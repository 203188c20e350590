"""The receive array's model: steering vectors from the antenna positions, and how alike the array
sees two directions (near-ambiguity, main lobes), from which the operator checks a rig's geometry,
resolves a collinear array's mirror ambiguity and weighs a direction's rivals.

Directions are angles in the robot frame, counter-clockwise from forward (x); the antenna
positions are (M, 2) in metres in that frame.
"""

from __future__ import annotations

import math

import numpy as np

from rover.errors import BadInput
from rover.formats.wifi import SPEED_OF_LIGHT_M_S
from rover.geometry import wrap_angle

AMBIGUOUS_CORRELATION = 0.9999
"""two directions at least this alike to the array cannot be told apart"""
GEOMETRY_GRID_DEG = 0.25
AMBIGUITY_SEPARATION_DEG = 10.0
"""directions closer than this are neighbours, not an ambiguity"""


def steering(antennas_m: np.ndarray, freq_hz: float, angles: np.ndarray) -> np.ndarray:
    """Antenna phases (..., M) of a plane wave at `freq_hz` from each angle (any shape):
    exp(+j 2 pi f p.u / c), so nearer antennas lead."""
    u = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
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


def on_side(angles: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Whether each direction lies on the side of a collinear array's axis that `normal` points to."""
    return np.cos(angles) * normal[0] + np.sin(angles) * normal[1] >= 0


def fold_to_side(angles: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Angles mirrored across a collinear array's axis onto the side of `normal`: such an array sees a
    direction and its mirror image alike, so only that side is reported."""
    u = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    behind = u @ normal < 0
    mirror = 2 * math.atan2(-normal[0], normal[1])
    return np.where(behind, wrap_angle(mirror - angles), angles)


def check_geometry(antennas_m: np.ndarray, max_freq_hz: float) -> str | None:
    """Refuse an array for which two directions 10 degrees apart give the same phase differences;
    warn that a collinear one resolves one side of its axis only (it is compared on that side)."""
    angles = np.radians(np.arange(0.0, 360.0, GEOMETRY_GRID_DEG))
    axis = array_axis(antennas_m)
    if axis is not None:
        angles = angles[on_side(angles, field_normal(axis))]
    corr = manifold_correlation(antennas_m, max_freq_hz, angles)
    gap = np.abs(wrap_angle(angles[:, None] - angles[None, :]))
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
        """Index of the whole degree nearest each angle (rad)."""
        return np.rint(np.degrees(angle)).astype(int) % 360

    def worst(self, angle) -> np.ndarray:
        """How alike the array sees each angle and the most similar direction outside its main lobe."""
        return self.sidelobe[self.degree(angle)].max(axis=-1)

    def energy(self, spatial: np.ndarray) -> np.ndarray:
        """Fraction of the power a plane wave from each whole degree explains (Bartlett), from the (M, M) covariance."""
        a = self.steering
        return np.einsum("am,mn,an->a", a.conj(), spatial, a).real / (a.shape[1] * np.trace(spatial).real)
