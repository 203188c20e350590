"""`ros_outputs` as function calls: map -> odom composes back to the SLAM's pose, the rig's frames,
the tags' markers (each ellipse point at exactly `ellipse_sigma` of its tag's covariance), frames."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rover.drivers.ros_outputs import STALE_ODOMETRY, RosOutputs, RosOutputsParams, yaw_of
from rover.frozen import freeze
from rover.geometry import quaternion_from_yaw
from rover.messages import header, make

T_NS = 1_700_000_010_000_000_000
RIG = """receiver:
  antenna_positions_m: [[0.1, 0.0], [0.1, 0.026], [0.1, -0.026]]
imu: {frame_id: imu_link, rotation_rpy_deg: [0, 0, 90], position_m: [0.05, 0.0, 0.1]}
tags: [{id: 1, channel: 149}]
excitation: {channel: 165}
"""


def pose_msg(x: float, y: float, yaw: float, stamp: int = T_NS) -> object:
    msg = make("geometry_msgs/msg/PoseWithCovarianceStamped", header=header(stamp, "world"))
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    q = msg.pose.pose.orientation
    q.x, q.y, q.z, q.w = (float(v) for v in quaternion_from_yaw(yaw))
    msg.pose.covariance = np.diag([0.01, 0.02, 0, 0, 0, 0.003]).ravel()
    return msg


def odom_msg(x: float, y: float, yaw: float, stamp: int) -> object:
    msg = make("nav_msgs/msg/Odometry", header=header(stamp, "odom"), child_frame_id="base_link")
    msg.pose.pose.position.x, msg.pose.pose.position.y = x, y
    q = msg.pose.pose.orientation
    q.x, q.y, q.z, q.w = (float(v) for v in quaternion_from_yaw(yaw))
    return msg


def compose(a: tuple[float, float, float], b: tuple[float, float, float]) -> tuple[float, float, float]:
    """a * b for planar poses (x, y, yaw)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]


def planar(transform) -> tuple[float, float, float]:
    t = transform.transform
    return t.translation.x, t.translation.y, yaw_of(t.rotation)


def test_map_to_odom_composed_with_the_odometry_is_the_slams_pose():
    op = RosOutputs()
    assert list(op.on_input("odom", odom_msg(1.0, 0.5, 0.3, T_NS - 20_000_000), T_NS - 20_000_000)) == []
    out = list(op.on_input("pose", pose_msg(2.0, 1.0, math.pi / 2), T_NS))
    by_port = {e.port: e.msg for e in out}
    assert set(by_port) == {"pose", "tf"}
    (tf,) = by_port["tf"].transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "odom")
    x, y, yaw = compose(planar(tf), (1.0, 0.5, 0.3))
    assert (x, y, math.remainder(yaw - math.pi / 2, 2 * math.pi)) == pytest.approx((2.0, 1.0, 0.0), abs=1e-12)
    pose = by_port["pose"]
    assert pose.header.frame_id == "map" and pose.pose.covariance[35] == pytest.approx(0.003)


def test_stale_odometry_gives_no_transform_and_is_counted():
    op = RosOutputs(RosOutputsParams(odom_max_age_s=0.1))
    list(op.on_input("odom", odom_msg(0, 0, 0, T_NS - 200_000_000), T_NS - 200_000_000))
    assert [e.port for e in op.on_input("pose", pose_msg(1, 1, 0), T_NS)] == ["pose"]
    assert op.drops == {STALE_ODOMETRY: 1}


def test_before_the_first_odometry_there_is_no_transform():
    """A pose before any odometry: no map -> odom yet (counted), and never map -> base_link, which
    would give base_link a second parent beside the robot's odom."""
    op = RosOutputs()
    assert [e.port for e in op.on_input("pose", pose_msg(1, 1, 0), T_NS)] == ["pose"]
    assert op.drops == {STALE_ODOMETRY: 1}


def test_a_robot_without_odometry_gets_map_to_base_link():
    op = RosOutputs(RosOutputsParams(odom_frame=""))
    (tf,) = next(e.msg for e in op.on_input("pose", pose_msg(2.0, -1.0, 0.5), T_NS) if e.port == "tf").transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
    assert planar(tf) == pytest.approx((2.0, -1.0, 0.5), abs=1e-12)


def test_the_rigs_frames_go_on_tf_static_once():
    op = RosOutputs()
    setup = make("rover_msgs/msg/RigSetup", header=header(T_NS, "base_link"), setup_yaml=RIG)
    (emit,) = op.on_input("setup", setup, T_NS)
    assert emit.port == "tf_static"
    frames = {t.child_frame_id: t for t in emit.msg.transforms}
    assert sorted(frames) == ["antenna_0", "antenna_1", "antenna_2", "imu_link"]
    assert all(t.header.frame_id == "base_link" for t in frames.values())
    a1 = frames["antenna_1"].transform.translation
    assert (a1.x, a1.y, a1.z) == pytest.approx((0.1, 0.026, 0.0))
    imu = frames["imu_link"].transform
    assert (imu.translation.x, imu.translation.z) == pytest.approx((0.05, 0.1))
    assert yaw_of(imu.rotation) == pytest.approx(math.pi / 2)


def tag(tag_id: int, x: float, y: float, cov: list[float], observable: bool) -> object:
    t = make("rover_msgs/msg/Tag", id=tag_id, channel=149, observable=observable, covariance_xy=np.array(cov))
    t.position.x, t.position.y = x, y
    return t


def test_each_tags_ellipse_lies_at_ellipse_sigma_of_its_covariance():
    """The localized tag: a sphere, a label and a closed ellipse whose every point is at Mahalanobis
    distance `ellipse_sigma` from the tag; the one not yet localized is grey and has its ellipse
    deleted."""
    cov = [0.04, 0.015, 0.015, 0.01]
    tags = make("rover_msgs/msg/TagArray", header=header(T_NS, "world"), tags=[
        tag(1, 3.0, 2.0, cov, True), tag(2, -1.0, 0.5, [1e4, 0, 0, 1e4], False)])  # fmt: skip
    (emit,) = RosOutputs(RosOutputsParams(ellipse_sigma=2.0)).on_input("tags", tags, T_NS)
    markers = {(m.ns, m.id): m for m in emit.msg.markers}
    assert sorted(markers) == sorted((ns, i) for ns in ("tags", "labels", "ellipses") for i in (1, 2))
    assert all(m.header.frame_id == "map" for m in markers.values())
    assert markers["labels", 1].text == "tag 1" and markers["tags", 1].type == 2
    loop = np.array([[p.x, p.y] for p in markers["ellipses", 1].points])
    assert np.allclose(loop[0], loop[-1]) and len(loop) > 10
    d = loop - [3.0, 2.0]
    mahalanobis = np.einsum("ni,ij,nj->n", d, np.linalg.inv(np.reshape(cov, (2, 2))), d)
    np.testing.assert_allclose(mahalanobis, 4.0, rtol=1e-9)
    assert markers["ellipses", 2].action == 2 and not markers["ellipses", 2].points
    assert markers["tags", 2].color.r == markers["tags", 2].color.g  # grey


def test_the_path_is_in_the_map_frame():
    path = make("nav_msgs/msg/Path", header=header(T_NS, "world"))
    path.poses = [make("geometry_msgs/msg/PoseStamped", header=header(T_NS - k, "world")) for k in range(3)]
    (emit,) = RosOutputs().on_input("path", freeze(path), T_NS)  # read-only, as the runtime delivers it
    assert emit.msg.header.frame_id == "map" and {p.header.frame_id for p in emit.msg.poses} == {"map"}
    assert [p.header.stamp for p in emit.msg.poses] == [p.header.stamp for p in path.poses]
