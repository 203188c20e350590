"""`foxglove_view` and `rover run --view`: a real WebSocket client speaking the Foxglove protocol
receives the advertised channels and decodes the messages (protobuf from the advertised schemas);
the view node is wired by type, and changes neither the digest nor the access rules."""

from __future__ import annotations

import base64
import json
import math
import queue
import re
import signal
import socket
import struct
import threading
import time
from typing import Any

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory  # type: ignore[import-untyped]
from helpers import ROOT, T0_NS, popen_rover, wait_until
from websockets.sync.client import ClientConnection, connect
from websockets.typing import Subprotocol

from rover.cli.app import parser
from rover.cli.registry import BUILTINS
from rover.cli.view import add_view, load_with_view
from rover.drivers.foxglove_view import FoxgloveView, FoxgloveViewParams
from rover.errors import BadInput, SpecError
from rover.geometry import quaternion_from_yaw
from rover.messages import header, make
from rover.operator import Emit, Out, Source, Watermark
from rover.pipeline.spec import parse, read_document
from rover.pipeline.validation import check
from rover.pipeline.yamlpos import load
from rover.security.acl import access_control, flows

SUBPROTOCOLS = [Subprotocol("foxglove.sdk.v1"), Subprotocol("foxglove.websocket.v1")]
"""the SDK's server speaks the ws-protocol v1 messages under `foxglove.sdk.v1`; older servers used the other name"""
MESSAGE_DATA = 0x01
TIMEOUT_S = 10.0
ROOT_PIPELINE = str(ROOT / "pipeline.yaml")


class FoxgloveClient:
    """A Foxglove WebSocket client: the advertised channels by topic, subscribes to all, and
    decodes message data (protobuf with the advertised FileDescriptorSet, or JSON)."""

    def __init__(self, port: int):
        self.port = port
        self.ws: ClientConnection
        self.server_info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.by_subscription: dict[int, dict[str, Any]] = {}

    def advertised(self, count: int) -> dict[str, dict[str, Any]]:
        """Read JSON messages until `count` channels are advertised."""
        deadline = time.monotonic() + TIMEOUT_S
        while len(self.channels) < count:
            frame = self.ws.recv(timeout=max(0.0, deadline - time.monotonic()))
            assert isinstance(frame, str), "message data before any channel was advertised"
            msg = json.loads(frame)
            if msg["op"] == "serverInfo":
                self.server_info = msg
            elif msg["op"] == "advertise":
                self.channels.update({c["topic"]: c for c in msg["channels"]})
        return self.channels

    def subscribe_all(self) -> None:
        subscriptions = [{"id": i, "channelId": c["id"]} for i, c in enumerate(self.channels.values(), start=1)]
        self.by_subscription = {s["id"]: c for s, c in zip(subscriptions, self.channels.values(), strict=True)}
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subscriptions}))

    def message(self, topic: str) -> tuple[int, Any]:
        """The next message on `topic`: its log time and the decoded message."""
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            frame = self.ws.recv(timeout=max(0.0, deadline - time.monotonic()))
            if isinstance(frame, str) or frame[0] != MESSAGE_DATA:
                continue
            subscription, log_time = struct.unpack_from("<IQ", frame, 1)
            channel = self.by_subscription[subscription]
            if channel["topic"] == topic:
                return log_time, decode(channel, frame[13:])

    def __enter__(self) -> FoxgloveClient:
        self.ws = connect(f"ws://127.0.0.1:{self.port}", subprotocols=SUBPROTOCOLS, open_timeout=TIMEOUT_S)
        self.ws.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.ws.__exit__(None, None, None)


def decode(channel: dict[str, Any], payload: bytes) -> Any:
    if channel["encoding"] == "json":
        return json.loads(payload)
    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString(payload)


@pytest.fixture
def served():
    """A started view on a free port and a client subscribed to all its channels."""
    view = FoxgloveView(FoxgloveViewParams(port=0, ray_m=10.0))
    view.start()
    with FoxgloveClient(view.port) as client:
        client.advertised(5)
        client.subscribe_all()
        channels = (view.tf, view.path, view.tags, view.aoa, view.diagnostics)
        wait_until(
            lambda: all(c.has_sinks() for c in channels),
            "the subscriptions to reach the server",
            timeout_s=TIMEOUT_S,
            poll_s=0.001,
        )
        yield view, client
    view.close()


def pose(stamp: int, x: float, y: float, yaw: float) -> Any:
    _, _, qz, qw = (float(v) for v in quaternion_from_yaw(yaw))
    return make(
        "geometry_msgs/msg/PoseStamped",
        header=header(stamp, "world"),
        pose=make(
            "geometry_msgs/msg/Pose",
            position=make("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
            orientation=make("geometry_msgs/msg/Quaternion", z=qz, w=qw),
        ),
    )


def tag(tag_id: int, x: float, y: float, cov: np.ndarray, observable: bool = True) -> Any:
    return make(
        "rover_msgs/msg/Tag",
        id=tag_id,
        channel=6,
        position=make("geometry_msgs/msg/Point", x=x, y=y, z=0.0),
        covariance_xy=np.asarray(cov, np.float64).ravel(),
        observable=observable,
    )


def xy(points) -> np.ndarray:
    return np.array([[p.x, p.y] for p in points])


def test_the_client_sees_the_channels_with_their_schemas(served):
    view, client = served
    schemas = {topic: (c["schemaName"], c["encoding"]) for topic, c in client.channels.items()}
    assert schemas == {
        "/tf": ("foxglove.FrameTransforms", "protobuf"),
        "/rover/path": ("foxglove.PosesInFrame", "protobuf"),
        "/rover/tags": ("foxglove.SceneUpdate", "protobuf"),
        "/rover/aoa": ("foxglove.SceneUpdate", "protobuf"),
        "/rover/diagnostics": ("rover.SlamDiagnostics", "json"),
    }
    assert client.server_info["name"] == "rover"


def test_a_tag_decodes_to_its_label_and_its_covariance_ellipse(served):
    view, client = served
    turn = math.radians(30)
    rotation = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    cov = rotation @ np.diag([0.25, 0.04]) @ rotation.T  # std 0.5 m along 30 deg, 0.2 m across
    unknown = np.eye(2) * 1e12  # as slam sends a tag it has not localized
    tags = make(
        "rover_msgs/msg/TagArray",
        header=header(T0_NS + 5, "world"),
        tags=[tag(7, 3.0, -2.0, cov), tag(9, 1.0, 1.0, unknown, observable=False)],
    )
    view.on_input("tags", tags, T0_NS + 5)
    log_time, update = client.message("/rover/tags")
    assert log_time == T0_NS + 5
    seven, nine = update.entities
    assert (seven.id, seven.frame_id, [t.text for t in seven.texts]) == ("tag-7", "world", ["tag 7"])
    assert (seven.timestamp.seconds, seven.timestamp.nanos) == divmod(T0_NS + 5, 1_000_000_000)
    (loop,) = seven.lines
    assert loop.type == 1  # LINE_LOOP
    points = xy(loop.points)
    center = points.mean(axis=0)
    assert center == pytest.approx([3.0, -2.0])
    # points evenly spread in angle on the 1-sigma ellipse: their covariance is half the tag's
    assert np.cov(points.T, bias=True) == pytest.approx(cov / 2, abs=1e-9)
    radii = np.linalg.norm(points - center, axis=1)
    assert (radii.max(), radii.min()) == pytest.approx((0.5, 0.2))
    major = points[radii.argmax()] - center
    assert abs(major @ rotation[:, 0]) == pytest.approx(0.5)
    assert (nine.id, [t.text for t in nine.texts], list(nine.lines)) == ("tag-9", ["tag 9"], [])


def test_a_pose_gives_the_robot_transform(served):
    view, client = served
    view.on_input("pose", pose(T0_NS + 1, 1.0, 2.0, 0.7), T0_NS + 1)
    log_time, tf = client.message("/tf")
    (transform,) = tf.transforms
    assert log_time == T0_NS + 1
    assert (transform.parent_frame_id, transform.child_frame_id) == ("world", "base_link")
    t, q = transform.translation, transform.rotation
    assert (t.x, t.y, t.z) == (1.0, 2.0, 0.0)
    assert (q.x, q.y, q.z, q.w) == pytest.approx((0.0, 0.0, math.sin(0.35), math.cos(0.35)))


def test_the_rays_of_an_epoch_start_at_its_pose_and_the_diagnostics_are_json(served):
    view, client = served
    view.on_input("pose", pose(T0_NS, 1.0, 2.0, 0.5), T0_NS)
    view.on_input("pose", pose(T0_NS + 10, 5.0, 5.0, 0.0), T0_NS + 10)  # the window moved on
    used = make("rover_msgs/msg/Aoa", header=header(T0_NS), tag_id=7, angle_rad=0.3, chosen=0)
    unfound = make("rover_msgs/msg/Aoa", header=header(T0_NS), tag_id=9, angle_rad=-0.5, chosen=-1)
    view.on_input("bearings", used, T0_NS + 10)
    view.on_input("bearings", unfound, T0_NS + 10)
    client.message("/rover/aoa")
    log_time, update = client.message("/rover/aoa")  # the second carries both rays
    assert log_time == T0_NS + 10
    (entity,) = update.entities
    green, grey = entity.lines
    assert green.type == grey.type == 2  # LINE_LIST
    assert xy(green.points) == pytest.approx(np.array([[1, 2], [1 + 10 * math.cos(0.8), 2 + 10 * math.sin(0.8)]]))
    assert xy(grey.points) == pytest.approx(np.array([[1, 2], [1 + 10 * math.cos(0.0), 2 + 10 * math.sin(0.0)]]))
    diagnostics = make(
        "rover_msgs/msg/SlamDiagnostics", header=header(T0_NS + 10), iterations=12, window_epochs=30, tags=2
    )
    view.on_input("diagnostics", diagnostics, T0_NS + 10)
    log_time, decoded = client.message("/rover/diagnostics")
    assert decoded == {
        "stamp_s": (T0_NS + 10) / 1e9,
        "iterations": 12,
        "window_epochs": 30,
        "tags": 2,
        "huber_active_rows": 0,
    }


def test_a_port_in_use_is_one_line_and_close_frees_it():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        view = FoxgloveView(FoxgloveViewParams(port=port))
        with pytest.raises(BadInput) as err:
            view.start()
        assert str(err.value).startswith(f"foxglove_view: cannot listen on 127.0.0.1:{port}: ")
        assert "\n" not in str(err.value)
    view = FoxgloveView(FoxgloveViewParams(port=port))
    view.start()
    view.close()
    wait_until(lambda: free(port), f"port {port} to be free", timeout_s=TIMEOUT_S, poll_s=0.001)


def free(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


# --- rover run --view: the node added to the spec -------------------------------------------------


def spec_of(text: str):
    spec, problems = parse(load(text, "x.yaml"))
    assert problems == []
    return spec


def default_spec():
    spec, problems = parse(read_document(ROOT_PIPELINE))
    assert problems == []
    return spec


def test_view_is_wired_to_the_slam_and_placed_beside_it():
    spec = default_spec()
    view = add_view(spec, BUILTINS, 0, None, {})
    assert {p: w.text for p, w in view.inputs.items()} == {
        "pose": "slam/pose",
        "path": "slam/path",
        "tags": "slam/tags",
        "bearings": "slam/bearings",
        "diagnostics": "slam/diagnostics",
    }
    assert (view.uses, view.host, view.params) == ("foxglove_view", "laptop", {"port": 0})
    node = check(spec, BUILTINS, local=["view"]).nodes["view"]
    assert node.local and node.params == FoxgloveViewParams(port=0)


def test_view_on_a_host_changes_neither_the_digest_nor_the_access_rules():
    plain = check(default_spec(), BUILTINS)
    pipeline = load_with_view(ROOT_PIPELINE, BUILTINS, {"view.ray_m": 5.0}, 0, "laptop")
    assert pipeline.nodes["view"].spec.host == "laptop"
    assert pipeline.nodes["view"].params.ray_m == 5.0
    assert pipeline.digest() == plain.digest()
    assert flows(pipeline.spec) == flows(plain.spec)
    for host in plain.spec.hosts:
        assert access_control(pipeline.spec, host) == access_control(plain.spec, host)


def test_view_on_a_host_without_the_slam_says_where_to_give_it():
    with pytest.raises(BadInput) as err:
        load_with_view(ROOT_PIPELINE, BUILTINS, {}, 8765, "nuc")
    assert str(err.value) == (
        f"{ROOT_PIPELINE}: --view on host nuc: the robot's pose is sent by slam on laptop: "
        "give --view to `rover run --host` on that host"
    )


def test_view_needs_a_pose():
    spec = spec_of("operators:\n  tick: {uses: toyops.Ticker}\n")
    with pytest.raises(BadInput, match=r"^x.yaml: --view needs an operator that sends the robot's pose"):
        add_view(spec, BUILTINS, 8765, None, {})


def test_view_reports_the_files_problems_first_and_a_bad_port(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("operators:\n  slam: {uses: slamm}\n")
    with pytest.raises(SpecError, match="unknown operator 'slamm'"):
        load_with_view(bad, BUILTINS, {}, 8765, None)
    with pytest.raises(BadInput, match=r"^--view 70000: a port from 0 \(any free one\) to 65535$"):
        add_view(default_spec(), BUILTINS, 70000, None, {})


def test_the_run_command_takes_view_with_an_optional_port():
    assert parser().parse_args(["run", "--view"]).view == FoxgloveViewParams().port
    assert parser().parse_args(["run", "p.yaml", "--view", "0"]).view == 0
    assert parser().parse_args(["run", "p.yaml"]).view is None


def test_a_local_node_is_left_out_of_the_digest_and_may_not_read_another_host():
    text = """\
name: two
hosts:
  a: {listen: ["tcp/127.0.0.1:7447"]}
  b: {connect: ["tcp/127.0.0.1:7447"]}
operators:
  tick: {uses: toyops.Ticker, host: a}
  pass: {uses: toyops.Passthrough, host: b, inputs: {imu: tick/imu}}
"""
    plain = check(spec_of(text), BUILTINS)
    spec = spec_of(text + "  extra: {uses: toyops.Passthrough, host: b, inputs: {imu: pass/imu}}\n")
    assert check(spec, BUILTINS).digest() != plain.digest()
    assert check(spec, BUILTINS, local=["extra"]).digest() == plain.digest()
    assert flows(spec) == flows(plain.spec)
    across = spec_of(text + "  extra: {uses: toyops.Passthrough, host: b, inputs: {imu: tick/imu}}\n")
    with pytest.raises(SpecError) as err:
        check(across, BUILTINS, local=["extra"])
    assert [d.message for d in err.value.diagnostics] == [
        "operator 'extra' (added on host b by the command line) cannot read tick/imu: it is produced on host a"
    ]


# --- rover run --view 0, the real command ---------------------------------------------------------


class PoseTicker(Source):
    """Poses along the x axis until stopped, stamped with wall-clock time, like a live SLAM."""

    live = True
    outputs = {"pose": Out("geometry_msgs/msg/PoseStamped")}

    def run(self, stop: threading.Event):
        n = 0
        while not stop.is_set():
            now = time.time_ns()
            yield Emit("pose", pose(now, 0.1 * n, 0.0, 0.0))
            yield Watermark(now)
            n += 1
            stop.wait(0.02)


def test_rover_run_view_serves_the_pipeline(tmp_path):
    pipeline = tmp_path / "poses.yaml"
    pipeline.write_text("name: poses\noperators:\n  robot: {uses: test_foxglove_view.PoseTicker}\n")
    proc = popen_rover("run", str(pipeline), "--view", "0", cwd=tmp_path)
    lines: queue.Queue[str | None] = queue.Queue()
    assert proc.stderr is not None
    stderr = proc.stderr

    def read() -> None:
        for line in stderr:
            lines.put(line)
        lines.put(None)

    threading.Thread(target=read, daemon=True).start()
    try:
        deadline, port, seen = time.monotonic() + 60, None, list[str]()
        while port is None:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
            assert line is not None, f"rover run ended: {''.join(seen)}"
            seen.append(line)
            found = re.search(r"foxglove_view: listening on ws://127\.0\.0\.1:(\d+) ", line)
            port = int(found.group(1)) if found else None
        with FoxgloveClient(port) as client:
            client.advertised(5)
            client.subscribe_all()
            _, tf = client.message("/tf")
        assert tf.transforms[0].child_frame_id == "base_link"
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=30)
    assert proc.returncode == 128 + signal.SIGINT
