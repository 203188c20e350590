"""The Intel 5300's chain phase jumps as the AoA sees them (rover.operators.aoa.jumps), and the
physics that makes them a problem for geometry rather than for a single burst.

The plane-wave helpers here are written from the array model (steering exp(+j 2 pi f p.u / c), a
chain's phase offset multiplies its antenna's response), not taken from the code under test; the
tag-search and sliding-window tests use them to make physically right ghost candidates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rover.operators.aoa.jumps import combination_multiples, jump_levels, jump_phases

C_M_S = 299_792_458.0
F_161_HZ = 5.805e9
"""channel 161: 5000 MHz + 5 MHz x 161"""
D_M = C_M_S / (2 * F_161_HZ)
TRIANGLE = np.array([[0.0, 0.0], [D_M, 0.0], [D_M / 2, -D_M * math.sqrt(3) / 2]])
"""the paper's half-wavelength triangle"""
GRID = np.radians(np.arange(-180.0, 180.0, 0.1))


def steering(angles: np.ndarray, antennas: np.ndarray = TRIANGLE, f_hz: float = F_161_HZ) -> np.ndarray:
    """(n, M) response of the antennas to plane waves arriving from `angles` (rad, robot frame)."""
    u = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    return np.exp(2j * np.pi * f_hz * (u @ antennas.T) / C_M_S)


def plane_wave_fit(response: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For array responses (n, M): the angle of the steering vector that best explains each, and
    the share of its power that steering vector explains (1 for a clean plane wave)."""
    a = steering(GRID)
    explained = np.abs(response @ a.conj().T) ** 2 / (
        np.sum(np.abs(response) ** 2, axis=1)[:, None] * np.sum(np.abs(a) ** 2, axis=1)[None, :]
    )
    best = np.argmax(explained, axis=1)
    return GRID[best], explained[np.arange(len(response)), best]


def five_ghz_multiples(combination, chains: int = 3) -> np.ndarray:
    """The documented numbering at 5 GHz (two levels): chain k >= 1 jumps by pi when bit k-1 is
    set; (..., chains) for an array of combination numbers."""
    combination = np.asarray(combination)[..., None]
    return np.concatenate([np.zeros_like(combination), (combination >> np.arange(chains - 1)) & 1], axis=-1)


def angle_gap_deg(a, b) -> np.ndarray:
    return np.degrees(np.abs((np.asarray(a) - np.asarray(b) + np.pi) % (2 * np.pi) - np.pi))


def noise_for_std(angles: np.ndarray, std_rad: float) -> np.ndarray:
    """Per-antenna complex noise std (E|w|^2) that gives a single snapshot's angle estimate the
    std `std_rad` at `angles`: the Cramer-Rao bound with an unknown complex gain,
    var = sigma^2 / (2 |P_a^perp da/dtheta|^2), da/dtheta = j k (p . u_perp) a."""
    a = steering(angles)
    u_perp = np.stack([-np.sin(angles), np.cos(angles)], axis=-1)
    da = 2j * np.pi * F_161_HZ / C_M_S * (u_perp @ TRIANGLE.T) * a
    along = np.sum(a.conj() * da, axis=1) / np.sum(np.abs(a) ** 2, axis=1)
    perp = da - along[:, None] * a
    return std_rad * np.sqrt(2 * np.sum(np.abs(perp) ** 2, axis=1))


def burst_candidates(true_angle, carried, undone, std_rad: float, rng: np.random.Generator) -> np.ndarray:
    """What the AoA measures: the wave from `true_angle` (n,) through chains carrying jump
    combinations `carried` (n,), plus receiver noise of the level that gives the true angle the
    std `std_rad`; then for each combination in `undone` (n, K) the angle of the plane wave that
    best explains the response with that combination undone (n, K). Every candidate gets the
    noise physics gives it: ghosts are not a noise-free map of a noisy angle."""
    true_angle = np.atleast_1d(np.asarray(true_angle, float))
    carried = np.broadcast_to(carried, true_angle.shape)
    undone = np.asarray(undone).reshape(len(true_angle), -1)
    sigma = noise_for_std(true_angle, std_rad)
    noise = rng.normal(size=(len(true_angle), 3)) + 1j * rng.normal(size=(len(true_angle), 3))
    y = steering(true_angle) * np.exp(1j * np.pi * five_ghz_multiples(carried)) + sigma[:, None] * noise / math.sqrt(2)
    undo = np.exp(-1j * np.pi * five_ghz_multiples(undone))  # (n, K, 3)
    angle, _ = plane_wave_fit((y[:, None, :] * undo).reshape(-1, 3))
    return angle.reshape(undone.shape)


@pytest.mark.parametrize(("channel", "levels", "step"), [(161, 2, math.pi), (6, 4, math.pi / 2)])
@pytest.mark.parametrize("chains", [2, 3, 4])
def test_every_combination_once_identity_first_numbered_as_documented(channel, levels, step, chains):
    phases = jump_phases(channel, chains)
    assert jump_levels(channel) == levels
    assert phases.shape == (levels ** (chains - 1), chains)
    assert np.all(phases[0] == 0.0), "combination 0 is the calibration itself"
    assert np.all(phases[:, 0] == 0.0), "only the phases relative to chain 0 matter"
    multiples = phases / step
    assert np.allclose(multiples, np.round(multiples)) and multiples.min() >= 0 and multiples.max() <= levels - 1
    distinct = {tuple(np.round(np.mod(row, 2 * math.pi), 9)) for row in phases}
    assert len(distinct) == len(phases), "no two combinations add the same phases"
    for number in range(len(phases)):
        m = combination_multiples(number, channel, chains)
        assert np.allclose(phases[number], m * step)
        # the module's numbering: sum over chains k >= 1 of m_k levels^(k-1)
        assert sum(int(m[k]) * levels ** (k - 1) for k in range(1, chains)) == number


def test_the_first_combinations_jump_one_chain_each():
    """Combination 1 jumps chain 1 by one step, the next power of `levels` jumps chain 2."""
    assert np.allclose(jump_phases(161, 3)[1], [0, math.pi, 0])
    assert np.allclose(jump_phases(161, 3)[2], [0, 0, math.pi])
    assert np.allclose(jump_phases(161, 3)[3], [0, math.pi, math.pi])
    assert np.allclose(jump_phases(6, 3)[1], [0, math.pi / 2, 0])
    assert np.allclose(jump_phases(6, 3)[4], [0, 0, math.pi / 2])
    for number in range(4):
        assert np.array_equal(combination_multiples(number, 161, 3), five_ghz_multiples(number))


@pytest.mark.parametrize("channel", [161, 6])
def test_without_jumps_only_the_identity(channel):
    phases = jump_phases(channel, 3, jumps=False)
    assert phases.shape == (1, 3) and np.all(phases == 0.0)


def test_the_helpers_recover_a_clean_plane_wave():
    """The test's own model, checked: no jump, the fit finds the wave's angle with all its power."""
    true = np.radians(np.arange(-180.0, 180.0, 7.0))
    angle, share = plane_wave_fit(steering(true))
    assert angle_gap_deg(angle, true).max() <= 0.1
    assert share.min() > 0.999


def test_the_burst_model_has_the_std_it_is_made_for():
    """Receiver noise at the level from the Cramer-Rao bound gives the unjumped angle a 3 deg std
    (robust spread: at this SNR the triangle's back lobe wins a rare burst, a physical outlier)."""
    rng = np.random.default_rng(0)
    true = rng.uniform(-math.pi, math.pi, 3000)
    for carried in (0, 3):
        undone = np.full((len(true), 1), carried)
        error = angle_gap_deg(burst_candidates(true, carried, undone, math.radians(3.0), rng)[:, 0], true)
        assert 2.7 < 1.4826 * np.median(error) < 3.3, "undoing the carried combination is exact"
        assert np.mean(error > 15.0) < 0.01


def test_a_pi_jump_on_the_triangle_looks_like_another_clean_plane_wave():
    """Why geometry is needed (issue 14): with the half-wavelength triangle at channel 161, a wave
    whose chains 2 and 3 carry 0/pi jumps is explained by a steering vector at another angle
    almost as well as a clean wave: at every true angle the best wrong combination explains at
    least 98% of the power (the issue's figure) at an angle far from the true one. Any single
    combination does so (>= 95%) only for part of the angles; a single burst cannot tell them apart."""
    true = np.radians(np.arange(-180.0, 180.0, 1.0))
    clean = steering(true)
    share_rows, gap_rows = [], []
    for jump in ([0, math.pi, 0], [0, 0, math.pi], [0, math.pi, math.pi]):  # chains 2 and/or 3 by pi
        jumped = clean * np.exp(1j * np.array(jump))[None, :]
        ghost, share = plane_wave_fit(jumped)
        share_rows.append(share)
        gap_rows.append(angle_gap_deg(ghost, true))
    shares, gaps = np.array(share_rows), np.array(gap_rows)
    best = np.argmax(shares, axis=0)
    assert shares.max(axis=0).min() >= 0.98
    assert gaps[best, np.arange(len(true))].min() > 30.0, "the look-alike is at another angle, not the true one"
    fooled = np.mean(shares >= 0.95, axis=1)
    assert np.all((fooled > 0) & (fooled < 1)), "which combination fools depends on the angle"
