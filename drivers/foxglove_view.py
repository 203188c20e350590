"""`foxglove_view`: a live view of the SLAM in Foxglove, served by the Foxglove SDK's WebSocket server.

Open Foxglove, "Open connection", `ws://HOST:PORT` (8765 by default; `rover run --view [PORT]` adds
this sink to a pipeline). Topics, all in frame `world`, each message logged at its event time:

- `/tf` (FrameTransforms): `world` -> `base_link` at every pose;
- `/rover/path` (PosesInFrame): the SLAM's best path so far;
- `/rover/tags` (SceneUpdate): per tag, entity `tag-<id>` with its label `tag <id>`, a sphere at
  its position and its `ellipse_sigma`-sigma covariance ellipse (a line loop; none while an axis is
  over 100 m, a tag not localized yet), orange once observable, grey before;
- `/rover/aoa` (SceneUpdate): entity `aoa`, a ray of `ray_m` from the robot along each bearing of the
  latest epoch to leave the SLAM window (green: used; grey: its tag not found yet), drawn from the
  live pose of that epoch;
- `/rover/diagnostics` (JSON): the solver's iterations, window size, tags and active Huber rows.

Only `pose` must be wired. The server never holds the run back: a client too slow for its queue
(1024 messages) loses the oldest. Nothing is written to disk.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Annotated, Any

import foxglove
import numpy as np
from foxglove.channels import FrameTransformsChannel, PosesInFrameChannel, SceneUpdateChannel
from foxglove.messages import (
    Color,
    FrameTransform,
    FrameTransforms,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    PosesInFrame,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from rover.errors import BadInput
from rover.geometry import ellipses, yaw_from_quaternion
from rover.messages import stamp_ns
from rover.operator import COMPLETE, In, Operator, RunOutcome
from rover.pipeline.params import Checked, PositiveFloat, Range

log = logging.getLogger("rover.view")

WORLD_FRAME = "world"
ROBOT_FRAME = "base_link"
ELLIPSE_POINTS = 64
"""points of a covariance ellipse's line loop (a multiple of 4: the axes' ends are among them)"""
ELLIPSE_MAX_AXIS_M = 100.0
"""a tag whose ellipse would be larger is not localized yet: no ellipse"""
TAG_SPHERE_M = 0.15
LABEL_OFFSET_M = 0.3
"""the label floats this far above the tag"""
LINE_PX = 2.0
LABEL_PX = 14.0
MAX_POSES_KEPT = 10_000
"""live poses kept to draw the rays of bearings from (a bearing arrives a window after its pose)"""
ORANGE = Color(r=1.0, g=0.55, b=0.0, a=1.0)
GREY = Color(r=0.6, g=0.6, b=0.6, a=0.8)
GREEN = Color(r=0.2, g=0.8, b=0.3, a=0.9)
DIAGNOSTICS_SCHEMA = {
    "title": "rover.SlamDiagnostics",
    "type": "object",
    "properties": {
        "stamp_s": {"type": "number"},
        "iterations": {"type": "integer"},
        "window_epochs": {"type": "integer"},
        "tags": {"type": "integer"},
        "huber_active_rows": {"type": "integer"},
    },
}


@dataclass(frozen=True)
class FoxgloveViewParams(Checked):
    host: str = "127.0.0.1"
    """the address to listen on (0.0.0.0: every interface; the view has no access control)"""
    port: Annotated[int, Range(ge=0, le=65535)] = 8765
    """0: any free port (logged)"""
    name: str = "rover"
    """the server name Foxglove shows"""
    ray_m: PositiveFloat = 10.0
    """length of the AoA rays"""
    ellipse_sigma: PositiveFloat = 1.0
    """the tags' ellipses are this many standard deviations (1: 39% of a 2-D Gaussian's mass, 2: 86%)"""


def timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _points(xy: np.ndarray) -> list[Point3]:
    return [Point3(x=float(x), y=float(y), z=0.0) for x, y in xy]


def _pose(x: float, y: float, z: float = 0.0, q: Any = None) -> Pose:
    orientation = Quaternion(x=q.x, y=q.y, z=q.z, w=q.w) if q is not None else Quaternion(w=1.0)
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=orientation)


class FoxgloveView(Operator):
    """Serves the robot, its path, the tags and the AoA rays to Foxglove over a WebSocket."""

    inputs = {
        "pose": In("geometry_msgs/msg/PoseStamped", doc="the live pose (slam/pose): /tf, and the rays' origins"),
        "path": In("nav_msgs/msg/Path", required=False, doc="slam/path"),
        "tags": In("rover_msgs/msg/TagArray", required=False, doc="slam/tags"),
        "bearings": In("rover_msgs/msg/Aoa", required=False, doc="slam/bearings: the rays"),
        "diagnostics": In("rover_msgs/msg/SlamDiagnostics", required=False, doc="slam/diagnostics"),
    }
    Params = FoxgloveViewParams

    def __init__(self, params: FoxgloveViewParams | None = None):
        super().__init__(params)
        self.foxglove_context = scope = foxglove.Context()  # its own: two views (or tests) never share channels
        self.tf = FrameTransformsChannel("/tf", context=scope)
        self.path = PosesInFrameChannel("/rover/path", context=scope)
        self.tags = SceneUpdateChannel("/rover/tags", context=scope)
        self.aoa = SceneUpdateChannel("/rover/aoa", context=scope)
        self.diagnostics = foxglove.Channel("/rover/diagnostics", schema=DIAGNOSTICS_SCHEMA, context=scope)
        self.server: Any = None
        self.poses: dict[int, tuple[float, float, float]] = {}
        """live pose (x, y, yaw) per header stamp, until the bearings of that epoch have come"""
        self.latest: tuple[float, float, float] | None = None
        self.rays: list[tuple[float, float, float, bool]] = []
        """the latest epoch's rays: origin x, y, world bearing, used"""
        self.rays_epoch: int | None = None

    @property
    def port(self) -> int:
        """The port the server listens on (once started)."""
        return int(self.server.port) if self.server is not None else self.params.port

    def start(self) -> None:
        p = self.params
        try:
            self.server = foxglove.start_server(name=p.name, host=p.host, port=p.port, context=self.foxglove_context)
        except RuntimeError as exc:
            reason = str(exc).removeprefix("FoxgloveError: ")
            raise BadInput(f"foxglove_view: cannot listen on {p.host}:{p.port}: {reason}") from None
        log.info("foxglove_view: listening on ws://%s:%d (Foxglove: Open connection)", p.host, self.port)

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "pose":
            self._pose(msg, stamp_ns)
        elif port == "path":
            self._path(msg, stamp_ns)
        elif port == "tags":
            self._tags(msg, stamp_ns)
        elif port == "bearings":
            self._bearing(msg, stamp_ns)
        else:
            self._diagnostics(msg, stamp_ns)
        return ()

    def _pose(self, msg: Any, stamp: int) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        transform = FrameTransform(
            timestamp=timestamp(stamp_ns(msg)),
            parent_frame_id=msg.header.frame_id or WORLD_FRAME,
            child_frame_id=ROBOT_FRAME,
            translation=Vector3(x=p.x, y=p.y, z=p.z),
            rotation=Quaternion(x=q.x, y=q.y, z=q.z, w=q.w),
        )
        self.tf.log(FrameTransforms(transforms=[transform]), log_time=stamp)
        self.latest = (p.x, p.y, float(yaw_from_quaternion(q.x, q.y, q.z, q.w)))
        self.poses[stamp_ns(msg)] = self.latest
        if len(self.poses) > MAX_POSES_KEPT:
            del self.poses[next(iter(self.poses))]

    def _path(self, msg: Any, stamp: int) -> None:
        poses = [_pose(s.pose.position.x, s.pose.position.y, s.pose.position.z, s.pose.orientation) for s in msg.poses]
        frame = msg.header.frame_id or WORLD_FRAME
        self.path.log(PosesInFrame(timestamp=timestamp(stamp_ns(msg)), frame_id=frame, poses=poses), log_time=stamp)

    def _tags(self, msg: Any, stamp: int) -> None:
        tags = list(msg.tags)
        if not tags:
            return
        when, frame = timestamp(stamp_ns(msg)), msg.header.frame_id or WORLD_FRAME
        centers = np.array([[t.position.x, t.position.y] for t in tags], float)
        covariances = np.array([np.asarray(t.covariance_xy, float).reshape(2, 2) for t in tags])
        finite = np.isfinite(covariances).all(axis=(1, 2))
        covariances[~finite] = 0.0
        offsets = ellipses(np.zeros_like(centers), covariances, self.params.ellipse_sigma, ELLIPSE_POINTS)
        drawn = finite & (np.abs(offsets).max(axis=(1, 2)) <= ELLIPSE_MAX_AXIS_M)
        loops = offsets + centers[:, None, :]
        entities = []
        for i, tag in enumerate(tags):
            if not np.isfinite(centers[i]).all():
                continue
            x, y = float(centers[i, 0]), float(centers[i, 1])
            color = ORANGE if tag.observable else GREY
            lines = [
                LinePrimitive(
                    type=LinePrimitiveLineType.LineLoop,
                    thickness=LINE_PX,
                    scale_invariant=True,
                    points=_points(loops[i]),
                    color=color,
                )
            ]
            entities.append(
                SceneEntity(
                    timestamp=when,
                    frame_id=frame,
                    id=f"tag-{tag.id}",
                    spheres=[
                        SpherePrimitive(
                            pose=_pose(x, y), size=Vector3(x=TAG_SPHERE_M, y=TAG_SPHERE_M, z=TAG_SPHERE_M), color=color
                        )
                    ],
                    lines=lines if drawn[i] else [],
                    texts=[
                        TextPrimitive(
                            pose=_pose(x, y, LABEL_OFFSET_M),
                            billboard=True,
                            font_size=LABEL_PX,
                            scale_invariant=True,
                            color=color,
                            text=f"tag {tag.id}",
                        )
                    ],
                )
            )
        self.tags.log(SceneUpdate(entities=entities), log_time=stamp)

    def _bearing(self, msg: Any, stamp: int) -> None:
        epoch = stamp_ns(msg)
        origin = self.poses.get(epoch, self.latest)
        if origin is None:
            self.drop("bearings before any pose (nothing to draw them from)")
            return
        if not math.isfinite(msg.angle_rad):
            self.drop("bearings with a non-finite angle")
            return
        if epoch != self.rays_epoch:
            self.rays, self.rays_epoch = [], epoch
            self.poses = {s: p for s, p in self.poses.items() if s >= epoch}
        x, y, yaw = origin
        self.rays.append((x, y, yaw + msg.angle_rad, msg.chosen >= 0))
        rays = np.array(self.rays)
        ends = rays[:, :2] + self.params.ray_m * np.stack([np.cos(rays[:, 2]), np.sin(rays[:, 2])], axis=1)
        segments = np.stack([rays[:, :2], ends], axis=1)  # (n, 2 ends, xy)
        used = rays[:, 3].astype(bool)
        lines = [
            LinePrimitive(
                type=LinePrimitiveLineType.LineList,
                thickness=LINE_PX,
                scale_invariant=True,
                points=_points(segments[which].reshape(-1, 2)),
                color=color,
            )
            for which, color in ((used, GREEN), (~used, GREY))
            if which.any()
        ]
        entity = SceneEntity(timestamp=timestamp(epoch), frame_id=WORLD_FRAME, id="aoa", lines=lines)
        self.aoa.log(SceneUpdate(entities=[entity]), log_time=stamp)

    def _diagnostics(self, msg: Any, stamp: int) -> None:
        self.diagnostics.log(
            {
                "stamp_s": stamp_ns(msg) / 1e9,
                "iterations": int(msg.iterations),
                "window_epochs": int(msg.window_epochs),
                "tags": int(msg.tags),
                "huber_active_rows": int(msg.huber_active_rows),
            },
            log_time=stamp,
        )

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Stop the server (clients see the connection close)."""
        if self.server is not None:
            self.server.stop()
            self.server = None
