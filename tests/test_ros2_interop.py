"""Rover's ROS 2 bridge (`ros2_publish`, `ros2_subscribe`) against an independent implementation:
zenoh-ros2-sdk 0.1.8, with its own rmw_zenoh keys, tokens and attachments, rosbags for CDR and
hashes, on the Zenoh rmw_zenoh pins for Jazzy (1.7.2, not ours), in an environment of its own
(.venv-interop, made by `make test`), through a router opened with rmw_zenoh's own router
configuration (tests/ros2_interop/). Both directions, Jazzy's and Humble's hashes, discovery both
ways. No network: the SDK reads the message definitions vendored in tests/ros2_interop/msgs.
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import os
import select
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
import zenoh
from helpers import LAP, ROOT, free_port, read_bag, run_rover

from rover.drivers.rmw_zenoh import LIVELINESS_PREFIX, parse_entity_token, qos_string, type_hash
from rover.drivers.ros2 import Ros2Params, Ros2Publish, Ros2Subscribe, Ros2SubscribeParams
from rover.messages import deserialize, header, make, stamp_ns
from rover.operator import Emit

HERE = ROOT / "tests" / "ros2_interop"
INTEROP_PYTHON = ROOT / ".venv-interop" / "bin" / "python"
SKIP = "ROVER_SKIP_INTEROP"
WAIT_S = 15.0
"""The longest a test waits for the other side (a process start, a route, a sample)."""
FIRST_WAIT_S = 0.2
"""How long the first message is waited for before it is sent again (its route may be on its way)."""
POLL_S = 0.005
SHORT_LAP = (*LAP, "trajectory.speed_m_s=1.0")
"""one lap of the paper's room at 1 m/s: 41 s of data"""
REPLAY_SPEED = 8.0
"""times real time: a live robot's pace, eight times over"""
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
        """Close its stdin (communicate does), wait for it; its stderr (what it printed on stdout
        since the last `line` joins `lines`)."""
        try:
            out, err = self.proc.communicate(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        self.lines += out.splitlines()
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


# -- pipelines/ros2.yaml end to end


def replayed(ros2_yaml: Path, dataset: Path, router_port: int, out: Path, target: Path) -> Path:
    """pipelines/ros2.yaml with its live sources (the NIC, its channel hops, the rig file and the robot's
    topics) replaced by a replay of `dataset`: everything from the sweep on, and what goes back to the
    ROS 2 graph, exactly as shipped."""
    doc = yaml.safe_load(ros2_yaml.read_text())
    ops = doc["operators"]
    for live in ("rig", "hop", "csi", "robot"):
        del ops[live]
    ops = {"replay": {"uses": "dataset_replay", "params": {"path": str(dataset), "speed": REPLAY_SPEED}}, **ops}
    renamed = {"csi/csi": "replay/csi", "rig/setup": "replay/setup", "robot/imu": "replay/imu",
               "robot/odom": "replay/odom"}  # fmt: skip
    for op in ops.values():
        op["inputs"] = {port: renamed.get(wire, wire) for port, wire in op.get("inputs", {}).items()}
    del ops["sweep"]["inputs"]["hops"]
    ops["sweep"]["params"]["mode"] = "label"  # a recording's frames are labelled, not hopped
    for topic in ops["publish"]["params"]["topics"].values():
        topic["history"] = "keep_all"  # a replay loses nothing: a slow subscriber holds it back
    # the tags as the SLAM sent them, to hold each marker array against
    ops["record"] = {"uses": "recorder", "inputs": {"tags": "slam/tags"}, "params": {"out": "${output}"}}
    doc["operators"] = ops
    doc["vars"] |= {"router": endpoint(router_port), "output": str(out)}
    target.write_text(yaml.safe_dump(doc, sort_keys=False))
    return target


def stamp_of(msg: dict[str, Any]) -> int:
    return msg["header"]["stamp"]["sec"] * 10**9 + msg["header"]["stamp"]["nanosec"]


def plane(p: dict[str, Any], q: dict[str, Any]) -> tuple[float, float, float]:
    """(x, y, yaw) of a position (or translation) and a quaternion."""
    return p["x"], p["y"], math.atan2(2 * (q["w"] * q["z"] + q["x"] * q["y"]), 1 - 2 * (q["y"] ** 2 + q["z"] ** 2))


@pytest.mark.slow
def test_the_ros2_pipeline_gives_the_graph_what_its_outputs_hold(interop, router, simulated, tmp_path):
    """pipelines/ros2.yaml on a replayed lap (41 s), over two workers, watched by the independent client:
    each /rover/pose it receives is the run's live pose at that stamp (trajectory_live.tum) with a
    positive-definite covariance; each /tf map -> odom composed with the dataset's odometry at that
    stamp is the pose; each /rover/tags marker array puts every tag where the tags the SLAM sent do,
    in order (recorded beside); the last of the run is tags.csv's; the last /rover/path is trajectory.tum,
    in the map frame. Every one the run sent arrives, the
    last ones too (the published topics keep all: a slow subscriber holds the replay back, and the
    samples still on their way when the run ends are waited for, not cut off)."""
    dataset = simulated(*SHORT_LAP)
    out = tmp_path / "out"
    pipeline = replayed(ROOT / "pipelines" / "ros2.yaml", dataset, router, out, tmp_path / "ros2-replay.yaml")
    watched = {"/rover/pose": "geometry_msgs/msg/PoseWithCovarianceStamped", "/rover/path": "nav_msgs/msg/Path",
               "/rover/tags": "visualization_msgs/msg/MarkerArray", "/tf": "tf2_msgs/msg/TFMessage"}  # fmt: skip
    port_of = {"/rover/pose": "pose", "/rover/path": "path", "/rover/tags": "markers", "/tf": "tf"}
    """each topic's input port of pipelines/ros2.yaml's ros2_publish"""
    saved = {topic: tmp_path / f"{topic.strip('/').replace('/', '_')}.jsonl" for topic in watched}
    sdk = {
        topic: Process(
            interop, "sdk_node.py", "sub", router, topic, kind, 10**9, "--save", saved[topic], "--deadline", 600
        )
        for topic, kind in watched.items()
    }
    try:
        assert all(p.json() == {"ready": True} for p in sdk.values())
        run = run_rover("run", str(pipeline), "--workers", "2", timeout=300)
        assert run.returncode == 0, run.stderr
        published = json.loads((out / "run.json").read_text())["operators"]["publish"]["received"]
        for topic, proc in sdk.items():  # what is still on its way when the run ends is waited for
            proc.send({"expect": published[port_of[topic]]})
        got = {}
        for topic, proc in sdk.items():
            err = proc.close()
            assert proc.proc.returncode == 0, err
            got[topic] = [json.loads(line)["msg"] for line in saved[topic].read_text().splitlines()]
    finally:
        for proc in sdk.values():
            if proc.proc.poll() is None:
                proc.close()
    rows = live = np.loadtxt(out / "trajectory_live.tum", ndmin=2)
    sent = [deserialize(d, "rover_msgs/msg/TagArray") for _t, _s, d in read_bag(out / "results.mcap")]
    assert published["pose"] == published["tf"] == len(live) and published["markers"] == len(sent)
    assert {topic: len(got[topic]) for topic in watched} == {t: published[port_of[t]] for t in watched}

    def live_at(stamp: int) -> np.ndarray:
        """The live pose of that stamp (TUM's seconds hold it to a microsecond at 1.7e9 s)."""
        k = int(np.argmin(np.abs(rows[:, 0] - stamp / 1e9)))
        assert abs(rows[k, 0] - stamp / 1e9) < 1e-6, f"no live pose at {stamp}"
        return rows[k]

    poses = got["/rover/pose"]
    assert len(poses) == len(live), f"{len(poses)} of {len(live)} poses received"
    received = np.array([stamp_of(m) for m in poses]) / 1e9
    assert np.allclose(received, live[:, 0], rtol=0, atol=1e-6), "not the run's poses, in order"
    for msg in poses:
        row = live_at(stamp_of(msg))
        p = msg["pose"]["pose"]["position"]
        assert msg["header"]["frame_id"] == "map" and (p["x"], p["y"]) == pytest.approx(row[1:3], abs=1e-6)
        cov = np.reshape(msg["pose"]["covariance"], (6, 6))
        assert np.all(np.linalg.eigvalsh(cov[:2, :2]) > 0)
    odom = sorted(
        (stamp_ns(m), m)
        for m in (
            deserialize(data, "nav_msgs/msg/Odometry") for topic, _t, data in read_bag(dataset) if topic == "/odom"
        )  # fmt: skip
    )
    odom_stamps = [s for s, _m in odom]
    transforms = [t for m in got["/tf"] for t in m["transforms"]]
    assert len(transforms) == len(live), f"{len(transforms)} of {len(live)} transforms received"
    received = np.array([stamp_of(t) for t in transforms]) / 1e9
    assert np.allclose(received, live[:, 0], rtol=0, atol=1e-6), "not the run's transforms, in order"
    assert {(t["header"]["frame_id"], t["child_frame_id"]) for t in transforms} == {("map", "odom")}
    for t in transforms:
        o = odom[bisect.bisect_right(odom_stamps, stamp_of(t)) - 1][1].pose.pose
        mo = plane(t["transform"]["translation"], t["transform"]["rotation"])
        q = o.orientation
        ob = plane({"x": o.position.x, "y": o.position.y}, {"x": q.x, "y": q.y, "z": q.z, "w": q.w})
        c, sn = math.cos(mo[2]), math.sin(mo[2])
        mb = (mo[0] + c * ob[0] - sn * ob[1], mo[1] + sn * ob[0] + c * ob[1])
        row = live_at(stamp_of(t))
        assert mb == pytest.approx(tuple(row[1:3]), abs=1e-6)
    arrays = got["/rover/tags"]
    assert len(arrays) == len(sent), f"{len(arrays)} of {len(sent)} marker arrays received"
    for array, tags in zip(arrays, sent, strict=True):  # in order, none lost
        spheres = {m["id"]: m["pose"]["position"] for m in array["markers"] if m["ns"] == "tags"}
        assert sorted(spheres) == sorted(t.id for t in tags.tags)
        for tag in tags.tags:
            at = spheres[tag.id]
            assert (at["x"], at["y"]) == pytest.approx((tag.position.x, tag.position.y), abs=1e-9)
    smoothed = np.loadtxt(out / "trajectory.tum", ndmin=2)  # the last path is the whole trajectory, final
    path = np.array([[stamp_of(p) / 1e9, *plane(p["pose"]["position"], p["pose"]["orientation"])[:2]]
                     for p in got["/rover/path"][-1]["poses"]])  # fmt: skip
    assert got["/rover/path"][-1]["header"]["frame_id"] == "map"
    assert path.shape == (len(smoothed), 3) and np.allclose(path, smoothed[:, :3], rtol=0, atol=1e-6)
    with (out / "tags.csv").open() as f:
        final = {int(row["id"]): row for row in csv.DictReader(f) if row["observable"] == "1"}
    assert final and all(
        (t.position.x, t.position.y) == pytest.approx((float(final[t.id]["x"]), float(final[t.id]["y"])), abs=1e-5)
        for t in sent[-1].tags
        if t.id in final
    )
