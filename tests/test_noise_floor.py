"""NoiseFloor: the IMU's white noise measured on its own samples, whatever the robot's motion."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from helpers import reference_data

from rover.operators.preintegration.noise_floor import MIN_SAMPLES, NoiseFloor

RATE_HZ = 200.0
DT_S = 1 / RATE_HZ


def driving(seconds: float, gyro_std: float, accel_std: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A robot weaving at up to 0.8 rad/s and accelerating at up to 0.5 m/s^2, its samples with
    white noise of the given per-sample stds."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * RATE_HZ)) * DT_S
    gyro = np.zeros((len(t), 3))
    gyro[:, 2] = 0.8 * np.sin(2 * math.pi * 0.3 * t)
    accel = np.zeros((len(t), 3))
    accel[:, 0] = 0.5 * np.sin(2 * math.pi * 0.5 * t)
    accel[:, 1] = 0.3 * np.cos(2 * math.pi * 0.2 * t)
    accel[:, 2] = 9.80665
    return gyro + rng.normal(0, gyro_std, gyro.shape), accel + rng.normal(0, accel_std, accel.shape)


@pytest.mark.parametrize(("gyro_std", "accel_std"), [(math.radians(1.0), 0.49), (math.radians(0.07), 0.0014)])
def test_the_noise_is_measured_through_the_motion(gyro_std, accel_std):
    """A datasheet's noise (0.005 deg/s/rtHz: 0.07 deg/s a sample) and a shaking base's (1 deg/s,
    50 mg), under a weaving, accelerating motion: each within 10% from 2 s of samples."""
    floor = NoiseFloor.for_rate(np.eye(3), DT_S)
    gyro, accel = driving(4.0, gyro_std, accel_std)
    floor.add(gyro, accel)
    measured = floor.stds()
    assert measured is not None
    np.testing.assert_allclose(measured, [gyro_std, accel_std], rtol=0.1)


def test_samples_added_in_pieces_measure_as_added_at_once():
    gyro, accel = driving(3.0, 0.02, 0.1, seed=1)
    whole, pieces = NoiseFloor.for_rate(np.eye(3), DT_S), NoiseFloor.for_rate(np.eye(3), DT_S)
    whole.add(gyro, accel)
    for at in np.array_split(np.arange(len(gyro)), 37):
        pieces.add(gyro[at], accel[at])
    at_once, in_pieces = whole.stds(), pieces.stds()
    assert at_once is not None and in_pieces is not None
    np.testing.assert_array_equal(at_once, in_pieces)


def test_the_densities_are_the_larger_of_told_and_measured():
    floor = NoiseFloor.for_rate(np.eye(3), DT_S)
    assert floor.densities(1e-4, 1e-3, DT_S) == (1e-4, 1e-3), "before any sample: as told"
    gyro, accel = driving(1.0, math.radians(1.0), 1e-5)
    floor.add(gyro[: MIN_SAMPLES - 1], accel[: MIN_SAMPLES - 1])
    assert floor.densities(1e-4, 1e-3, DT_S) == (1e-4, 1e-3), "too few samples to speak"
    floor.add(gyro, accel)
    gyro_rthz, accel_rthz = floor.densities(1e-4, 1e-3, DT_S)
    assert gyro_rthz == pytest.approx(math.radians(1.0) * math.sqrt(DT_S), rel=0.15)
    assert accel_rthz == 1e-3, "a quiet accelerometer keeps the density told"


def test_a_bump_does_not_move_the_measure():
    gyro, accel = driving(2.0, 0.01, 0.05, seed=2)
    quiet, bumped = NoiseFloor.for_rate(np.eye(3), DT_S), NoiseFloor.for_rate(np.eye(3), DT_S)
    quiet.add(gyro, accel)
    gyro[200, 2] += 2.0  # a kerb
    accel[200, 0] += 20.0
    bumped.add(gyro, accel)
    before, after = quiet.stds(), bumped.stds()
    assert before is not None and after is not None
    np.testing.assert_allclose(after, before, rtol=0.05)


def test_only_the_latest_samples_count():
    """The robot stops: its shake is gone from the measure within the window (2 s)."""
    floor = NoiseFloor.for_rate(np.eye(3), DT_S)
    floor.add(*driving(3.0, 0.05, 0.5, seed=3))
    floor.add(*driving(2.5, 0.001, 0.002, seed=4))
    assert floor.stds() == pytest.approx([0.001, 0.002], rel=0.15)


def test_a_real_jackal_imu_is_far_noisier_than_a_datasheet():
    """The real ROS 1 bag of a Jackal driving (50 Hz, 61 s), its samples taken 10 at a time as
    epochs would: while it drives its gyro's vertical axis and its accelerometer read ten times and
    more the densities the preintegration assumes by default, and never less."""
    from rosbags.rosbag1 import Reader
    from rosbags.typesys import Stores, get_typestore

    from rover.operators.preintegration.operator import PreintegrationParams

    store = get_typestore(Stores.ROS1_NOETIC)
    gyro, accel = [], []
    with Reader(reference_data() / "bags" / "jackal_imu_odom.bag") as bag:
        for c, _t, raw in bag.messages(connections=[c for c in bag.connections if c.topic == "/imu/data"]):
            msg: Any = store.deserialize_ros1(raw, c.msgtype)
            gyro.append([msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z])
            accel.append([msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z])
    assert len(gyro) == 3061
    dt_s = 1 / 50
    floor = NoiseFloor.for_rate(np.eye(3), dt_s)
    told = PreintegrationParams()
    used = []
    for at in range(0, len(gyro), 10):
        floor.add(np.array(gyro[at : at + 10]), np.array(accel[at : at + 10]))
        used.append(floor.densities(told.gyro_noise_rad_s_rthz, told.accel_noise_m_s2_rthz, dt_s))
    gyro_rthz, accel_rthz = np.array(used).T
    assert gyro_rthz.min() >= told.gyro_noise_rad_s_rthz and accel_rthz.min() >= told.accel_noise_m_s2_rthz
    assert gyro_rthz.max() > 10 * told.gyro_noise_rad_s_rthz
    assert accel_rthz.max() > 10 * told.accel_noise_m_s2_rthz
