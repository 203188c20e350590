"""The IMU's white noise as its own samples show it, so that the odometry's covariance is never
tighter than the IMU it integrates.

The densities a user gives are a datasheet's, measured on a bench. On a robot that drives, the
motors and the floor shake the IMU: the real Jackal bag of the reference data (50 Hz, 61 s) reads
0.05-0.24 deg/s/rtHz on its gyro's vertical axis and 0.01-0.08 m/s^2/rtHz on its accelerometer,
10 to 80 times a MicroStrain 3DM-GX4-45's datasheet (the project's defaults). Integrated with the
datasheet's densities, that odometry's covariance would claim a hundred times and more too little.

So the noise is measured over the latest samples, from their second differences: the robot's own
motion hardly changes its slope from one sample to the next (a constant angular or linear
acceleration leaves no second difference), while white noise of std s per sample leaves one of
variance 6 s^2. The mean of their squares over WINDOW_S, the largest tenth left out (a bump),
gives s, and s * sqrt(dt) the density (a median, tried first, is the noisier estimate: a shaking
IMU's yaw variance came out 24% high with it, within a fifth with this). The covariance uses the
larger of that and the density told: a shake that is real motion (integrated as it is) only makes
it cautious, never overconfident.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

WINDOW_S = 2.0
"""trailing span of samples the noise is measured over"""
KEPT_SHARE = 0.9
"""the smallest squared second differences averaged: a bump's few are left out"""
KEPT_MEAN_CHI2_1 = 0.560710 / KEPT_SHARE
"""the mean of a chi-squared variable with one degree of freedom below its 90th percentile
(2.7055): P(chi2_3 < 2.7055) / 0.9, since x f_1(x) = f_3(x)"""
SECOND_DIFFERENCE_VARIANCE = 6.0
"""variance of e[k+1] - 2 e[k] + e[k-1] over that of white noise e"""
MIN_SAMPLES = 20
"""second differences needed before the measure speaks (the densities told until then)"""


@dataclass
class NoiseFloor:
    """Per-sample white noise of the gyro about the vertical and of the horizontal specific force,
    measured over the latest samples (the IMU's body frame levelled by `level`)."""

    level: np.ndarray
    window: int
    """second differences kept (WINDOW_S of samples)"""
    _tail: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """the last two samples' [yaw rate, horizontal specific force x, y]"""
    _d2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """the latest squared second differences: yaw rate, force x, force y"""
    worst: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """the largest per-sample std `densities` measured: gyro (rad/s), accelerometer (m/s^2)"""

    @classmethod
    def for_rate(cls, level: np.ndarray, dt_s: float) -> NoiseFloor:
        return cls(level, max(MIN_SAMPLES, round(WINDOW_S / dt_s)))

    def add(self, gyro: np.ndarray, accel: np.ndarray) -> None:
        """Consecutive samples (n, 3) of the gyro (rad/s) and accelerometer (m/s^2), body frame."""
        up = self.level[2]
        rows = np.column_stack([gyro @ up, (accel @ self.level.T)[:, 0:2]])
        joined = np.concatenate([self._tail, rows])
        if len(joined) >= 3:
            d2 = joined[2:] - 2 * joined[1:-1] + joined[:-2]
            self._d2 = np.concatenate([self._d2, d2**2])[-self.window :]
        self._tail = joined[-2:]

    def stds(self) -> np.ndarray | None:
        """Per-sample white-noise std now: [gyro about the vertical (rad/s), the worse horizontal
        axis of the accelerometer (m/s^2)]; None before MIN_SAMPLES."""
        if len(self._d2) < MIN_SAMPLES:
            return None
        kept = np.sort(self._d2, axis=0)[: max(1, int(KEPT_SHARE * len(self._d2)))]
        variance = kept.mean(axis=0) / (KEPT_MEAN_CHI2_1 * SECOND_DIFFERENCE_VARIANCE)
        return np.sqrt([variance[0], max(variance[1], variance[2])])

    def densities(self, gyro_told: float, accel_told: float, dt_s: float) -> tuple[float, float]:
        """The noise densities to propagate with (per root hertz): the larger of those told and
        those measured now."""
        now = self.stds()
        if now is None:
            return gyro_told, accel_told
        self.worst = np.maximum(self.worst, now)
        root = math.sqrt(dt_s)
        return max(gyro_told, float(now[0]) * root), max(accel_told, float(now[1]) * root)
