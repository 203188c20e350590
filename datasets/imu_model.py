"""IMU and wheel-odometry measurements of a planar robot, with the noise of real sensors.

The IMU reports specific force in the body frame, gravity included (+9.81 on z when level),
and angular velocity, each with white noise (noise density times the square root of the rate),
a constant bias drawn once, and a bias random walk; optionally a warm-up drift of the gyro bias
after power-up and the shake of a base that drives (drawn from a stream of their own, so that
turning them on changes nothing else).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rover.datasets.motion import State
from rover.datasets.scenario import Imu, Odometry

GRAVITY_M_S2 = 9.80665
MG_M_S2 = 1e-3 * GRAVITY_M_S2
UG_M_S2 = 1e-6 * GRAVITY_M_S2


@dataclass(frozen=True)
class ImuSamples:
    accel: np.ndarray  # (N, 3) m/s^2, body frame
    gyro: np.ndarray  # (N, 3) rad/s, body frame
    gyro_bias: np.ndarray
    accel_bias: np.ndarray


def imu_samples(state: State, spec: Imu, rng: np.random.Generator, extra: np.random.Generator) -> ImuSamples:
    """The IMU's samples along `state`: the noise and biases from `rng`, the drift and shake from `extra`."""
    n = len(state.yaw)
    dt = 1.0 / spec.rate_hz
    cos, sin = np.cos(state.yaw), np.sin(state.yaw)
    true_accel = np.stack(
        [
            cos * state.acc[:, 0] + sin * state.acc[:, 1],
            -sin * state.acc[:, 0] + cos * state.acc[:, 1],
            np.full(n, GRAVITY_M_S2),
        ],
        axis=1,
    )
    true_gyro = np.stack([np.zeros(n), np.zeros(n), state.yaw_rate], axis=1)
    gyro_bias = rng.normal(0, math.radians(spec.gyro_bias_deg_s), 3) + np.cumsum(
        rng.normal(0, math.radians(spec.gyro_bias_walk_deg_s_rts) * math.sqrt(dt), (n, 3)), axis=0
    )
    accel_bias = rng.normal(0, spec.accel_bias_mg * MG_M_S2, 3) + np.cumsum(
        rng.normal(0, spec.accel_bias_walk_mg_rts * MG_M_S2 * math.sqrt(dt), (n, 3)), axis=0
    )
    gyro_white = math.radians(spec.gyro_noise_deg_s_rthz) * math.sqrt(spec.rate_hz)
    accel_white = spec.accel_noise_ug_rthz * UG_M_S2 * math.sqrt(spec.rate_hz)
    if spec.gyro_bias_drift_deg_s > 0:
        t_s = np.arange(n) * dt
        signs = extra.choice([-1.0, 1.0], 3)
        warm = 1.0 - np.exp(-t_s / spec.gyro_bias_drift_tau_s)
        gyro_bias = gyro_bias + np.outer(warm, signs * math.radians(spec.gyro_bias_drift_deg_s))
    gyro = true_gyro + gyro_bias + rng.normal(0, gyro_white, (n, 3))
    accel = true_accel + accel_bias + rng.normal(0, accel_white, (n, 3))
    if spec.vibration_deg_s > 0 or spec.vibration_mg > 0:
        moving = ((np.hypot(state.vel[:, 0], state.vel[:, 1]) > 1e-6) | (np.abs(state.yaw_rate) > 1e-6))[:, None]
        gyro = gyro + moving * extra.normal(0, math.radians(spec.vibration_deg_s), (n, 3))
        accel = accel + moving * extra.normal(0, spec.vibration_mg * MG_M_S2, (n, 3))
    return ImuSamples(accel, gyro, gyro_bias, accel_bias)


@dataclass(frozen=True)
class OdometrySamples:
    xy: np.ndarray  # (N, 2) in the odometry frame (the robot's start pose)
    yaw: np.ndarray
    speed: np.ndarray
    yaw_rate: np.ndarray


def odometry_samples(state: State, t: np.ndarray, spec: Odometry, rng: np.random.Generator) -> OdometrySamples:
    """Wheel odometry: forward speed with a scale error and noise, yaw rate with a drift, integrated."""
    scale = 1.0 + rng.normal(0, spec.scale_error)
    drift = math.radians(rng.normal(0, spec.heading_drift_deg_s))
    cos, sin = np.cos(state.yaw), np.sin(state.yaw)
    forward = cos * state.vel[:, 0] + sin * state.vel[:, 1]
    moving = np.abs(forward) > 1e-6
    speed = scale * forward + moving * rng.normal(0, spec.speed_noise_m_s, len(t))
    turning = np.abs(state.yaw_rate) > 1e-6
    yaw_rate = state.yaw_rate + drift * (moving | turning)
    dt = np.diff(t, prepend=t[0])
    yaw = np.cumsum(yaw_rate * dt)
    xy = np.cumsum(np.stack([speed * np.cos(yaw) * dt, speed * np.sin(yaw) * dt], axis=1), axis=0)
    return OdometrySamples(xy, yaw, speed, yaw_rate)
