"""`preintegration`: IMU motion between epochs against the simulator's ground truth, and its start-up logic."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest
from conftest import T0_NS, read_bag

from rover.datasets.scenario import load_scenario
from rover.datasets.simulate import simulate
from rover.geometry import wrap_angle, yaw_from_quaternion
from rover.messages import deserialize, header, make
from rover.operators.preintegration.operator import Preintegration, rpy_matrix

EPOCH_NS = 400_000_000


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    path = tmp_path_factory.mktemp("pre") / "sim.mcap"
    simulate(load_scenario("paper", {"trajectory.laps": "1"}), 21, path)
    imu, poses = [], {}
    for topic, stamp, data in read_bag(path):
        if topic == "/imu/data":
            imu.append((stamp, deserialize(data, "sensor_msgs/msg/Imu")))
        elif topic == "/groundtruth/pose":
            p = deserialize(data, "geometry_msgs/msg/PoseStamped").pose
            poses[stamp] = (p.position.x, p.position.y, float(yaw_of(p.orientation)))
    return imu, poses


def feed(op: Preintegration, imu, epoch_ns: int = EPOCH_NS, mount: np.ndarray | None = None):
    """IMU samples and an epoch every `epoch_ns`, in stamp order. Not rover.testing.run_operator: these epochs
    fall on IMU stamps, and there the runtime (ties by port name) delivers the epoch first, after which the
    operator drops the IMU sample of the same stamp as a duplicate; here the sample goes first."""
    out, next_epoch = [], imu[0][0] + epoch_ns
    for stamp, msg in imu:
        while stamp > next_epoch:
            out += list(op.on_input("epochs", make("rover_msgs/msg/Aoa", header=header(next_epoch)), next_epoch))
            next_epoch += epoch_ns
        if mount is not None:
            w = mount.T @ [msg.angular_velocity.x, msg.angular_velocity.y, msg.angular_velocity.z]
            a = mount.T @ [msg.linear_acceleration.x, msg.linear_acceleration.y, msg.linear_acceleration.z]
            msg = make(
                "sensor_msgs/msg/Imu",
                header=msg.header,
                angular_velocity=make("geometry_msgs/msg/Vector3", x=w[0], y=w[1], z=w[2]),
                linear_acceleration=make("geometry_msgs/msg/Vector3", x=a[0], y=a[1], z=a[2]),
            )
        out += list(op.on_input("imu", msg, stamp))
    return [e.msg for e in out] + [e.msg for e in op.on_end()]


def yaw_of(q) -> float:
    return float(yaw_from_quaternion(q.x, q.y, q.z, q.w))


def check_against_truth(out, poses):
    stamps = np.array(sorted(poses))
    truth = np.array([poses[s] for s in stamps])

    def at(t: int) -> np.ndarray:
        return truth[min(int(np.searchsorted(stamps, t)), len(stamps) - 1)]

    errors, yaw_errors = [], []
    for o in out:
        start = o.start.sec * 10**9 + o.start.nanosec
        end = o.header.stamp.sec * 10**9 + o.header.stamp.nanosec
        a, b, a2 = at(start), at(end), at(start + 10_000_000)
        velocity = (a2[:2] - a[:2]) / 0.01
        predicted = a[:2] + velocity * o.dt + [o.delta_position.x, o.delta_position.y]
        errors.append(np.linalg.norm(predicted - b[:2]))
        yaw_errors.append(abs(wrap_angle(yaw_of(o.orientation) - b[2])))
    return np.array(errors), np.array(yaw_errors)


def test_increments_match_the_ground_truth(run, caplog):
    imu, poses = run
    with caplog.at_level(logging.INFO):
        out = feed(Preintegration(), imu)
    assert "gyro bias" in caplog.text and "standing still" in caplog.text
    assert len(out) > 200
    errors, yaw_errors = check_against_truth(out, poses)
    assert np.median(errors) < 0.01 and errors.max() < 0.03
    assert math.degrees(yaw_errors.max()) < 2.0
    cov = np.array(out[50].covariance).reshape(9, 9)
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > -1e-15)
    assert 1e-4 < math.sqrt(cov[6, 6]) < 0.02


def test_the_mounting_rotation_from_the_setup(run):
    imu, poses = run
    mount = rpy_matrix(0.0, 0.0, math.radians(90))
    op = Preintegration()
    setup = (
        "receiver: {antenna_positions_m: [[0, 0], [0.02, 0]]}\nexcitation: {channel: 165}\ntags: []\n"
        "imu: {rotation_rpy_deg: [0, 0, 90]}\n"
    )
    list(op.on_input("setup", make("rover_msgs/msg/RigSetup", setup_yaml=setup), 0))
    errors, yaw_errors = check_against_truth(feed(op, imu, mount=mount), poses)
    assert np.median(errors) < 0.01 and math.degrees(yaw_errors.max()) < 2.0


def test_no_stationary_start_warns_and_falls_back(run, caplog):
    imu, _ = run
    moving = [s for s in imu if s[0] > T0_NS + 27_500_000_000]  # in the first corner turn
    with caplog.at_level(logging.WARNING):
        out = feed(Preintegration(), moving)
    assert "does not start with 1.0 s standing still" in caplog.text
    assert len(out) > 100


def test_duplicates_out_of_order_and_gaps_are_counted(run, caplog):
    imu, _ = run
    stream = list(imu[:2000])
    stream.insert(500, stream[499])
    stream.insert(900, stream[850])
    del stream[1200:1300]
    op = Preintegration()
    with caplog.at_level(logging.WARNING):
        out = feed(op, stream)
    assert op.drops == {"duplicate IMU samples": 1, "IMU samples out of order": 1}
    assert "gap(s) in the IMU stream" in caplog.text
    assert len(out) > 10
