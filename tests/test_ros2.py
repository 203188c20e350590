"""`ros2_subscribe` and `ros2_publish` on real Zenoh sessions, a router on a free loopback port per test.

What a ROS 2 node would send or expect is built here by hand (struct, xxhash and rosbags' Jazzy
store), not with rover.drivers.rmw_zenoh, so the two cannot agree on a mistake. No ROS 2 install
takes part: the format is the one of rmw_zenoh_cpp 0.2.4+ (Jazzy), as its sources document it.
"""

from __future__ import annotations

import struct
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import xxhash
import zenoh
from helpers import free_port, run_rover
from rmw_bytes import legacy_attachment
from rosbags.typesys import Stores, get_typestore

from rover.drivers.rmw_zenoh import parse_entity_token
from rover.drivers.ros2 import (
    BAD_PAYLOAD,
    NO_ATTACHMENT,
    QUEUE_FULL,
    Ros2Params,
    Ros2Publish,
    Ros2Subscribe,
    Ros2SubscribeParams,
)
from rover.errors import BadInput
from rover.messages import header, make
from rover.operator import Emit

WAIT_S = 5.0
"""The longest a test waits for a route, a token or a sample on loopback."""
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
IMU_HASH = "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b"
IMU_KEY = f"0/imu/data/sensor_msgs::msg::dds_::Imu_/{IMU_HASH}"
HUMBLE_IMU_KEY = "0/imu/data/sensor_msgs::msg::dds_::Imu_/TypeHashNotSupported"
GID = bytes(range(16))
IMU_TOPICS = {"imu": {"topic": "/imu/data", "type": "sensor_msgs/msg/Imu"}}
jazzy = get_typestore(Stores.ROS2_JAZZY)


@pytest.fixture
def router() -> Iterator[str]:
    """A Zenoh router on a free loopback port, standing in for rmw_zenohd; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    yield endpoint
    session.close()


def client(endpoint: str) -> zenoh.Session:
    """A plain Zenoh client of the router, as a ROS 2 node's session would be."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def matched(publisher: zenoh.Publisher) -> bool:
    """Wait until a subscriber matches the publisher (so nothing put is lost for want of a route)."""
    ready = threading.Event()
    listener = publisher.declare_matching_listener(lambda status: ready.set() if status.matching else None)
    try:
        return publisher.matching_status or ready.wait(WAIT_S)
    finally:
        listener.undeclare()


def collect(op: Ros2Subscribe, done: Callable[[list[Emit]], bool]) -> list[Emit]:
    """Iterate the source, as the runtime does, until `done(emitted)` or WAIT_S (it yields a watermark
    whenever it is idle, so the deadline is checked)."""
    stop = threading.Event()
    got: list[Emit] = []
    deadline = time.monotonic() + WAIT_S
    for item in op.run(stop):
        if isinstance(item, Emit):
            got.append(item)
        if done(got) or time.monotonic() > deadline:
            break
    return got


def jazzy_imu(stamp_ns: int, gyro_z: float) -> bytes:
    """A sensor_msgs/Imu as a Jazzy node serializes it (rosbags' Jazzy store, CDR little-endian)."""
    t = jazzy.types
    msg = t["sensor_msgs/msg/Imu"](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="imu"
        ),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.zeros(9),
        angular_velocity=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=gyro_z),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )
    return bytes(jazzy.serialize_cdr(msg, "sensor_msgs/msg/Imu"))


def attachment33(seq: int, stamp_ns: int) -> bytes:
    return struct.pack("<qqB16s", seq, stamp_ns, 16, GID)


def test_subscribe_takes_what_rmw_zenoh_publishes_and_drops_the_rest(router):
    op = Ros2Subscribe(Ros2SubscribeParams(topics=IMU_TOPICS, router=router))
    node = client(router)
    try:
        jazzy_pub = node.declare_publisher(IMU_KEY)
        humble_pub = node.declare_publisher(HUMBLE_IMU_KEY)
        assert matched(jazzy_pub) and matched(humble_pub)
        t1, t3, source2 = 1_700_000_000_100_000_000, 1_700_000_000_300_000_000, 1_700_000_000_222_000_000
        jazzy_pub.put(jazzy_imu(t1, 0.25), attachment=attachment33(1, t1 + 5))
        humble_pub.put(jazzy_imu(0, 0.5), attachment=attachment33(1, source2))  # zero stamp: the source's
        jazzy_pub.put(jazzy_imu(t3, 0.75), attachment=legacy_attachment(2, t3 + 5, GID))  # rmw_zenoh 0.2.0-0.2.3
        jazzy_pub.put(jazzy_imu(t3, 1.0))  # no attachment
        jazzy_pub.put(jazzy_imu(t3, 1.0), attachment=b"\x01" * 10)
        jazzy_pub.put(b"\x00\x01\x00\x00\x01", attachment=attachment33(3, t3))  # truncated CDR
        got = collect(op, lambda got: len(got) == 3 and sum(op.drops.values()) == 3)
    finally:
        op.close()
        node.close()
    assert [(e.port, e.stamp_ns) for e in got] == [("imu", t1), ("imu", source2), ("imu", t3)]
    assert [e.msg.angular_velocity.z for e in got] == [0.25, 0.5, 0.75]
    assert got[0].msg.__msgtype__ == "sensor_msgs/msg/Imu"
    assert got[0].msg.header.frame_id == "imu" and got[0].msg.linear_acceleration.z == 9.81
    assert op.drops == {NO_ATTACHMENT: 2, BAD_PAYLOAD: 1}


def test_a_publisher_of_rmw_zenoh_0_2_3_is_named_once(router, caplog):
    """Samples with the labelled attachment of rmw_zenoh 0.2.0-0.2.3 are read, and one warning
    names their publisher's node, found in the graph by the GID (XXH3 of its token)."""
    op = Ros2Subscribe(Ros2SubscribeParams(topics=IMU_TOPICS, router=router))
    node = client(router)
    entity = f"@ros2_lv/0/{'ab' * 16}/0/3/MP/%/%robot/old_driver"
    mp_key = f"{entity}/%imu%data/sensor_msgs::msg::dds_::Imu_/{IMU_HASH}/::,10:,:,:,,"
    gid = xxhash.xxh3_128_intdigest(mp_key.encode()).to_bytes(16, "little")
    try:
        token = node.liveliness().declare_token(mp_key)
        old_pub = node.declare_publisher(IMU_KEY)
        assert matched(old_pub)
        t1 = 1_700_000_000_100_000_000
        with caplog.at_level("WARNING", logger="rover"):
            for i in range(3):
                old_pub.put(jazzy_imu(t1 + i, 0.25), attachment=legacy_attachment(i + 1, t1 + i, gid))
            got = collect(op, lambda got: len(got) == 3)
        token.undeclare()
    finally:
        op.close()
        node.close()
    assert len(got) == 3 and not op.drops
    named = [r.getMessage() for r in caplog.records if "0.2.0-0.2.3" in r.getMessage()]
    assert named == [
        "ros2_subscribe: /imu/data: the publisher /robot/old_driver runs rmw_zenoh 0.2.0-0.2.3 (a labelled "
        "attachment): supported are 0.2.4 and later; its samples are read"
    ]


def test_a_full_queue_drops_the_oldest(router):
    op = Ros2Subscribe(Ros2SubscribeParams(topics=IMU_TOPICS, router=router, queue_size=2))
    node = client(router)
    try:
        pub = node.declare_publisher(IMU_KEY)
        assert matched(pub)
        for i in range(5):
            pub.put(jazzy_imu(1_000 + i, float(i)), attachment=attachment33(i + 1, 1_000 + i))
        with op._ready:  # five samples arrived: two held, three pushed out
            assert op._ready.wait_for(lambda: op._overflow + len(op._pending) == 5, WAIT_S)
        got = collect(op, lambda got: len(got) == 2)
    finally:
        op.close()
        node.close()
    assert [e.msg.angular_velocity.z for e in got] == [3.0, 4.0]
    assert op.drops == {QUEUE_FULL: 3}


def test_publish_to_subscribe_round_trip(router):
    topics: dict[str, dict[str, Any]] = {
        "imu": {"topic": "/imu/data", "type": "sensor_msgs/msg/Imu", "depth": 5, "reliable": False},
        "aoa": {"topic": "rover/aoa", "type": "rover_msgs/msg/Aoa"},  # relative: in the namespace
        "note": {"topic": "/note", "type": "std_msgs/msg/String"},
    }
    sub = Ros2Subscribe(Ros2SubscribeParams(topics=topics, router=router, node="listener", namespace="/robot1"))
    pub = Ros2Publish(Ros2Params(topics=topics, router=router, node="talker", namespace="/robot1"))
    try:
        assert all(matched(p) for p in pub.publishers.values())
        stamp = 1_700_000_000_000_000_123
        imu = make("sensor_msgs/msg/Imu", header=header(stamp, "imu_link"))
        imu.angular_velocity.z = 0.5
        aoa = make("rover_msgs/msg/Aoa", header=header(stamp + 1, "array"), tag_id=7, angle_rad=0.25)
        pub.on_input("imu", imu, stamp)
        pub.on_input("aoa", aoa, stamp + 1)
        before_ns = time.time_ns()
        pub.on_input("note", make("std_msgs/msg/String", data="hello"), stamp + 2)
        after_ns = time.time_ns()
        got = collect(sub, lambda got: len(got) == 3)
    finally:
        pub.close()
        sub.close()
    by_port = {e.port: e for e in got}
    assert sorted(by_port) == ["aoa", "imu", "note"] and not sub.drops
    assert by_port["imu"].stamp_ns == stamp and by_port["imu"].msg.angular_velocity.z == 0.5
    assert by_port["imu"].msg.header.frame_id == "imu_link"
    assert by_port["aoa"].stamp_ns == stamp + 1 and by_port["aoa"].msg.tag_id == 7
    assert by_port["aoa"].msg.angle_rad == 0.25
    # without a header: the attachment's source timestamp, the publish time (as rmw_zenoh puts it)
    note_ns = by_port["note"].stamp_ns
    assert note_ns is not None and before_ns <= note_ns <= after_ns and by_port["note"].msg.data == "hello"
    assert sub.topics["aoa"].topic == "/robot1/rover/aoa"


class Tokens:
    """Liveliness tokens seen on `@ros2_lv/0/**`, as `ros2 topic list` discovers the graph."""

    def __init__(self, session: zenoh.Session):
        self.alive: set[str] = set()
        self.changed = threading.Condition()
        self.subscriber = session.liveliness().declare_subscriber("@ros2_lv/0/**", self._seen, history=True)

    def _seen(self, sample: zenoh.Sample) -> None:
        with self.changed:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(key)
            else:
                self.alive.discard(key)
            self.changed.notify_all()

    def wait(self, until: Callable[[set[str]], bool]) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: until(self.alive), WAIT_S)


def test_publish_is_seen_as_rmw_zenoh_sees_a_publisher(router):
    node = client(router)
    samples: list[tuple[str, bytes, bytes | None]] = []
    arrived = threading.Condition()

    def receive(sample: zenoh.Sample) -> None:
        with arrived:
            att = sample.attachment
            samples.append((str(sample.key_expr), sample.payload.to_bytes(), None if att is None else att.to_bytes()))
            arrived.notify_all()

    data_key = f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    subscriber = node.declare_subscriber(data_key, receive)  # a listener already running
    topics = {"chatter": {"topic": "/chatter", "type": "std_msgs/msg/String", "depth": 7}}
    pub = Ros2Publish(Ros2Params(topics=topics, router=router, node="talker"))
    try:
        zid = pub.zid
        node_key = f"@ros2_lv/0/{zid}/0/0/NN/%/%/talker"
        mp_key = f"@ros2_lv/0/{zid}/0/1/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/{STRING_HASH}/::,7:,:,:,,"
        tokens = Tokens(node)  # declared after the publisher: its tokens come from the history
        assert tokens.wait(lambda alive: {node_key, mp_key} <= alive), tokens.alive
        assert {k for k in tokens.alive if f"/{zid}/" in k} == {node_key, mp_key}
        parsed = parse_entity_token(mp_key)
        assert (parsed.kind, parsed.namespace, parsed.node) == ("MP", "/", "talker")
        assert (parsed.topic, parsed.typename, parsed.type_hash) == ("/chatter", "std_msgs/msg/String", STRING_HASH)

        assert matched(pub.publishers["chatter"])
        stamps = [1_700_000_000_123_456_789, 1_700_000_001_000_000_000]
        published_ns = []
        for stamp, text in zip(stamps, ["hello", "world"], strict=True):
            before_ns = time.time_ns()
            pub.on_input("chatter", make("std_msgs/msg/String", data=text), stamp)
            published_ns.append((before_ns, time.time_ns()))
        with arrived:
            assert arrived.wait_for(lambda: len(samples) == 2, WAIT_S), samples
        subscriber.undeclare()

        pub.close()  # the graph sees the node leave
        assert tokens.wait(lambda alive: not any(f"/{zid}/" in k for k in alive))
    finally:
        pub.close()
        node.close()

    gid = xxhash.xxh3_128_intdigest(mp_key.encode()).to_bytes(16, "little")
    assert [key for key, _, _ in samples] == [data_key, data_key]
    assert samples[0][1] == bytes.fromhex("00010000 06000000 68656c6c6f00")  # std_msgs/String "hello"
    world = jazzy.types["std_msgs/msg/String"](data="world")
    assert samples[1][1] == bytes(jazzy.serialize_cdr(world, "std_msgs/msg/String"))
    for seq, ((before_ns, after_ns), (_key, _payload, att)) in enumerate(zip(published_ns, samples, strict=True), 1):
        assert att is not None and len(att) == 33
        number, source_ns, gid_length, source_gid = struct.unpack("<qqB16s", att)
        assert (number, gid_length, source_gid) == (seq, 16, gid)
        assert before_ns <= source_ns <= after_ns, "the source timestamp is the publish time, as rmw_zenoh's"
    assert samples[0][2] is not None and samples[0][2][:8].hex(" ") == "01 00 00 00 00 00 00 00"  # little-endian
    assert samples[0][2][16] == 16  # the GID's length, before the GID


def test_subscribe_declares_its_node_and_subscription(router):
    topics = {"imu": {"topic": "/imu/data", "type": "sensor_msgs/msg/Imu", "reliable": False, "depth": 5}}
    op = Ros2Subscribe(Ros2SubscribeParams(topics=topics, router=router, domain_id=0))
    node = client(router)
    try:
        tokens = Tokens(node)
        ms_key = f"@ros2_lv/0/{op.zid}/0/1/MS/%/%/rover/%imu%data/sensor_msgs::msg::dds_::Imu_/{IMU_HASH}/2::,5:,:,:,,"
        assert tokens.wait(lambda alive: {f"@ros2_lv/0/{op.zid}/0/0/NN/%/%/rover", ms_key} <= alive), tokens.alive
    finally:
        op.close()
        node.close()


def test_an_unreachable_router_is_one_line_naming_it():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(BadInput) as info:
        Ros2Subscribe(Ros2SubscribeParams(topics=IMU_TOPICS, router=endpoint, connect_timeout_s=0.3))
    assert endpoint in str(info.value) and "\n" not in str(info.value)


PIPELINE = """\
version: 1
name: ros
operators:
  ros:
    uses: ros2_subscribe
    params:
      topics:
        imu: {topic: /imu/data, type: IMU_TYPE}
        aoa: {topic: /rover/aoa, type: rover_msgs/msg/Aoa}
  preint:
    uses: preintegration
    inputs: {imu: ros/imu, epochs: ros/aoa}
"""


def test_check_wires_ros2_ports_by_their_types(tmp_path):
    good = tmp_path / "good.yaml"
    good.write_text(PIPELINE.replace("IMU_TYPE", "sensor_msgs/msg/Imu"))
    ok = run_rover("check", str(good))
    assert ok.returncode == 0 and ": ok: pipeline 'ros'" in ok.stdout, ok.stderr

    mismatch = tmp_path / "mismatch.yaml"
    text = PIPELINE.replace("IMU_TYPE", "sensor_msgs/msg/Imu") + (
        "  slam:\n    uses: slam\n    inputs: {aoa: ros/aoa, odometry: preint/odometry, wheel: ros/imu}\n"
    )
    mismatch.write_text(text)
    bad = run_rover("check", str(mismatch))
    lines = bad.stderr.strip().splitlines()
    assert bad.returncode == 2 and len(lines) == 2 and lines[1] == "1 problem found", bad.stderr
    assert "mismatch.yaml:15:62: message type mismatch: ros/imu sends sensor_msgs/msg/Imu" in lines[0]
    assert "input 'wheel' of 'slam' takes nav_msgs/msg/Odometry" in lines[0]


def test_check_names_the_topics_param_for_an_unknown_type(tmp_path):
    path = tmp_path / "unknown.yaml"
    path.write_text(PIPELINE.replace("IMU_TYPE", "sensor_msgs/msg/Imuu").split("  preint:")[0])
    proc = run_rover("check", str(path))
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 2 and lines[1] == "1 problem found", proc.stderr
    assert lines[0].endswith(
        "unknown.yaml:6:5: operator 'ros' (ros2_subscribe): param 'topics': 'imu': unknown message type "
        "'sensor_msgs/msg/Imuu'"
    )
    assert "Traceback" not in proc.stderr
