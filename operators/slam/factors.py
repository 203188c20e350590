"""The window's measurement models, one per sensor, each as the rows or information it adds:

- odometry (the preintegrated IMU): `Edge`, from one epoch to the next, and `bias_jacobian`, how it
  moves with the accelerometer bias states;
- bearing (an AoA): `angle_residuals` under the Huber loss (`huber_cost`, `huber_weight`); the
  cheirality hinge is a row of the convex program (`window_program`), `GN_HINGE_WEIGHT` in the
  Gauss-Newton steps;
- wheel odometry and the velocity constraints (no sideways motion, zero velocity when turning in
  place): `velocity_terms`, and `wheel_rows` when the wheel scale is a state;
- the accelerometer biases' prior at the start: `bias_prior`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from rover.geometry import rotation_2d, wrap_angle
from rover.operators.slam.settings import WindowSettings
from rover.operators.slam.window_program import edge_matrix

GN_HINGE_WEIGHT = 1e-6
"""the Gauss-Newton steps need no cheirality (the angle residual has it); a tiny weight keeps h unique"""


def bias_jacobian(yaw_start: float, yaw_end: float, dt: float) -> np.ndarray:
    """How an edge's [dv, dp] (x/y) move with [body-frame bias, world-frame bias] (4x4) for a robot
    turning steadily from `yaw_start` to `yaw_end` in `dt` (Simpson's rule over the turn: for
    odometry that does not say it itself)."""
    r0, rm, r1 = rotation_2d(yaw_start), rotation_2d(0.5 * (yaw_start + yaw_end)), rotation_2d(yaw_end)
    body = np.concatenate([dt / 6 * (r0 + 4 * rm + r1), dt**2 / 6 * (r0 + 2 * rm)])
    world = np.concatenate([dt * np.eye(2), 0.5 * dt**2 * np.eye(2)])
    return np.concatenate([body, world], axis=1)


@dataclass
class Edge:
    """Odometry from one epoch to the next: [dv, dp] in x/y and their covariance."""

    dt: float
    delta: np.ndarray
    covariance: np.ndarray
    bias_jacobian: np.ndarray = field(default_factory=lambda: np.zeros((4, 0)))
    """(4, biases) how [dv, dp] move with the window's bias states (measured = true + J b)"""
    chol: np.ndarray = field(init=False, repr=False)
    """the covariance's Cholesky factor (the program's odometry rows are whitened by it)"""
    block: np.ndarray = field(init=False, repr=False)
    """M'WM over [p_k, v_k, p_k+1, v_k+1, biases], M = [L J]: the edge's information, for covariances"""

    def __post_init__(self) -> None:
        self.chol = np.linalg.cholesky(self.covariance)
        lmat = np.concatenate([edge_matrix(np.array([self.dt]))[0], self.bias_jacobian], axis=1)
        self.block = lmat.T @ np.linalg.solve(self.covariance, lmat)

    def with_bias_columns(self, extra: int) -> Edge:
        """The same edge over `extra` more bias states that do not move it (zero Jacobian columns,
        zero rows and columns of `block`), without factorizing its covariance again."""
        out = copy.copy(self)
        out.bias_jacobian = np.pad(self.bias_jacobian, ((0, 0), (0, extra)))
        out.block = np.pad(self.block, ((0, extra), (0, extra)))
        return out


def huber_cost(r: np.ndarray, m: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= m, a**2, 2 * m * a - m**2)


def huber_weight(r: np.ndarray, m: float) -> np.ndarray:
    """The IRLS weight of the Huber loss: 1 inside the threshold, m/|r| beyond."""
    return np.minimum(1.0, m / np.maximum(np.abs(r), 1e-12))


def angle_residuals(
    delta: np.ndarray, bearing: np.ndarray, std: np.ndarray, min_range_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Bearing residuals in std units for robot-to-tag vectors `delta`, and their gradients with
    respect to the tag position (the robot's gradient is the opposite)."""
    range2 = np.maximum(np.sum(delta**2, axis=1), min_range_m**2)
    predicted = np.arctan2(delta[:, 1], delta[:, 0])
    measured = np.arctan2(bearing[:, 1], bearing[:, 0])
    residual = wrap_angle(predicted - measured) / std
    return residual, np.stack([-delta[:, 1], delta[:, 0]], axis=1) / (range2 * std)[:, None]


def velocity_terms(
    s: WindowSettings, scale: bool, yaw: float, speed_m_s: float | None, turning_in_place: bool
) -> tuple[np.ndarray, np.ndarray]:
    """An epoch's (W, w) over its velocity (and the wheel scale s, with `scale`) that need no
    linearization: no sideways motion, zero velocity when turning in place, and, without the scale
    as a state, the wheel speed z (its scale error as noise). With the scale a state, the reading is
    `wheel_rows`'s."""
    width = 2 + scale
    info, linear = np.zeros((width, width)), np.zeros(width)
    forward, side = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
    if s.nonholonomic:
        info[:2, :2] += np.outer(side, side) / s.lateral_std_m_s**2
    if turning_in_place and s.turns_in_place:
        info[:2, :2] += np.eye(2) / s.zero_velocity_std_m_s**2
    if speed_m_s is not None and not scale:
        var = s.wheel_speed_std_m_s**2 + (s.wheel_scale_std * speed_m_s) ** 2
        info[:2, :2] += np.outer(forward, forward) / var
        linear[:2] += forward * speed_m_s / var
    return info, linear


def wheel_rows(
    yaw: np.ndarray, speed_m_s: np.ndarray, velocity: np.ndarray, scale: float, std_m_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each epoch's wheel reading z = u (1 + s) + noise, with u = f'v its forward speed and s the
    wheel scale, linearized at the velocities `velocity` (epochs, 2) and the window's scale s0 =
    `scale`: the row ((1 + s0) f'v + u0 s - z - u0 s0) / std, with u0 = f'v there; returned as
    (W, w) per epoch over [v, s] (zero where the epoch has no reading, `speed_m_s` NaN).

    The reading's noise is on z, so z must not be the coefficient of the scale: written as
    f'v = z (1 - s), as it was, the noisy reading multiplies the state it measures, and least
    squares then reads the noise as scale (errors in variables). On `long_hall` with a perfect
    IMU the scale came out 0.6% short of the truth from the wheels' 5 mm/s noise alone (exact
    with noise-free wheels). Linearized at the estimate, re-linearized at every update, the
    coefficient is the IMU-smoothed speed and the fixed point is the model's maximum likelihood."""
    forward = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)
    u0 = np.einsum("ij,ij->i", forward, velocity)
    read = np.isfinite(speed_m_s)
    row = np.where(read[:, None], np.concatenate([(1 + scale) * forward, u0[:, None]], axis=1), 0.0) / std_m_s
    target = np.where(read, speed_m_s + u0 * scale, 0.0) / std_m_s
    return row[:, :, None] * row[:, None, :], row * target[:, None]


def bias_prior(s: WindowSettings, yaw: float, levelled_std_m_s2: float) -> np.ndarray:
    """Information on [body bias, world bias] at the start: each within `accel_bias_std_m_s2`, or,
    when the IMU was levelled on a still start at heading `yaw`, the body bias so and the two
    cancelling there (what levelling removed is exactly what the IMU felt at rest: c + R b = 0)."""
    if levelled_std_m_s2 <= 0:
        return np.eye(4) / s.accel_bias_std_m_s2**2
    both = np.concatenate([rotation_2d(yaw), np.eye(2)], axis=1)  # c + R b
    info = both.T @ both / levelled_std_m_s2**2
    info[0:2, 0:2] += np.eye(2) / s.accel_bias_std_m_s2**2
    return info
