"""The gyro bias as it drifts: re-estimated on every span in which the gyro holds still.

A gyro's bias moves after power-up as it warms (a consumer MEMS part by 0.1-0.5 deg/s over
minutes), which the still start cannot see: 0.3 deg/s left unestimated turns the heading by 18 deg
a minute. Whenever the robot does not rotate, the gyro reads its bias plus white noise, so each
span of `block` samples is judged on its own:

- **quiet**: every axis's spread is at most `quiet_factor` times the spread measured standing
  still at the start (a base that drives shakes its IMU: a Jackal's gyro spreads 1-20 deg/s while
  it moves, 0.26 deg/s at rest), so a span that moves or changes its rate is never used;
- **within the gate**: its mean is within `GATE_SIGMA` of the bias as predicted now (its last
  estimate carried on at its rate, uncertain by the random walks since), so a steady turn (a turn
  in place at its peak rate is as quiet as a stop) is never taken for a bias.

A span that passes is a measurement of the bias (its mean, with the white noise's variance over
its samples) fused by a Kalman update. A robot that
drives straight on a smooth floor passes too, rightly: it does not rotate either. What it cannot
tell apart is an arc slower than the gate (about 0.02 deg/s while quiet spans come every half
second, 1 deg a minute; some 0.05 deg/s after 25 s without one), which is then taken for bias.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

GATE_SIGMA = 3.0
"""how far (in stds of the predicted bias and the span's noise) a span's mean may be from the bias"""


@dataclass
class GyroBias:
    """Each axis's bias (rad/s) and its rate of change (rad/s^2), with their 2x2 covariance, updated
    from quiet spans of samples.

    A warm-up is smooth: the bias moves steadily in one direction for minutes. So the bias carries
    its rate (an integrated random walk, `rate_walk`, beside the bias's own random walk, `walk`),
    and a span is gated against the bias extrapolated at that rate: a robot that stops every 25 s
    sees its bias move on between stops by as much as the gate, and a random walk alone would
    lose it there for good.
    """

    bias: np.ndarray
    rate: np.ndarray
    covariance: np.ndarray
    """(3, 2, 2): each axis's covariance of [bias, rate] at `stamp_ns`"""
    still_std: np.ndarray
    """(3,) each axis's spread per sample standing still at the start (rad/s)"""
    stamp_ns: int
    walk_rad_s_rts: float
    rate_walk_rad_s2_rts: float
    quiet_factor: float
    block: int
    """samples judged at a time"""
    spans: int = 0
    """quiet spans used"""
    samples: list[np.ndarray] = field(default_factory=list)

    @classmethod
    def from_still_start(
        cls,
        gyro: np.ndarray,
        stamp_ns: int,
        walk_rad_s_rts: float,
        rate_walk_rad_s2_rts: float,
        rate_rad_s2: float,
        quiet_factor: float,
        block: int,
    ) -> GyroBias:
        """The bias and its spread from the still start's samples (N, 3); its rate zero, `rate_rad_s2` 1 sigma."""
        std = gyro.std(axis=0)
        covariance = np.zeros((3, 2, 2))
        covariance[:, 0, 0] = std**2 / len(gyro)
        covariance[:, 1, 1] = rate_rad_s2**2
        return cls(
            gyro.mean(axis=0),
            np.zeros(3),
            covariance,
            std,
            stamp_ns,
            walk_rad_s_rts,
            rate_walk_rad_s2_rts,
            quiet_factor,
            block,
        )

    def predicted(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bias (3,), rate (3,) and covariance (3, 2, 2) carried from the last update to `stamp_ns`."""
        dt = max(stamp_ns - self.stamp_ns, 0) / 1e9
        step = np.array([[1.0, dt], [0.0, 1.0]])
        noise = self.rate_walk_rad_s2_rts**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        noise[0, 0] += self.walk_rad_s_rts**2 * dt
        return self.bias + self.rate * dt, self.rate, step @ self.covariance @ step.T + noise

    def bias_std(self, stamp_ns: int) -> np.ndarray:
        """(3,) each axis's bias std at `stamp_ns`."""
        return np.sqrt(self.predicted(stamp_ns)[2][:, 0, 0])

    def add(self, stamp_ns: int, gyro: np.ndarray) -> bool:
        """Take one sample; at the end of each span judge it. Whether the bias moved."""
        self.samples.append(gyro)
        if len(self.samples) < self.block:
            return False
        span = np.array(self.samples)
        self.samples = []
        return self.update(span, stamp_ns)

    def update(self, span: np.ndarray, stamp_ns: int) -> bool:
        """Fuse a span's mean (N, 3 samples ending at `stamp_ns`) if it is quiet and within the gate."""
        if np.any(span.std(axis=0) > self.quiet_factor * self.still_std):
            return False
        bias, rate, covariance = self.predicted(stamp_ns)
        innovation = span.mean(axis=0) - bias
        total = covariance[:, 0, 0] + self.still_std**2 / len(span)
        if np.any(np.abs(innovation) > GATE_SIGMA * np.sqrt(total)):
            return False
        gain = np.divide(covariance[:, :, 0], total[:, None], out=np.zeros((3, 2)), where=total[:, None] > 0)
        self.bias = bias + gain[:, 0] * innovation
        self.rate = rate + gain[:, 1] * innovation
        self.covariance = covariance - gain[:, :, None] * covariance[:, None, 0, :]
        self.stamp_ns = stamp_ns
        self.spans += 1
        return True
