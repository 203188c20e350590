"""The receive array's model: steering vectors from the antenna positions, and how alike the array
sees two directions (near-ambiguity, aliases, main lobes), from which the operator checks a rig's
geometry, keeps angles in the rig's field of view (resolving a collinear array's mirror ambiguity)
and weighs a direction's rivals.

Directions are angles in the robot frame, counter-clockwise from forward (x); the antenna
positions are (M, 2) in metres in that frame.
"""

from __future__ import annotations

import math

import numpy as np

from rover.errors import BadInput
from rover.formats.rig import Rig, field_of_view_span_deg
from rover.formats.wifi import SPEED_OF_LIGHT_M_S
from rover.geometry import wrap_angle

AMBIGUOUS_CORRELATION = 0.9999
"""two directions at least this alike to the array cannot be told apart"""
GEOMETRY_GRID_DEG = 0.25
AMBIGUITY_SEPARATION_DEG = 10.0
"""directions closer than this are neighbours, not an ambiguity; for a collinear array, aliases that
only reach directions this close to its axis (neighbours of their own mirror image) are not named"""
ALIAS_GRID_DEG = 0.01
"""the grid alias_angles searches"""
ALIAS_SHIFT_STEP = 1e-4
"""the grid of differences of direction cosines along a collinear array's axis searched for aliasing"""
FIELD_TOLERANCE_DEG = 1e-6
"""a whole degree this close to an end of the field of view is in it"""
EXAMPLE_OFFSET_DEG = 20.0
"""the example of aliasing in a warning is the direction nearest this far from the field's centre that aliases"""


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


def field_mask(antennas_m: np.ndarray, field_of_view_deg: tuple[float, float] | None = None) -> np.ndarray:
    """Whether each whole degree 0..359 (robot frame) lies in the field of view [from, to], the interval
    going counter-clockwise from `from` to `to`, ends included. Without one: the whole circle for a
    planar array; for a collinear one the half plane it can resolve, in front of its axis when it
    can, else on its left (`field_normal`)."""
    start, span = _field(antennas_m, field_of_view_deg)
    offset = (np.arange(360.0) - start + FIELD_TOLERANCE_DEG) % 360.0
    inside: np.ndarray = offset <= span + 2 * FIELD_TOLERANCE_DEG
    return inside


def _field(antennas_m: np.ndarray, field_of_view_deg: tuple[float, float] | None) -> tuple[float, float]:
    """Where the field of view starts and how far it spans counter-clockwise, in degrees."""
    if field_of_view_deg is not None:
        return field_of_view_deg[0], field_of_view_span_deg(field_of_view_deg)
    axis = array_axis(antennas_m)
    if axis is None:
        return 0.0, 360.0
    return _broadside_deg(axis) - 90.0, 180.0


def _broadside_deg(axis: np.ndarray) -> float:
    """The direction a collinear array reports around (`field_normal`), in degrees."""
    normal = field_normal(axis)
    return math.degrees(math.atan2(normal[1], normal[0]))


def mirror_into_field(angles: np.ndarray, antennas_m: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """For a collinear array, which sees a direction and its mirror image across its axis alike: each
    angle (rad) outside the field (a field_mask) whose mirror image is inside it, mirrored; the
    others as they are. A planar array's angles are returned as they are."""
    axis = array_axis(antennas_m)
    angles = np.asarray(angles, dtype=float)
    if axis is None:
        return angles
    mirror = wrap_angle(2 * math.atan2(axis[1], axis[0]) - angles)
    degree = np.rint(np.degrees(angles)).astype(int) % 360
    mirror_degree = np.rint(np.degrees(mirror)).astype(int) % 360
    return np.where(~mask[degree] & mask[mirror_degree], mirror, angles)


def alias_angles(antennas_m: np.ndarray, freq_hz: float, angle_rad: float, field_mask: np.ndarray) -> np.ndarray:
    """The directions (rad, wrapped by wrap_angle, ascending) in the field of view (a field_mask) that the array
    sees as it sees `angle_rad` at `freq_hz`: steering vectors at least AMBIGUOUS_CORRELATION alike,
    a grating lobe or, for a collinear array, the mirror image across its axis; `angle_rad` itself
    is left out. Found as peaks on an ALIAS_GRID_DEG grid, to that precision."""
    grid = np.radians(np.arange(0.0, 360.0, ALIAS_GRID_DEG))
    reference = steering(antennas_m, freq_hz, np.asarray(float(angle_rad)))
    corr = np.abs(steering(antennas_m, freq_hz, grid) @ reference.conj()) / len(antennas_m)
    peak = (corr >= np.roll(corr, 1)) & (corr > np.roll(corr, -1)) & (corr >= AMBIGUOUS_CORRELATION)
    itself = np.abs(wrap_angle(grid - angle_rad)) < np.radians(2 * ALIAS_GRID_DEG)
    inside = field_mask[np.rint(np.degrees(grid)).astype(int) % 360]
    found: np.ndarray = np.sort(wrap_angle(grid[peak & ~itself & inside]))
    return found


def _alias_shifts(antennas_m: np.ndarray, axis: np.ndarray, freq_hz: float) -> np.ndarray:
    """For a collinear array, the differences of direction cosine along its axis (in (0, 2)) at which
    two directions look alike: its phases depend on the cosine only, so these hold for every pair."""
    along = (antennas_m - antennas_m[0]) @ axis
    shift = np.arange(1, round(2 / ALIAS_SHIFT_STEP)) * ALIAS_SHIFT_STEP
    phases = np.exp(2j * np.pi * freq_hz * np.outer(shift, along) / SPEED_OF_LIGHT_M_S)
    corr = np.abs(phases.sum(axis=1)) / len(along)
    peak = (corr[1:-1] >= corr[:-2]) & (corr[1:-1] > corr[2:]) & (corr[1:-1] >= AMBIGUOUS_CORRELATION)
    found: np.ndarray = shift[1:-1][peak]
    return found


def _and(items: list[str]) -> str:
    """Items as English lists them: "a, b and c"."""
    return ", ".join(items[:-1]) + " and " + items[-1] if len(items) > 1 else "".join(items)


def _deg(value: float) -> str:
    """Degrees as a warning shows them: to a tenth, without trailing zeros."""
    return f"{round(value, 1):g}"


def _collinear_warning(
    antennas_m: np.ndarray, axis: np.ndarray, max_freq_hz: float, field_of_view_deg: tuple[float, float] | None
) -> str:
    """What a collinear array resolves: the side of its axis in the field of view, and the aliases of a
    wide spacing (the rule, and the aliases of one direction as an example)."""
    start, span = _field(antennas_m, field_of_view_deg)
    mask = field_mask(antennas_m, field_of_view_deg)
    shown = field_of_view_deg or (start, start + span)
    warning = (
        "aoa: the antennas are collinear: a direction and its mirror image across the array's axis look alike, "
        f"so angles are reported in the field of view [{_deg(shown[0])}, {_deg(shown[1])}] deg"
    )
    axis_deg = math.degrees(math.atan2(axis[1], axis[0]))
    inside = np.flatnonzero(mask)
    mirror = 2 * axis_deg - inside
    distinct = np.abs((mirror - inside + 180.0) % 360.0 - 180.0) > 1.0
    if (mask[np.rint(mirror).astype(int) % 360] & distinct).any():
        warning += (
            ", which reaches across the axis: a direction in it and its mirror image are both candidates (the SLAM "
            "tells them apart by the robot's motion; an NLOS tag's estimate may then be off beyond its covariance: "
            "docs/rig.md#linear-arrays)"
        )
    shifts = _alias_shifts(antennas_m, axis, max_freq_hz)
    off_axis = math.cos(math.radians(AMBIGUITY_SEPARATION_DEG))
    shifts = shifts[shifts < 1 + off_axis]
    if not len(shifts):
        return warning
    broadside = _broadside_deg(axis)
    cosine = np.abs(np.cos(np.radians(inside - axis_deg)))
    example = start + span / 2 + EXAMPLE_OFFSET_DEG
    order = np.argsort(np.abs((inside - example + 180.0) % 360.0 - 180.0), kind="stable")
    for degree, cos_axis in zip(inside[order], cosine[order], strict=True):
        if shifts[0] - 1 <= cos_axis < off_axis:
            aliases = alias_angles(antennas_m, max_freq_hz, math.radians(degree), mask)
            if len(aliases):
                break
    else:
        return warning
    ratios = shifts / shifts[0]
    if len(shifts) == 1:
        rule = f"{shifts[0]:.3g}"
    elif np.allclose(ratios, np.rint(ratios), atol=0.01):
        rule = f"a multiple of {shifts[0]:.3g}"
    else:
        rule = "one of " + _and([f"{x:.3g}" for x in shifts])
    sine = f"sin(angle - {_deg(broadside)} deg)" if abs(broadside) > FIELD_TOLERANCE_DEG else "sin(angle)"
    seen = _and([_deg(a) for a in np.degrees(aliases)])
    return (
        f"{warning}; at {max_freq_hz / 1e6:.0f} MHz the spacing also aliases directions whose {sine} differ by "
        f"{rule}: {_deg(math.degrees(wrap_angle(math.radians(degree))))} deg is also seen at {seen} deg"
    )


def check_rig_geometry(rig: Rig) -> str | None:
    """check_geometry for a rig: at the highest frequency it listens on, in its field of view. The aoa
    operator and `rover check` both call this, so they give the same verdict."""
    return check_geometry(rig.antenna_positions_m, rig.max_freq_hz, rig.field_of_view_deg)


def check_geometry(
    antennas_m: np.ndarray, max_freq_hz: float, field_of_view_deg: tuple[float, float] | None = None
) -> str | None:
    """Refuse a planar array for which two directions 10 degrees apart give the same phase differences.
    Accept a collinear one with a warning: it sees a direction and its mirror image across its axis
    alike (angles are reported in the field of view), and with a spacing over half a wavelength
    directions alias on its side too (the warning names them)."""
    axis = array_axis(antennas_m)
    if axis is not None:
        return _collinear_warning(antennas_m, axis, max_freq_hz, field_of_view_deg)
    angles = np.radians(np.arange(0.0, 360.0, GEOMETRY_GRID_DEG))
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
    return None


class ArrayResponse:
    """The array at one frequency, per whole degree: its steering vectors, and how alike it sees a
    direction j outside direction i's main lobe, sidelobe[i, j] (0 inside it; the main lobe ends
    at the first minimum on each side; a collinear array's takes in the lobe of i's mirror image
    across its axis, which it cannot tell from i: the operator gives the mirror as a candidate)."""

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
        axis = array_axis(antennas_m)
        if axis is not None:  # a collinear array sees a direction's mirror image as the direction itself
            mirror = np.rint(2 * math.degrees(math.atan2(axis[1], axis[0])) - np.arange(360)).astype(int) % 360
            outside &= outside[mirror]
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
        return self.energy_batch(spatial[None])[0]

    def energy_batch(self, spatial: np.ndarray) -> np.ndarray:
        """`energy` of each of a stack of (M, M) covariances: (C, 360)."""
        a = self.steering
        power = np.einsum("am,cmn,an->ca", a.conj(), spatial, a).real
        return power / (a.shape[1] * np.trace(spatial, axis1=1, axis2=2).real[:, None])
