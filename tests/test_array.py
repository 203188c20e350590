"""The receive array's model: the field of view, linear arrays (mirror image, aliasing) and the geometry
verdict, the same for the aoa operator and for `rover check`."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rover.errors import BadInput
from rover.formats.rig import rig_from_text
from rover.formats.wifi import SPEED_OF_LIGHT_M_S, channel_freq_hz
from rover.messages import make
from rover.operators.aoa.array import (
    AMBIGUOUS_CORRELATION,
    ArrayResponse,
    alias_angles,
    check_geometry,
    check_rig_geometry,
    field_mask,
    mirror_into_field,
    steering,
)
from rover.operators.aoa.operator import Aoa

F64_HZ = channel_freq_hz(64)
LGTM = np.array([[0.0, 0.0], [0.0, -0.1], [0.0, -0.2]])
"""LGTM's laptop: a uniform linear array along -y, 0.10 m apart (1.77 wavelengths at 5.32 GHz)"""
TRIANGLE = np.array([[0.0, 0.0], [0.0258, 0.0], [0.0129, -0.0223]])


def ula(spacing_m: float, axis_deg: float, count: int = 3) -> np.ndarray:
    axis = np.array([math.cos(math.radians(axis_deg)), math.sin(math.radians(axis_deg))])
    return np.arange(count)[:, None] * spacing_m * axis


def degrees_in(mask: np.ndarray) -> set[int]:
    return set(np.flatnonzero(mask).tolist())


def test_the_default_field_is_the_whole_circle_or_the_half_plane_in_front():
    assert field_mask(TRIANGLE).all()
    front = {d % 360 for d in range(-90, 91)}
    assert degrees_in(field_mask(LGTM)) == front
    assert degrees_in(field_mask(ula(0.02, 0.0))) == set(range(0, 181))  # along x: no front, so the left
    assert degrees_in(field_mask(ula(0.02, 60.0))) == {d % 360 for d in range(-120, 61)}  # around -30 deg


def test_a_given_field_runs_counter_clockwise_from_its_first_angle():
    assert degrees_in(field_mask(LGTM, (-30, 30))) == {d % 360 for d in range(-30, 31)}
    assert degrees_in(field_mask(TRIANGLE, (90, -90))) == set(range(90, 271))
    assert degrees_in(field_mask(TRIANGLE, (350, 10))) == {d % 360 for d in range(-10, 11)}
    assert field_mask(LGTM, (0, 360)).all() and field_mask(LGTM, (-180.0, 180.0)).all()
    assert degrees_in(field_mask(TRIANGLE, (10.5, 12.5))) == {11, 12}


def test_angles_outside_the_field_come_back_as_their_mirror_image():
    angles = np.radians([20.0, 160.0, -170.0, 90.0])
    folded = np.degrees(mirror_into_field(angles, LGTM, field_mask(LGTM)))
    np.testing.assert_allclose(folded, [20.0, 20.0, -10.0, 90.0], atol=1e-9)
    np.testing.assert_allclose(mirror_into_field(angles, TRIANGLE, field_mask(TRIANGLE, (-90, 90))), angles)


def test_lgtms_array_aliases_as_its_spacing_says():
    """sin(theta) of the aliases of theta differ from sin(theta) by multiples of wavelength / spacing."""
    period = SPEED_OF_LIGHT_M_S / F64_HZ / 0.1
    theta = math.radians(20.0)
    shifted = math.sin(theta) + period * np.arange(-3, 4)
    expected = np.degrees(np.arcsin(shifted[(np.abs(shifted) <= 1) & (np.arange(-3, 4) != 0)]))
    found = np.degrees(alias_angles(LGTM, F64_HZ, theta, field_mask(LGTM)))
    np.testing.assert_allclose(found, np.sort(expected), atol=0.01)
    reference = steering(LGTM, F64_HZ, np.array(theta))
    alike = np.abs(steering(LGTM, F64_HZ, np.radians(found)) @ reference.conj()) / 3
    assert (alike >= AMBIGUOUS_CORRELATION).all()


def test_over_the_whole_circle_a_linear_array_also_sees_the_mirror_images():
    half_wave = ula(SPEED_OF_LIGHT_M_S / F64_HZ / 2, -90.0)
    assert alias_angles(half_wave, F64_HZ, math.radians(20.0), field_mask(half_wave)).size == 0
    mirror = alias_angles(half_wave, F64_HZ, math.radians(20.0), field_mask(half_wave, (0, 360)))
    np.testing.assert_allclose(np.degrees(mirror), [160.0], atol=0.01)
    assert alias_angles(TRIANGLE, 5.825e9, 0.3, field_mask(TRIANGLE)).size == 0


@pytest.mark.parametrize("axis_deg", [90.0, 0.0, 35.0])
@pytest.mark.parametrize("count", [2, 3])
def test_a_half_wavelength_linear_array_is_accepted_with_its_mirror_ambiguity(axis_deg, count):
    """It used to be refused: the two ends of its axis look alike at exactly half a wavelength, and
    directions near them were counted as an ambiguity."""
    antennas = ula(SPEED_OF_LIGHT_M_S / 5.825e9 / 2, axis_deg, count)
    for freq_hz in (5.18e9, 5.825e9):
        warning = check_geometry(antennas, freq_hz)
        assert warning is not None and "mirror image" in warning and "aliases" not in warning
        assert "field of view" in warning and "reaches across" not in warning


def test_a_wide_linear_array_is_accepted_with_its_aliases_named():
    warning = check_geometry(LGTM, F64_HZ)
    assert warning is not None and check_rig_geometry(rig_from_text(rig_text(LGTM, 64))) == warning
    assert "differ by a multiple of 0.564" in warning
    assert "20 deg is also seen at -51.7, -12.8 and 64.9 deg" in warning
    slightly_wide = ula(SPEED_OF_LIGHT_M_S / F64_HZ / 2, -90.0)
    at_149 = check_geometry(slightly_wide, channel_freq_hz(149)) or ""
    example = at_149.split("; ")[-1]
    assert "aliases" in example and "is also seen at" in example


def test_a_field_reaching_across_a_linear_arrays_axis_is_accepted_with_a_warning():
    assert "reaches across the axis" in (check_geometry(LGTM, F64_HZ, (-100, 100)) or "")
    assert "reaches across" not in (check_geometry(LGTM, F64_HZ, (-90, 90)) or "")
    assert "reaches across" not in (check_geometry(LGTM, F64_HZ, (0, 90)) or "")


def test_an_ambiguous_planar_array_is_still_refused():
    assert check_geometry(TRIANGLE, 5.825e9) is None
    with pytest.raises(BadInput, match="cannot tell"):
        check_geometry(np.array([[0, 0], [0.2, 0], [0.1, -0.17]]), 5.825e9)


def rig_text(antennas: np.ndarray, channel: int) -> str:
    return f"receiver: {{antenna_positions_m: {antennas.tolist()}, channel: {channel}}}\n"


@pytest.mark.parametrize(
    "antennas",
    [ula(SPEED_OF_LIGHT_M_S / 5.825e9 / 2, 90.0), LGTM, TRIANGLE, np.array([[0, 0], [0.2, 0], [0.1, -0.17]])],
)
def test_the_operator_and_the_check_give_one_verdict(antennas):
    text = rig_text(antennas, 165)
    try:
        verdict: str | None = check_rig_geometry(rig_from_text(text))
    except BadInput as exc:
        verdict = str(exc)
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=text)
    if verdict is not None and verdict.startswith("aoa: the antenna array cannot tell"):
        with pytest.raises(BadInput, match="cannot tell"):
            list(Aoa().on_input("setup", setup, 0))
    else:
        assert list(Aoa().on_input("setup", setup, 0)) == []


def test_a_collinear_arrays_mirror_image_is_in_its_main_lobe():
    """A collinear array cannot tell a direction from its mirror image: the mirror's lobe is no
    sidelobe (the operator makes it a candidate, not a rival); a planar array's back lobe stays one."""
    lgtm = ArrayResponse(LGTM, F64_HZ)
    axis_deg = 270  # LGTM's array lies along -y
    for deg in (10, 45, 100, 200):
        assert lgtm.sidelobe[deg, (2 * axis_deg - deg) % 360] == 0.0
    triangle = ArrayResponse(TRIANGLE, 5.825e9)
    assert triangle.sidelobe.max() > 0.8
