"""The gyro bias as it drifts: re-estimated on every span in which the gyro holds still.

A gyro's bias moves after power-up as it warms (a consumer MEMS part by 0.1-0.5 deg/s over
minutes), which the still start cannot see: 0.3 deg/s left unestimated turns the heading by 18 deg
a minute. Whenever the robot does not rotate, the gyro reads its bias plus white noise, so each
span of `block` samples is judged on its own:

- **quiet**: every axis's spread is at most `quiet_factor` times the spread measured standing
  still at the start (a base that drives shakes its IMU: a Jackal's gyro spreads 1-20 deg/s while
  it moves, 0.26 deg/s at rest), so a span that moves or changes its rate is never used;
- **within the gate**, axis by axis: its mean is within `GATE_SIGMA` of the bias as predicted
  now (its last estimate carried on at its rate, uncertain by the random walks since), so a steady
  turn (a turn in place at its peak rate is as quiet as a stop) is never taken for a bias.

A span that passes is a measurement of the bias (its mean, with the white noise's variance over
its samples) fused by a Kalman update. A robot that drives straight on a smooth floor passes too,
rightly: it does not rotate either. What it cannot tell apart is an arc slower than the gate:
about 0.02 deg/s while quiet spans come every half second, but up to 0.4 deg/s at a first stop
25 s in, before the rate is pinned down.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GATE_SIGMA = 3.0
"""how far (in stds of the predicted bias and the span's noise) a span's mean may be from the bias"""
RATE_TAU_S = 120.0
"""a warm-up's rate fades (first-order Gauss-Markov with this time constant): carried on at full
speed through minutes without a still span, an estimated rate turns the bias further than it goes"""


@dataclass(frozen=True)
class BiasModel:
    """How the bias may move, and what a quiet span is."""

    walk_rad_s_rts: float
    """the bias's own random walk (1 sigma per root second)"""
    rate_walk_rad_s2_rts: float
    """the random walk of its rate of change"""
    rate_rad_s2: float
    """its rate of change at the start (1 sigma)"""
    quiet_factor: float
    """a quiet span's spread is at most this times the still start's"""
    block: int
    """samples judged at a time"""
    noise_rad_s: float
    """the gyro's white noise per sample (datasheet): the least spread taken for the still start's,
    so that a noise-free or quantized start does not refuse every span"""


@dataclass
class GyroBias:
    """Each axis's bias (rad/s) and its rate of change (rad/s^2), with their 2x2 covariance, updated
    from quiet spans of samples.

    A warm-up is smooth: the bias moves steadily in one direction for minutes. So the bias carries
    its rate, and a span is gated against the bias carried on at that rate: a robot that stops
    every 25 s sees its bias move on between stops by as much as the gate, and a random walk alone
    lost it there for good. The rate fades with RATE_TAU_S, as a warm-up's does.
    """

    bias: np.ndarray
    rate: np.ndarray
    covariance: np.ndarray
    """(3, 2, 2): each axis's covariance of [bias, rate] at `stamp_ns`"""
    still_std: np.ndarray
    """(3,) each axis's spread per sample standing still at the start (rad/s)"""
    stamp_ns: int
    model: BiasModel
    spans: int = 0
    """spans that moved the bias"""
    samples: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def from_still_start(cls, gyro: np.ndarray, stamp_ns: int, model: BiasModel) -> GyroBias:
        """The bias and its spread from the still start's samples (N, 3); its rate zero, within `model.rate_rad_s2`."""
        std = np.maximum(gyro.std(axis=0), model.noise_rad_s)
        covariance = np.zeros((3, 2, 2))
        covariance[:, 0, 0] = std**2 / len(gyro)
        covariance[:, 1, 1] = model.rate_rad_s2**2
        return cls(gyro.mean(axis=0), np.zeros(3), covariance, std, stamp_ns, model)

    def carried(self, dt_s: np.ndarray | float) -> np.ndarray:
        """How far the rate moves the bias in `dt_s` from the last update (per unit rate), as it fades."""
        return RATE_TAU_S * -np.expm1(-np.maximum(dt_s, 0.0) / RATE_TAU_S)

    def at(self, stamps_ns: np.ndarray) -> np.ndarray:
        """(N, 3) the bias at each stamp: the last estimate carried on at its fading rate."""
        return self.bias + np.outer(self.carried((stamps_ns - self.stamp_ns) / 1e9), self.rate)

    def predicted(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bias (3,), rate (3,) and covariance (3, 2, 2) carried from the last update to `stamp_ns`."""
        dt = max(stamp_ns - self.stamp_ns, 0) / 1e9
        fade = float(np.exp(-dt / RATE_TAU_S))
        step = np.array([[1.0, float(self.carried(dt))], [0.0, fade]])
        m = self.model
        noise = m.rate_walk_rad_s2_rts**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        noise[0, 0] += m.walk_rad_s_rts**2 * dt
        return self.bias + step[0, 1] * self.rate, fade * self.rate, step @ self.covariance @ step.T + noise

    def bias_variance(self, stamp_ns: int) -> np.ndarray:
        """(3,) each axis's bias variance at `stamp_ns`."""
        return self.predicted(stamp_ns)[2][:, 0, 0]

    def add(self, stamp_ns: int, gyro: np.ndarray) -> bool:
        """Take one sample; at the end of each span judge it. Whether the bias moved."""
        self.samples.append(gyro)
        if len(self.samples) < self.model.block:
            return False
        span = np.array(self.samples)
        self.samples = []
        return self.update(span, stamp_ns)

    def update(self, span: np.ndarray, stamp_ns: int) -> bool:
        """Fuse a span's mean (N, 3 samples ending at `stamp_ns`) on each axis within its gate, if the
        span is quiet on every axis (a span that rotates about any axis is not a still robot)."""
        spread = span.std(axis=0)
        if np.any(spread > self.model.quiet_factor * self.still_std):
            return False
        bias, rate, covariance = self.predicted(stamp_ns)
        innovation = span.mean(axis=0) - bias
        total = covariance[:, 0, 0] + np.maximum(spread, self.still_std) ** 2 / len(span)
        fused = np.abs(innovation) <= GATE_SIGMA * np.sqrt(total)
        gain = np.divide(covariance[:, :, 0], total[:, None], out=np.zeros((3, 2)), where=total[:, None] > 0)
        gain[~fused] = 0.0
        self.bias = bias + gain[:, 0] * innovation
        self.rate = rate + gain[:, 1] * innovation
        self.covariance = covariance - gain[:, :, None] * covariance[:, None, 0, :]
        self.stamp_ns = stamp_ns
        self.spans += bool(fused.any())
        return bool(fused.any())
