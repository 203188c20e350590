"""`ros2_subscribe` and `ros2_publish`: ROS 2 topics into and out of a pipeline, over rmw_zenoh.

Each operator opens its own Zenoh session as a client of the ROS 2 router (`rmw_zenohd`, param
`router`), apart from the pipeline's own session, and appears in the ROS graph as a node
(`node`, `namespace`) with one subscription or publisher per entry of `topics`:
`{port: {topic: /imu/data, type: sensor_msgs/msg/Imu, depth: 10, reliable: true}}`, which also
names the operator's ports. No bridge and no ROS install are needed.

The wire format (keys, liveliness tokens, CDR payloads, attachments) follows rmw_zenoh_cpp
0.2.4 and later, as released for ROS 2 Jazzy; see `rover.drivers.rmw_zenoh`. It was tested
against itself and plain Zenoh sessions only, NOT against a real ROS 2 install. Limits: volatile
keep-last topics only (no transient_local history, services or actions); Rover publishes with the
Jazzy type hash, so a Humble (rmw_zenoh 0.1.x) subscriber does not match, while samples of
Humble publishers (`TypeHashNotSupported`) are received; types whose fields differ between
Rover's message set (Humble's) and Jazzy's are refused.
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import zenoh
import zenoh.ext

from rover.drivers import rmw_zenoh as rz
from rover.errors import BadInput
from rover.messages import ANY, Raw, deserialize, has_header, known_type, serialize
from rover.messages import stamp_ns as header_stamp_ns
from rover.operator import (
    COMPLETE,
    PORT_NAME_RE,
    Emit,
    In,
    Operator,
    Out,
    Ports,
    RunOutcome,
    Source,
    Watermark,
)
from rover.pipeline.params import Checked, Matches, NonNegativeFloat, NonNegativeInt, PositiveFloat, PositiveInt

log = logging.getLogger("rover.ros2")

POLL_S = 0.1
"""how long `Ros2Subscribe.run` waits for a sample before it sends a watermark"""
RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 1.5}
ENCLAVE = "/"
"""the default ROS security enclave (tokens carry it; Rover does not use SROS2)"""
NODE_ENTITY_ID = 0
"""the node's id in its tokens; its publishers or subscriptions are numbered from 1"""
TOPIC_KEYS = ("topic", "type", "depth", "reliable", "durability", "history")
DURABILITIES = ("volatile", "transient_local")
HISTORIES = ("keep_last", "keep_all")
HEARTBEAT_S = 0.5
"""A reliable transient-local publisher's sporadic heartbeat (rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD)"""
DEFAULT_DEPTH = 10
"""rclcpp/rclpy's usual `QoS(10)`"""
_TOPIC_NAME = re.compile(r"(/[A-Za-z_][A-Za-z0-9_]*)+")
QUEUE_FULL = "ROS 2 samples (the oldest) that overflowed the queue (`queue_size`)"
NO_ATTACHMENT = "ROS 2 samples without a valid rmw_zenoh attachment"
BAD_PAYLOAD = "ROS 2 samples that do not deserialize as their topic's type"


@dataclass(frozen=True)
class TopicSpec:
    """One entry of `topics`, checked: the fully qualified topic name and its QoS."""

    topic: str
    type: str
    depth: int = DEFAULT_DEPTH
    reliable: bool = True
    transient_local: bool = False
    """a publisher keeps its last `depth` samples for subscriptions that join later (latched:
    `/tf_static`, a map); a subscription asks the publishers it finds for theirs"""
    keep_all: bool = False
    """a reliable publisher waits for a slow subscriber instead of dropping (rmw_zenoh: KEEP_ALL and
    RELIABLE put with congestion control BLOCK): nothing is lost, and the pipeline is held back"""

    @property
    def qos(self) -> str:
        return rz.qos_string(self.reliable, self.depth, self.transient_local, self.keep_all)


RouterEndpoint = Annotated[str, Matches(r"[a-z0-9-]+/\S+", "a Zenoh endpoint like tcp/127.0.0.1:7447")]
NodeName = Annotated[str, Matches(r"[A-Za-z][A-Za-z0-9_]*", "a ROS node name (a letter, then letters, digits, _)")]
Namespace = Annotated[str, Matches(r"/|(/[A-Za-z_][A-Za-z0-9_]*)+", "a ROS namespace like / or /robot1")]


@dataclass(frozen=True)
class Ros2Params(Checked):
    """What both directions share: the topics (one port each) and where the ROS graph is."""

    topics: dict[str, dict[str, Any]]
    """port -> {topic, type, depth (10), reliable (true), durability (volatile, or transient_local),
    history (keep_last, or keep_all)}; a relative topic is resolved in `namespace`"""
    router: RouterEndpoint = "tcp/127.0.0.1:7447"
    """the ROS 2 Zenoh router (`ros2 run rmw_zenoh_cpp rmw_zenohd`), connected to as a client"""
    domain_id: NonNegativeInt = 0
    """ROS_DOMAIN_ID"""
    node: NodeName = "rover"
    namespace: Namespace = "/"
    connect_timeout_s: PositiveFloat = 5.0
    """how long opening waits for the router"""


@dataclass(frozen=True)
class Ros2SubscribeParams(Ros2Params):
    lateness_s: NonNegativeFloat = 0.5
    """while no sample comes, watermarks are this far behind the host clock: a sample stamped
    earlier than that (a slow link, another host's clock) is late for the pipeline"""
    queue_size: PositiveInt = 1000
    """samples held between Zenoh's receive thread and the pipeline; when full the oldest are dropped"""


def parse_topics(topics: Mapping[str, Any] | None, namespace: str = "/") -> dict[str, TopicSpec]:
    """Check the `topics` param; ValueError naming the param and the entry for anything wrong."""
    if not topics:
        raise ValueError("param 'topics' must name at least one topic, as {port: {topic: /name, type: pkg/msg/Type}}")
    specs = {}
    for port, entry in topics.items():
        where = f"param 'topics': {port!r}"
        if not (isinstance(port, str) and PORT_NAME_RE.match(port)):
            raise ValueError(f"{where}: a port name must start with a letter and use letters, digits or _")
        if not isinstance(entry, Mapping):
            raise ValueError(f"{where}: expected {{topic: /name, type: pkg/msg/Type}}, got {entry!r}")
        unknown = sorted(str(k) for k in entry if k not in TOPIC_KEYS)
        if unknown:
            raise ValueError(f"{where}: unknown key(s) {', '.join(unknown)} (keys: {', '.join(TOPIC_KEYS)})")
        topic, typename = entry.get("topic"), entry.get("type")
        depth, reliable = entry.get("depth", DEFAULT_DEPTH), entry.get("reliable", True)
        if not isinstance(topic, str):
            raise ValueError(f"{where}: needs 'topic', a ROS topic name like /imu/data")
        if not topic.startswith("/"):
            topic = f"{namespace.rstrip('/')}/{topic}"
        if not _TOPIC_NAME.fullmatch(topic):
            raise ValueError(f"{where}: {entry['topic']!r} is not a ROS topic name (like /imu/data)")
        if not isinstance(typename, str) or typename == ANY or not known_type(typename):
            raise ValueError(f"{where}: unknown message type {typename!r}")
        if not rz.same_layout_as_jazzy(typename):
            raise ValueError(
                f"{where}: {typename} has other fields in ROS 2 Jazzy than in Rover's message set (Humble's)"
            )
        if isinstance(depth, bool) or not isinstance(depth, int) or depth < 1:
            raise ValueError(f"{where}: 'depth' must be an integer >= 1, got {depth!r}")
        if not isinstance(reliable, bool):
            raise ValueError(f"{where}: 'reliable' must be true or false, got {reliable!r}")
        durability = entry.get("durability", DURABILITIES[0])
        if durability not in DURABILITIES:
            raise ValueError(f"{where}: 'durability' must be {' or '.join(DURABILITIES)}, got {durability!r}")
        history = entry.get("history", HISTORIES[0])
        if history not in HISTORIES:
            raise ValueError(f"{where}: 'history' must be {' or '.join(HISTORIES)}, got {history!r}")
        specs[port] = TopicSpec(
            topic, typename, depth, reliable, durability == "transient_local", history == "keep_all"
        )
    return specs


def _topics_of(params: Any) -> dict[str, TopicSpec]:
    if not isinstance(params, Ros2Params):
        raise ValueError("param 'topics' is required")
    return parse_topics(params.topics, params.namespace)


def open_ros_session(router: str, timeout_s: float) -> zenoh.Session:
    """A Zenoh client of the ROS 2 router, scouting off; BadInput naming the router when it cannot connect."""
    conf = zenoh.Config()
    try:
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([router]))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
        conf.insert_json5("connect/timeout_ms", str(max(1, int(timeout_s * 1000))))
        conf.insert_json5("connect/exit_on_failure", "true")
        conf.insert_json5("connect/retry", json.dumps(RETRY))
    except zenoh.ZError as exc:
        raise BadInput(f"param 'router': {router!r} is not a Zenoh endpoint: {_first_line(exc)}") from None
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        log.debug("ros2: opening a session to %s failed: %s", router, exc)
        raise BadInput(
            f"cannot reach the ROS 2 router at {router} within {timeout_s:g} s (is rmw_zenohd running?)"
        ) from None


def _first_line(exc: Exception) -> str:
    text = str(exc).strip()
    return text.splitlines()[0].split(" at /")[0] if text else type(exc).__name__


class _Ros2Node:
    """A session to the ROS 2 router and this operator's node token; entities are added by the subclass."""

    kind: str = ""
    """the token kind of each topic's entity: MP or MS"""

    def _open(self, params: Ros2Params, topics: Mapping[str, TopicSpec]) -> None:
        self.session = open_ros_session(params.router, params.connect_timeout_s)
        self.zid = str(self.session.info.zid())
        self.node_key = rz.node_token(
            params.domain_id, self.zid, NODE_ENTITY_ID, ENCLAVE, params.namespace, params.node
        )
        self.entity_keys: dict[str, str] = {}
        for eid, (port, spec) in enumerate(topics.items(), start=NODE_ENTITY_ID + 1):
            self.entity_keys[port] = rz.entity_token(
                self.kind,
                params.domain_id,
                self.zid,
                NODE_ENTITY_ID,
                eid,
                ENCLAVE,
                params.namespace,
                params.node,
                spec.topic,
                spec.type,
                rz.type_hash(spec.type),
                spec.qos,
            )
        liveliness = self.session.liveliness()
        self.tokens: list[zenoh.LivelinessToken] = []
        try:
            for key in [self.node_key, *self.entity_keys.values()]:
                self.tokens.append(liveliness.declare_token(key))
        except zenoh.ZError as exc:
            self._close([])
            raise BadInput(f"cannot declare the ROS 2 graph tokens on {params.router}: {_first_line(exc)}") from None

    def _close(self, entities: list[Any]) -> None:
        """Undeclare the entities and tokens before closing: the graph sees the node leave at once.
        Closing again does nothing."""
        if self.session.is_closed():
            return
        for entity in [*entities, *self.tokens]:
            with contextlib.suppress(zenoh.ZError):
                entity.undeclare()
        with contextlib.suppress(zenoh.ZError):
            self.session.close()


class Ros2Subscribe(_Ros2Node, Source):
    """Publishes each ROS 2 topic of `topics` on the output port of the same name.

    A sample is stamped with its message's header stamp, or, for a message without a header (or
    with a zero stamp), with the publisher's source timestamp from the attachment. Stamps are the
    ROS publishers' own: one older than what was already sent is counted late by the runtime."""

    live = True
    kind = rz.SUBSCRIPTION
    Params = Ros2SubscribeParams

    @classmethod
    def declared_ports(cls, params: Any) -> Ports:
        topics = _topics_of(params)
        return Ports({}, {port: Out(spec.type, doc=f"ROS 2 topic {spec.topic}") for port, spec in topics.items()})

    def __init__(self, params: Ros2SubscribeParams):
        super().__init__(params)
        self.topics = _topics_of(params)
        self._hashes = {port: rz.type_hash(spec.type) for port, spec in self.topics.items()}
        self._pending: deque[tuple[str, str, bytes, bytes | None]] = deque()
        self._ready = threading.Condition()
        self._overflow = 0
        self._warned: set[tuple[str, str]] = set()
        self._publishers: dict[bytes, str] = {}
        """GID -> the node (namespace/name) of each publisher seen in the graph"""
        self._legacy: set[bytes] = set()
        self._open(params, self.topics)
        self.graph = self.session.liveliness().declare_subscriber(
            f"{rz.LIVELINESS_PREFIX}/{params.domain_id}/**",
            zenoh.handlers.Callback(self._on_token, indirect=False),
            history=True,
        )
        self.subscribers = [
            self._subscribe(rz.topic_key(params.domain_id, spec.topic, spec.type, rz.ANY_HASH), port, spec)
            for port, spec in self.topics.items()
        ]
        log.info(
            "ros2_subscribe: node %s in %s on %s, topics %s",
            params.node,
            params.namespace,
            params.router,
            ", ".join(f"{s.topic} ({s.type})" for s in self.topics.values()),
        )

    def _subscribe(self, key: str, port: str, spec: TopicSpec) -> Any:
        """A subscriber as rmw_zenoh declares one: a transient-local one also finds the publishers
        with a cache (late or early) and asks each for its last `depth` samples, and a reliable one
        recovers what it missed from their heartbeats."""
        handler = zenoh.handlers.Callback(self._receiver(port), indirect=False)
        if not spec.transient_local:
            return self.session.declare_subscriber(key, handler)
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=spec.depth)
        recovery = zenoh.ext.RecoveryConfig(periodic_queries=None, heartbeat=True) if spec.reliable else None
        return zenoh.ext.declare_advanced_subscriber(
            self.session, key, handler, history=history, recovery=recovery, subscriber_detection=True
        )

    def _on_token(self, sample: zenoh.Sample) -> None:
        """Note each publisher's node by its GID (the XXH3 of its token), to name it in warnings."""
        if sample.kind != zenoh.SampleKind.PUT:
            return
        try:
            token = rz.parse_entity_token(str(sample.key_expr))
        except ValueError:
            return  # another kind of token, or one this reader does not know: nothing to name
        if token.kind == rz.PUBLISHER:
            node = f"{token.namespace.rstrip('/')}/{token.node}"
            self._publishers[rz.gid(str(sample.key_expr))] = node

    def _receiver(self, port: str) -> Callable[[zenoh.Sample], None]:
        def receive(sample: zenoh.Sample) -> None:
            """Runs in Zenoh's receive thread: only queue the bytes (the oldest go when the queue is full)."""
            if sample.kind != zenoh.SampleKind.PUT:
                return
            att = sample.attachment
            key_hash = str(sample.key_expr).rsplit("/", 1)[-1]
            item = (port, key_hash, sample.payload.to_bytes(), None if att is None else att.to_bytes())
            with self._ready:
                if len(self._pending) >= self.params.queue_size:
                    self._pending.popleft()
                    self._overflow += 1
                self._pending.append(item)
                self._ready.notify()

        return receive

    def _take(self, timeout_s: float) -> list[tuple[str, str, bytes, bytes | None]]:
        with self._ready:
            if not self._pending:
                self._ready.wait(timeout_s)
            batch = list(self._pending)
            self._pending.clear()
            overflow, self._overflow = self._overflow, 0
        self.drop(QUEUE_FULL, overflow)
        return batch

    def _decode(self, port: str, key_hash: str, payload: bytes, att: bytes | None) -> Emit | None:
        spec = self.topics[port]
        try:
            _seq, source_ns, gid = rz.parse_attachment(att)
        except ValueError as exc:
            self.drop(NO_ATTACHMENT)
            log.debug("ros2_subscribe: %s: dropped a sample: %s", spec.topic, exc)
            return None
        if rz.is_legacy_attachment(att) and gid not in self._legacy:
            self._legacy.add(gid)
            who = self._publishers.get(gid, f"of GID {gid.hex()} (its node not in the graph)")
            log.warning(
                "ros2_subscribe: %s: the publisher %s runs rmw_zenoh 0.2.0-0.2.3 (a labelled attachment): "
                "supported are 0.2.4 and later; its samples are read",
                spec.topic,
                who,
            )
        if key_hash not in (self._hashes[port], rz.HUMBLE_HASH) and (port, key_hash) not in self._warned:
            self._warned.add((port, key_hash))
            log.warning(
                "ros2_subscribe: %s: a publisher's type hash %s is not %s's %s: its definition may differ",
                spec.topic,
                key_hash,
                spec.type,
                self._hashes[port],
            )
        try:
            msg = deserialize(payload, spec.type)
        except Exception as exc:  # noqa: BLE001 - any decoding failure of foreign bytes is a drop, never a crash
            self.drop(BAD_PAYLOAD)
            log.debug("ros2_subscribe: %s: dropped a sample: %s: %s", spec.topic, type(exc).__name__, exc)
            return None
        stamp = header_stamp_ns(msg) if has_header(spec.type) else 0
        return Emit(port, msg, stamp or source_ns)

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        lateness_ns = int(self.params.lateness_s * 1e9)
        while not stop.is_set():
            batch = self._take(POLL_S)
            if not batch:
                yield Watermark(time.time_ns() - lateness_ns)
                continue
            for item in batch:
                emit = self._decode(*item)
                if emit is not None:
                    yield emit

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        self._close([self.graph, *self.subscribers])


class Ros2Publish(_Ros2Node, Operator):
    """Publishes each input on the ROS 2 topic `topics` gives its port, as an rmw_zenoh publisher does:
    CDR on the topic's key with an attachment (sequence number from 1, the publish time on the system
    clock as source timestamp, the publisher's GID); the message's own stamp stays in its header. A
    transient-local topic keeps its last `depth` samples for subscriptions that join later."""

    kind = rz.PUBLISHER
    Params = Ros2Params

    @classmethod
    def declared_ports(cls, params: Any) -> Ports:
        topics = _topics_of(params)
        return Ports({port: In(spec.type, raw=True, doc=f"to ROS 2 {spec.topic}") for port, spec in topics.items()}, {})

    def __init__(self, params: Ros2Params):
        super().__init__(params)
        self.topics = _topics_of(params)
        self._open(params, self.topics)
        self.gids = {port: rz.gid(key) for port, key in self.entity_keys.items()}
        self.sequence = dict.fromkeys(self.topics, 0)
        self.publishers = {
            port: self._publisher(rz.topic_key(params.domain_id, spec.topic, spec.type, rz.type_hash(spec.type)), spec)
            for port, spec in self.topics.items()
        }
        log.info(
            "ros2_publish: node %s in %s on %s, topics %s",
            params.node,
            params.namespace,
            params.router,
            ", ".join(f"{s.topic} ({s.type})" for s in self.topics.values()),
        )

    def _publisher(self, key: str, spec: TopicSpec) -> Any:
        """A publisher as rmw_zenoh declares one (rmw_publisher_data.cpp): a transient-local one keeps a
        cache of `depth` samples and can be detected by late subscriptions; a reliable one of those
        also sends sporadic heartbeats so they recover a missed last sample."""
        reliability = zenoh.Reliability.RELIABLE if spec.reliable else zenoh.Reliability.BEST_EFFORT
        block = spec.reliable and spec.keep_all
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        if not spec.transient_local:
            return self.session.declare_publisher(key, reliability=reliability, congestion_control=congestion)
        miss = zenoh.ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=HEARTBEAT_S) if spec.reliable else None
        return zenoh.ext.declare_advanced_publisher(
            self.session,
            key,
            reliability=reliability,
            congestion_control=congestion,
            cache=zenoh.ext.CacheConfig(spec.depth),
            sample_miss_detection=miss,
            publisher_detection=True,
        )

    def on_input(self, port: str, msg: Any, stamp_ns: int) -> tuple[Emit, ...]:
        spec = self.topics[port]
        payload = msg.payload if isinstance(msg, Raw) else serialize(msg, spec.type)
        self.sequence[port] += 1
        att = rz.attachment(self.sequence[port], time.time_ns(), self.gids[port])
        self.publishers[port].put(payload, attachment=att)
        return ()

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        self._close(list(self.publishers.values()))
