"""Datasets written on the fly, and reading one back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from rover.formats.bag import BagReader, BagWriter, iter_messages
from rover.messages import deserialize, header, make

T0_NS = 1_700_000_000_000_000_000

LAP = ("paper", 2, "trajectory.laps=1")
"""one lap of the paper's scenario, seed 2: the dataset of conftest's `lap_runs`"""


def write_imu_dataset(path: Path, n_imu: int, *, imu_hz: float = 200.0, odom_every: int = 10, seed: int = 7) -> Path:
    """A dataset with `n_imu` IMU samples and odometry every `odom_every` samples, from a seeded RNG."""
    rng = np.random.default_rng(seed)
    gyro_z = rng.normal(0.0, 0.3, n_imu)
    with BagWriter(path) as bag:
        for i in range(n_imu):
            stamp = T0_NS + int(i * 1e9 / imu_hz)
            imu = make(
                "sensor_msgs/msg/Imu",
                header=header(stamp, "imu_link"),
                angular_velocity=make("geometry_msgs/msg/Vector3", z=float(gyro_z[i])),
                linear_acceleration=make("geometry_msgs/msg/Vector3", z=9.81),
            )
            bag.write("/imu/data", imu, stamp)
            if odom_every and i % odom_every == 0:
                odom = make("nav_msgs/msg/Odometry", header=header(stamp, "odom"))
                odom.pose.pose.position.x = math.sin(i / 100.0)
                bag.write("/odom", odom, stamp)
    return path


def read_bag(path: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log time, payload) of every message of an MCAP file, in file order."""
    return [(m.topic, m.log_time_ns, m.data) for m in iter_messages(path, log_time_order=False)]


def strip_truth(source: Path, target: Path) -> None:
    """The same dataset without /groundtruth/* and without the truth metadata."""
    with BagReader(source) as reader:
        meta = {k: v for k, v in reader.metadata().items() if k not in ("rover.truth", "rover.simulation")}
        with BagWriter(target, metadata=meta) as bag:
            for message in reader.messages(log_time_order=True):
                if not message.topic.startswith("/groundtruth/"):
                    bag.write(message.topic, deserialize(message.data, message.schema), message.log_time_ns)
