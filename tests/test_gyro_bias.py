"""The gyro bias tracked over quiet spans: what it takes, what it refuses, and how it follows a drift."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rover.operators.preintegration.gyro_bias import BiasModel, GyroBias

RATE_HZ = 200
NOISE_RAD_S = math.radians(0.07)
"""white noise per sample: 0.005 deg/s/rtHz at 200 Hz"""
BLOCK = 100
MODEL = BiasModel(
    walk_rad_s_rts=math.radians(0.001),
    rate_walk_rad_s2_rts=math.radians(1e-4),
    rate_rad_s2=math.radians(0.005),
    quiet_factor=2.0,
    block=BLOCK,
    noise_rad_s=NOISE_RAD_S,
)
SPAN_NS = BLOCK * 10**9 // RATE_HZ


def still_start(rng: np.random.Generator, bias: np.ndarray, seconds: float = 3.0) -> GyroBias:
    samples = bias + rng.normal(0, NOISE_RAD_S, (int(seconds * RATE_HZ), 3))
    return GyroBias.from_still_start(samples, 0, MODEL)


def span(rng: np.random.Generator, rate: np.ndarray, shake_rad_s: float = 0.0) -> np.ndarray:
    return rate + rng.normal(0, math.hypot(NOISE_RAD_S, shake_rad_s), (BLOCK, 3))


def test_the_still_start_gives_the_bias_and_the_quiet_reference():
    rng = np.random.default_rng(1)
    bias = np.radians([0.02, -0.01, 0.25])
    tracker = still_start(rng, bias)
    assert np.all(np.abs(tracker.bias - bias) < 4 * NOISE_RAD_S / math.sqrt(600))
    assert np.allclose(tracker.still_std, NOISE_RAD_S, rtol=0.1)


@pytest.mark.parametrize("seed", range(5))
def test_a_quiet_span_moves_the_bias_to_the_posterior(seed):
    """A span of 0.05 deg/s after a minute: the Kalman posterior between the carried bias and the span's mean."""
    rng = np.random.default_rng(seed)
    tracker = still_start(rng, np.zeros(3))
    samples = span(rng, np.radians([0.0, 0.0, 0.05]))
    bias, _, covariance = tracker.predicted(60 * 10**9)
    noise = np.maximum(samples.std(axis=0), tracker.still_std) ** 2 / BLOCK
    expected = bias + covariance[:, 0, 0] / (covariance[:, 0, 0] + noise) * (samples.mean(axis=0) - bias)
    assert tracker.update(samples, 60 * 10**9)
    assert np.allclose(tracker.bias, expected)
    assert tracker.spans == 1
    assert tracker.bias_variance(60 * 10**9)[2] < covariance[2, 0, 0]


def test_a_shaking_span_is_refused_whatever_its_mean():
    rng = np.random.default_rng(3)
    tracker = still_start(rng, np.zeros(3))
    before = tracker.bias.copy()
    assert not tracker.update(span(rng, np.zeros(3), shake_rad_s=math.radians(1.0)), SPAN_NS)
    assert tracker.spans == 0 and np.array_equal(tracker.bias, before)


def test_a_steady_turn_is_quiet_but_refused_by_the_gate():
    rng = np.random.default_rng(4)
    tracker = still_start(rng, np.zeros(3))
    for k, rate_deg_s in enumerate((37.0, 0.5), 1):  # a turn in place at its peak rate, a slow arc
        tracker.update(span(rng, np.radians([0.0, 0.0, rate_deg_s])), k * SPAN_NS)
        assert abs(math.degrees(tracker.bias[2])) < 0.01, "the yaw axis took the turn for its bias"


def test_each_axis_is_gated_on_its_own():
    """A step on the roll axis is refused there and does not hold back the yaw axis."""
    rng = np.random.default_rng(7)
    tracker = still_start(rng, np.zeros(3))
    moved = np.radians([0.3, 0.0, 0.02])
    for k in range(1, 21):
        tracker.update(span(rng, moved), k * SPAN_NS)
    assert abs(tracker.bias[0]) < math.radians(0.01)
    assert abs(tracker.bias[2] - moved[2]) < math.radians(0.01)


def test_a_noise_free_start_does_not_refuse_every_span():
    """Synthetic or quantized data: a still start with no spread takes the datasheet noise as its own."""
    tracker = GyroBias.from_still_start(np.full((600, 3), 0.001), 0, MODEL)
    rng = np.random.default_rng(8)
    assert tracker.update(0.001 + rng.normal(0, NOISE_RAD_S, (BLOCK, 3)), SPAN_NS)


@pytest.mark.parametrize("seed", range(4))
def test_a_warm_up_drift_is_followed_span_by_span(seed):
    """0.3 deg/s over a 300 s time constant, quiet spans every 0.5 s for 20 minutes: within 0.005
    deg/s rms. The gate refuses a good span now and then (3 sigma: 0.3% an axis), never for long."""
    rng = np.random.default_rng(seed)
    tracker = still_start(rng, np.zeros(3))
    drift = np.radians([0.0, 0.0, 0.3])
    errors, spans = [], 2400
    for k in range(1, spans + 1):
        true = drift * (1 - math.exp(-k * SPAN_NS / 1e9 / 300))
        tracker.update(span(rng, true), k * SPAN_NS)
        errors.append(tracker.bias[2] - true[2])
    assert tracker.spans > 0.97 * spans
    assert math.degrees(float(np.sqrt(np.mean(np.square(errors))))) < 0.005


def test_without_still_spans_the_carried_bias_is_no_worse_than_the_held_one():
    """A minute of spans on a 0.5 deg/s warm-up (2-minute time constant), then five minutes without
    one: the bias carried on at its fading rate ends nearer the truth than the last estimate held."""
    rng = np.random.default_rng(9)
    tracker = still_start(rng, np.zeros(3))
    drift = math.radians(0.5)

    def true(t_s: float) -> float:
        return drift * (1 - math.exp(-t_s / 120))

    for k in range(1, 121):
        tracker.update(span(rng, np.array([0.0, 0.0, true(k * 0.5)])), k * SPAN_NS)
    held = tracker.bias[2]
    for t_s in (120.0, 300.0, 360.0):
        carried = tracker.at(np.array([int(t_s * 1e9)]))[0, 2]
        assert abs(carried - true(t_s)) < abs(held - true(t_s))


def test_samples_are_judged_a_span_at_a_time():
    rng = np.random.default_rng(6)
    tracker = still_start(rng, np.zeros(3))
    samples = span(rng, np.radians([0.0, 0.0, 0.005]))
    moved = [tracker.add(10**9 + k, s) for k, s in enumerate(samples)]
    assert moved == [False] * (BLOCK - 1) + [True]
