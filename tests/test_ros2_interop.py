"""Rover's ROS 2 bridge (`ros2_publish`, `ros2_subscribe`) against an independent implementation:
zenoh-ros2-sdk 0.1.8, with its own rmw_zenoh keys, tokens and attachments, rosbags for CDR and
hashes, on the Zenoh rmw_zenoh pins for Jazzy (1.7.2, not ours), in an environment of its own
(.venv-interop, made by `make test`), through a router opened with rmw_zenoh's own router
configuration (tests/ros2_interop/). Both directions, Jazzy's and Humble's hashes, discovery both
ways. No network: the SDK reads the message definitions vendored in tests/ros2_interop/msgs.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers import ROOT, free_port

from rover.drivers.rmw_zenoh import LIVELINESS_PREFIX, parse_entity_token, qos_string, type_hash
from rover.drivers.ros2 import Ros2Params, Ros2Publish, Ros2Subscribe, Ros2SubscribeParams
from rover.messages import header, make
from rover.operator import Emit

HERE = ROOT / "tests" / "ros2_interop"
INTEROP_PYTHON = ROOT / ".venv-interop" / "bin" / "python"
SKIP = "ROVER_SKIP_INTEROP"
WAIT_S = 15.0
"""The longest a test waits for the other side (a process start, a route, a sample)."""
FIRST_WAIT_S = 0.2
"""How long the first message is waited for before it is sent again (its route may be on its way)."""
POLL_S = 0.005
STAMP_NS = 1_700_000_000_123_456_789
IMU = "sensor_msgs/msg/Imu"
STRING = "std_msgs/msg/String"


@pytest.fixture(scope="module")
def interop() -> Path:
    """The interop environment's Python; the tests fail saying how to make it, unless told to skip."""
    if not INTEROP_PYTHON.exists():
        if os.environ.get(SKIP) == "1":
            pytest.skip(f"{SKIP}=1: the independent ROS 2 client is not installed")
        pytest.fail(f"no {INTEROP_PYTHON}: `make .venv-interop/.installed` makes it (make test does); {SKIP}=1 skips")
    return INTEROP_PYTHON


class Process:
    """A process of the interop environment that speaks JSON lines on stdout."""

    def __init__(self, python: Path, script: str, *args: Any):
        self.script = script
        self.proc = subprocess.Popen(
            [str(python), str(HERE / script), *map(str, args)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        self.lines: list[str] = []

    def line(self) -> str:
        """The next line it prints; fail after WAIT_S or when it ends first (with its stderr)."""
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], WAIT_S)
        text = self.proc.stdout.readline() if ready else ""
        if not text:
            self.proc.kill()
            _out, err = self.proc.communicate()
            raise AssertionError(f"{self.script} printed nothing more (exit {self.proc.returncode}):\n{err}")
        self.lines.append(text)
        return text.strip()

    def json(self) -> dict[str, Any]:
        return json.loads(self.line())

    def send(self, doc: dict[str, Any]) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(doc) + "\n")
        self.proc.stdin.flush()

    def close(self) -> str:
        """Close its stdin (communicate does), wait for it; its stderr."""
        try:
            _out, err = self.proc.communicate(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            _out, err = self.proc.communicate()
        return err


@pytest.fixture
def router(interop) -> Iterator[int]:
    """rmw_zenoh's router configuration opened on a free loopback port; the port."""
    port = free_port()
    proc = Process(interop, "router.py", HERE / "DEFAULT_RMW_ZENOH_ROUTER_CONFIG.json5", port)
    assert proc.line() == "ready"
    yield port
    proc.close()


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def imu_msg(i: int) -> Any:
    msg = make(IMU, header=header(STAMP_NS + i, "imu_link"))  # orientation left unset: the identity
    msg.angular_velocity.z = 0.25 * i
    msg.linear_acceleration.z = 9.81
    return msg


def imu_json(i: int) -> dict[str, Any]:
    """The same message as the SDK's fields take it."""
    stamp = STAMP_NS + i
    vector = {"x": 0.0, "y": 0.0, "z": 0.0}
    return {
        "header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "imu_link"},
        "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        "orientation_covariance": [0.0] * 9,
        "angular_velocity": {**vector, "z": 0.25 * i},
        "angular_velocity_covariance": [0.0] * 9,
        "linear_acceleration": {**vector, "z": 9.81},
        "linear_acceleration_covariance": [0.0] * 9,
    }


def publisher_matched(pub: Ros2Publish) -> bool:
    """Every Zenoh publisher of the operator has a subscriber (nothing put is lost for want of a route)."""
    deadline = time.monotonic() + WAIT_S
    while not all(p.matching_status for p in pub.publishers.values()):
        if time.monotonic() > deadline:
            return False
        time.sleep(POLL_S)
    return True


class Collector:
    """Runs a Ros2Subscribe source in a thread, as the runtime does, keeping what it emits."""

    def __init__(self, op: Ros2Subscribe):
        self.op = op
        self.got: list[Emit] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        for item in self.op.run(self.stop):
            if isinstance(item, Emit):
                self.got.append(item)

    def wait_until(self, done: Callable[[list[Emit]], bool], timeout_s: float = WAIT_S) -> list[Emit]:
        """What it emitted once `done` holds for it, or after `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        while not done(list(self.got)) and time.monotonic() < deadline:
            time.sleep(POLL_S)
        return list(self.got)

    def wait_for(self, count: int, timeout_s: float = WAIT_S) -> list[Emit]:
        return self.wait_until(lambda got: len(got) >= count, timeout_s)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(WAIT_S)
        self.op.close()


# -- Rover publishes, the SDK subscribes


def test_an_independent_subscriber_receives_what_rover_publishes(interop, router):
    sdk = Process(interop, "sdk_node.py", "sub", router, "/imu/data", IMU, 3)
    assert sdk.json() == {"ready": True}
    topics = {"imu": {"topic": "/imu/data", "type": IMU}}
    pub = Ros2Publish(Ros2Params(topics=topics, router=endpoint(router), node="rover", namespace="/robot"))
    try:
        assert publisher_matched(pub), "the SDK's subscription never matched Rover's publisher"
        for i in range(3):
            pub.on_input("imu", imu_msg(i), STAMP_NS + i)
        got = [sdk.json()["msg"] for _ in range(3)]
    finally:
        pub.close()
        err = sdk.close()
    assert "Error" not in err, err
    for i, msg in enumerate(got):
        stamp = STAMP_NS + i
        assert msg["header"] == {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": "imu_link"}
        assert msg["angular_velocity"]["z"] == 0.25 * i and msg["linear_acceleration"]["z"] == 9.81
        assert msg["orientation"]["w"] == 1.0


# -- the SDK publishes, Rover subscribes


@pytest.mark.parametrize("their_hash", ["", "TypeHashNotSupported"], ids=["jazzy", "humble"])
def test_rover_receives_what_an_independent_publisher_sends(interop, router, their_hash):
    """With the SDK's own (Jazzy) hash and as a Humble node (no hash): the first message is sent
    until Rover has it (the route may take a moment), then three more, all received in order."""
    topics = {"imu": {"topic": "/imu/data", "type": IMU}}
    sub = Collector(Ros2Subscribe(Ros2SubscribeParams(topics=topics, router=endpoint(router), node="rover")))
    sdk = Process(interop, "sdk_node.py", "pub", router, "/imu/data", IMU, "--hash", their_hash)
    try:
        assert sdk.json() == {"ready": True}
        deadline, sent = time.monotonic() + WAIT_S, 0
        while not sub.wait_for(1, FIRST_WAIT_S):
            assert time.monotonic() < deadline, "Rover never received the SDK's first message"
            sdk.send(imu_json(0))
            sent += 1
            assert sdk.json() == {"sent": sent}
        for i in range(1, 4):
            sdk.send(imu_json(i))
            assert sdk.json() == {"sent": sent + i}
        got = [e for e in sub.wait_until(lambda got: sum(e.msg.angular_velocity.z > 0 for e in got) == 3)]
    finally:
        err = sdk.close()
        sub.close()
    assert "Error" not in err, err
    later = [e for e in got if e.msg.angular_velocity.z > 0]
    assert [e.msg.angular_velocity.z for e in later] == [0.25, 0.5, 0.75]
    assert [e.stamp_ns for e in later] == [STAMP_NS + i for i in (1, 2, 3)]
    assert all(e.msg.header.frame_id == "imu_link" for e in got) and not sub.op.drops


# -- discovery, both ways


def test_the_independent_client_lists_rovers_endpoints(interop, router):
    """`ros2 topic info --verbose` as the SDK answers it: Rover's publisher and subscription on the
    topic, each with Rover's node, namespace, type, Jazzy hash and QoS."""
    out = {"imu": {"topic": "/imu/data", "type": IMU, "depth": 5, "reliable": False}}
    into = {"imu": {"topic": "/imu/data", "type": IMU}}
    pub = Ros2Publish(Ros2Params(topics=out, router=endpoint(router), node="talker", namespace="/robot"))
    sub = Ros2Subscribe(Ros2SubscribeParams(topics=into, router=endpoint(router), node="listener"))
    try:
        info = Process(interop, "sdk_node.py", "info", router, "/imu/data")
        seen = info.json()
        info.close()
    finally:
        pub.close()
        sub.close()
    (publisher,) = seen["publishers"]
    (subscriber,) = seen["subscribers"]
    assert (publisher["node"], publisher["namespace"], publisher["type"]) == ("talker", "/robot", IMU)
    assert (subscriber["node"], subscriber["namespace"], subscriber["type"]) == ("listener", "/", IMU)
    assert publisher["hash"] == subscriber["hash"] == type_hash(IMU)
    keep_last = {"durability": "VOLATILE", "history": "KEEP_LAST"}
    assert publisher["qos"] == {**keep_last, "reliability": "BEST_EFFORT", "depth": 5}
    assert subscriber["qos"] == {**keep_last, "reliability": "RELIABLE", "depth": 10}


def test_rover_reads_the_independent_clients_tokens(interop, router):
    """The SDK's node and subscription, as Rover's token parser reads them from the router."""
    sdk = Process(interop, "sdk_node.py", "sub", router, "/chatter", STRING, 1)
    assert sdk.json() == {"ready": True}
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint(router)]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    keys: list[str] = []

    def mine() -> list[Any]:
        return [t for t in map(parse_entity_token, list(keys)) if t.node == "sdk_node"]

    try:
        with zenoh.open(conf) as session:
            watch = session.liveliness().declare_subscriber(
                f"{LIVELINESS_PREFIX}/0/**", lambda sample: keys.append(str(sample.key_expr)), history=True
            )
            deadline = time.monotonic() + WAIT_S
            while {t.kind for t in mine()} != {"NN", "MS"} and time.monotonic() < deadline:
                time.sleep(POLL_S)
            watch.undeclare()
    finally:
        sdk.close()
    tokens = mine()
    assert {t.kind for t in tokens} == {"NN", "MS"}, keys
    (subscription,) = [t for t in tokens if t.kind == "MS"]
    assert (subscription.namespace, subscription.topic, subscription.typename) == ("/interop", "/chatter", STRING)
    assert subscription.type_hash == type_hash(STRING)
    assert subscription.qos == qos_string(reliable=True, depth=10), subscription.qos


# -- durability: latched topics for late joiners


def messages(sdk: Process, count: int) -> list[dict[str, Any]]:
    """The next `count` messages the SDK node prints (its other lines skipped)."""
    got: list[dict[str, Any]] = []
    while len(got) < count:
        doc = sdk.json()
        if "msg" in doc:
            got.append(doc["msg"])
    return got


LATCHED = {"topic": "/latched", "type": STRING, "depth": 2, "durability": "transient_local"}
"""A topic of one name chunk: zenoh-ros2-sdk 0.1.8 finds transient-local publishers of those only."""


def test_a_late_independent_subscription_gets_rovers_latched_samples(interop, router):
    """Rover publishes three samples on a transient-local topic of depth 2 before anyone subscribes;
    an SDK subscription (transient local) that joins later receives the last two, in order, and lists
    Rover's publisher as transient local."""
    pub = Ros2Publish(Ros2Params(topics={"map": LATCHED}, router=endpoint(router), node="rover"))
    try:
        for i in range(3):
            pub.on_input("map", make(STRING, data=f"map {i}"), STAMP_NS + i)
        sdk = Process(interop, "sdk_node.py", "sub", router, "/latched", STRING, 2, "--transient-local", 2)
        got = [msg["data"] for msg in messages(sdk, 2)]
        sdk.close()
        info = Process(interop, "sdk_node.py", "info", router, "/latched")
        (publisher,) = info.json()["publishers"]
        info.close()
    finally:
        pub.close()
    assert got == ["map 1", "map 2"]
    assert publisher["qos"] == {"reliability": "RELIABLE", "durability": "TRANSIENT_LOCAL", "history": "KEEP_LAST",
                                "depth": 2}  # fmt: skip


def test_a_late_rover_subscription_gets_an_independent_publishers_latched_samples(interop, router):
    """The SDK's publisher on a zenoh-ext cache of depth 2 (as rmw_zenoh declares a transient-local
    one) sends three samples; a transient-local Rover subscription that joins later receives the last
    two, in order."""
    sdk = Process(interop, "sdk_node.py", "pub", router, "/latched", STRING, "--transient-local", 2)
    try:
        assert sdk.json() == {"ready": True}
        for i in range(3):
            sdk.send({"data": f"map {i}"})
            assert sdk.json() == {"sent": i + 1}
        sub = Collector(Ros2Subscribe(Ros2SubscribeParams(topics={"map": LATCHED}, router=endpoint(router))))
        got = sub.wait_for(2)
        sub.close()
    finally:
        err = sdk.close()
    assert "Error" not in err, err
    assert [e.msg.data for e in got] == ["map 1", "map 2"] and not sub.op.drops
