"""`ros_outputs`: Rover's estimate as the tools of a ROS 2 robot take it, in the `map` frame.

- `tf`: `map -> odom`, so that the robot's own odometry tree (`odom -> base_link`) stays intact: the
  SLAM's pose at its stamp composed with the inverse of the robot's odometry at that stamp (the
  latest odometry at or before it, at most `odom_max_age_s` older; the event-time merge delivers it
  first). With `odom_frame` empty (a robot without odometry), `map -> base_link` itself.
- `tf_static`: the antennas (`antenna_0`, ...) and the IMU frame on `base_link`, from the rig.
- `pose`: the pose with its covariance (robot_localization, nav2, AMCL's form: x, y, yaw).
- `markers`: per tag a sphere, a label and its `ellipse_sigma` covariance ellipse (RViz2, Foxglove);
  a tag not localized yet is grey, with no ellipse.
- `path`: the SLAM's path.

Pure conversion, no transport: wire the outputs to `ros2_publish` (pipelines/ros2.yaml).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from rover.formats.rig import Rig, rig_from_message
from rover.geometry import ellipses, quaternion_from_matrix, quaternion_from_yaw, rpy_matrix, yaw_from_quaternion
from rover.messages import make, stamp_ns
from rover.operator import Emit, In, Operator, Out
from rover.pipeline.params import Checked, Matches, PositiveFloat

FrameName = Annotated[str, Matches(r"[A-Za-z_][A-Za-z0-9_/]*", "a ROS frame id like map or base_link")]
OptionalFrame = Annotated[str, Matches(r"([A-Za-z_][A-Za-z0-9_/]*)?", "a ROS frame id like odom, or empty")]
ELLIPSE_POINTS = 48
"""points of a tag's ellipse (a closed line strip: the first point again at the end)"""
SPHERE_M = 0.15
LABEL_M = 0.25
"""the labels' text height, and how far above its tag"""
LINE_M = 0.02
LOCALIZED = (0.12, 0.47, 0.71, 1.0)
"""RGBA of a localized tag (matplotlib's default blue, as in trajectory.png)"""
NOT_LOCALIZED = (0.6, 0.6, 0.6, 0.8)
STALE_ODOMETRY = "poses without the robot's odometry within odom_max_age_s before them (no map -> odom)"


@dataclass(frozen=True)
class RosOutputsParams(Checked):
    map_frame: FrameName = "map"
    odom_frame: OptionalFrame = "odom"
    """the robot's odometry frame, which its `odom` input is in; empty: the robot has none, and /tf
    gives map -> base_link"""
    base_frame: FrameName = "base_link"
    ellipse_sigma: PositiveFloat = 2.0
    """the tags' ellipses are this many standard deviations (2: 86% of a 2-D Gaussian's mass)"""
    odom_max_age_s: PositiveFloat = 0.5
    """an odometry older than this at the pose's stamp gives no map -> odom (counted)"""


class RosOutputs(Operator):
    """Turns the SLAM's pose, tags and path into /tf, /tf_static, a pose with covariance, markers and a path."""

    inputs = {
        "pose": In("geometry_msgs/msg/PoseWithCovarianceStamped", doc="slam/pose_covariance"),
        "tags": In("rover_msgs/msg/TagArray", required=False, doc="slam/tags"),
        "path": In("nav_msgs/msg/Path", required=False, doc="slam/path"),
        "odom": In("nav_msgs/msg/Odometry", required=False, doc="the robot's own odometry: odom -> base_link"),
        "setup": In("rover_msgs/msg/RigSetup", required=False, doc="the rig: the antennas' and IMU's frames"),
    }
    outputs = {
        "tf": Out("tf2_msgs/msg/TFMessage", doc="map -> odom (map -> base_link without odometry)"),
        "tf_static": Out("tf2_msgs/msg/TFMessage", doc="base_link -> antenna_k and the IMU's frame, once"),
        "pose": Out("geometry_msgs/msg/PoseWithCovarianceStamped", doc="the robot in the map frame"),
        "markers": Out("visualization_msgs/msg/MarkerArray", doc="the tags: spheres, labels, covariance ellipses"),
        "path": Out("nav_msgs/msg/Path", doc="the SLAM's path in the map frame"),
    }
    Params = RosOutputsParams

    def __init__(self, params: RosOutputsParams | None = None):
        super().__init__(params)
        self.odom: tuple[int, float, float, float] | None = None
        """(stamp, x, y, yaw) of the latest odometry"""

    def on_input(self, port: str, msg: Any, stamp: int):
        if port == "odom":
            p = msg.pose.pose
            self.odom = (stamp_ns(msg) or stamp, p.position.x, p.position.y, yaw_of(p.orientation))
        elif port == "pose":
            yield from self._pose(msg, stamp)
        elif port == "tags":
            yield Emit("markers", self._markers(msg), stamp)
        elif port == "path":
            poses = [
                make("geometry_msgs/msg/PoseStamped", header=self._in_map(p.header), pose=p.pose) for p in msg.poses
            ]
            yield Emit("path", make("nav_msgs/msg/Path", header=self._in_map(msg.header), poses=poses), stamp)
        elif port == "setup":
            yield Emit("tf_static", self._static(rig_from_message(msg), stamp_ns(msg) or stamp), stamp)

    def _in_map(self, header: Any) -> Any:
        return make("std_msgs/msg/Header", stamp=header.stamp, frame_id=self.params.map_frame)

    def _pose(self, msg: Any, stamp: int):
        p = self.params
        pose = make("geometry_msgs/msg/PoseWithCovarianceStamped", header=self._in_map(msg.header), pose=msg.pose)
        yield Emit("pose", pose, stamp)
        at = stamp_ns(msg) or stamp
        q = msg.pose.pose.orientation
        x, y, yaw = msg.pose.pose.position.x, msg.pose.pose.position.y, yaw_of(q)
        if not p.odom_frame:
            yield Emit("tf", self._tf(msg.header.stamp, p.map_frame, p.base_frame, x, y, yaw), stamp)
            return
        if self.odom is None or at - self.odom[0] > p.odom_max_age_s * 1e9:
            self.drop(STALE_ODOMETRY)
            return
        _s, ox, oy, oyaw = self.odom
        # map -> odom = (map -> base) * (odom -> base)^-1
        yaw_mo = yaw - oyaw
        c, s = math.cos(yaw_mo), math.sin(yaw_mo)
        tx, ty = x - (c * ox - s * oy), y - (s * ox + c * oy)
        yield Emit("tf", self._tf(msg.header.stamp, p.map_frame, p.odom_frame, tx, ty, yaw_mo), stamp)

    @staticmethod
    def _tf(stamp: Any, parent: str, child: str, x: float, y: float, yaw: float) -> Any:
        qx, qy, qz, qw = (float(v) for v in quaternion_from_yaw(yaw))
        transform = transform_stamped(stamp, parent, child, (x, y, 0.0), (qx, qy, qz, qw))
        return make("tf2_msgs/msg/TFMessage", transforms=[transform])

    def _static(self, rig: Rig, at_ns: int) -> Any:
        stamp = make("builtin_interfaces/msg/Time", sec=at_ns // 10**9, nanosec=at_ns % 10**9)
        base = self.params.base_frame
        antennas = [
            transform_stamped(stamp, base, f"antenna_{k}", (float(a[0]), float(a[1]), 0.0), (0.0, 0.0, 0.0, 1.0))
            for k, a in enumerate(rig.antenna_positions_m)
        ]
        roll, pitch, yaw = (math.radians(v) for v in rig.imu.rotation_rpy_deg)
        imu_q = quaternion_from_matrix(rpy_matrix(roll, pitch, yaw))
        imu = transform_stamped(stamp, base, rig.imu.frame_id, tuple(map(float, rig.imu.position_m)), imu_q)
        return make("tf2_msgs/msg/TFMessage", transforms=[*antennas, imu])

    def _markers(self, msg: Any) -> Any:
        header = self._in_map(msg.header)
        tags = list(msg.tags)
        markers = []
        if tags:
            centers = np.array([[t.position.x, t.position.y] for t in tags])
            covariances = np.array([np.asarray(t.covariance_xy, float).reshape(2, 2) for t in tags])
            finite = np.isfinite(covariances).all(axis=(1, 2))
            loops = ellipses(centers, np.where(finite[:, None, None], covariances, 0.0), self.params.ellipse_sigma,
                             ELLIPSE_POINTS)  # fmt: skip
        for i, tag in enumerate(tags):
            color = LOCALIZED if tag.observable else NOT_LOCALIZED
            at = (tag.position.x, tag.position.y, 0.0)
            markers.append(marker(header, "tags", tag.id, 2, at, (SPHERE_M,) * 3, color))  # SPHERE
            label = marker(header, "labels", tag.id, 9, (at[0], at[1], LABEL_M), (0.0, 0.0, LABEL_M), color)
            label.text = f"tag {tag.id}"  # TEXT_VIEW_FACING
            markers.append(label)
            ellipse = marker(header, "ellipses", tag.id, 4, (0.0, 0.0, 0.0), (LINE_M, 0.0, 0.0), color)  # LINE_STRIP
            if tag.observable and finite[i]:
                loop = np.vstack([loops[i], loops[i][:1]])
                ellipse.points = [make("geometry_msgs/msg/Point", x=float(px), y=float(py)) for px, py in loop]
            else:
                ellipse.action = 2  # DELETE: no ellipse while the tag is not localized
            markers.append(ellipse)
        return make("visualization_msgs/msg/MarkerArray", markers=markers)


def yaw_of(q: Any) -> float:
    return float(yaw_from_quaternion(q.x, q.y, q.z, q.w))


def transform_stamped(stamp: Any, parent: str, child: str, xyz: tuple[float, ...], q: tuple[float, ...]) -> Any:
    t = make("geometry_msgs/msg/TransformStamped")
    t.header = make("std_msgs/msg/Header", stamp=stamp, frame_id=parent)
    t.child_frame_id = child
    t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = xyz
    t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w = q
    return t


def marker(header: Any, ns: str, tag_id: int, kind: int, at: tuple[float, ...], scale: tuple[float, ...],
           rgba: tuple[float, ...]) -> Any:  # fmt: skip
    m = make("visualization_msgs/msg/Marker", header=header, ns=ns, id=int(tag_id), type=kind, action=0)
    m.pose.position.x, m.pose.position.y, m.pose.position.z = at
    m.scale.x, m.scale.y, m.scale.z = scale
    m.color.r, m.color.g, m.color.b, m.color.a = rgba
    return m
