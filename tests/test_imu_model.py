"""The simulated IMU: the warm-up drift and the shake change only what they model."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from rover.datasets.imu_model import imu_samples
from rover.datasets.motion import Motion
from rover.datasets.scenario import Imu, load_scenario


def samples(spec: Imu, pause_s: float = 0.0):
    scenario = load_scenario("paper", {"trajectory.laps": "1", "trajectory.pause_s": str(pause_s)})
    motion = Motion(scenario.trajectory)
    t = np.arange(0.0, motion.duration_s, 1.0 / spec.rate_hz)
    state = motion.state(t)
    return t, state, imu_samples(state, spec, np.random.default_rng(1), np.random.default_rng([1, 17]))


def test_the_warm_up_drift_adds_to_the_gyro_alone():
    t, _, plain = samples(Imu())
    _, _, warm = samples(replace(Imu(), gyro_bias_drift_deg_s=0.3, gyro_bias_drift_tau_s=300.0))
    assert np.array_equal(plain.accel, warm.accel)
    moved = np.degrees(warm.gyro - plain.gyro)
    assert np.allclose(np.abs(moved), 0.3 * (1 - np.exp(-t / 300.0))[:, None])


def test_the_shake_comes_only_while_the_robot_moves():
    _, state, plain = samples(Imu(), pause_s=2.0)
    _, _, shaken = samples(replace(Imu(), vibration_deg_s=1.0, vibration_mg=50.0), pause_s=2.0)
    still = (np.hypot(state.vel[:, 0], state.vel[:, 1]) < 1e-6) & (np.abs(state.yaw_rate) < 1e-6)
    assert still.sum() >= (3 + 4 * 2) * 200, "3 s at the start and 2 s at each of the lap's 4 waypoints"
    assert np.array_equal(shaken.gyro[still], plain.gyro[still])
    spread = np.degrees((shaken.gyro - plain.gyro)[~still]).std()
    assert math.isclose(spread, 1.0, rel_tol=0.05)
