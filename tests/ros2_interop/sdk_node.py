"""A ROS 2 node of the independent client, zenoh-ros2-sdk, for tests/test_ros2_interop.py. Runs in the
interop environment (its own Zenoh), with the message definitions vendored beside it (msgs/: no
network). One command per run, everything it saw printed as JSON lines on stdout:

    python sdk_node.py sub PORT TOPIC TYPE COUNT [--hash H] [--transient-local DEPTH]
        prints {"ready": true} once subscribed, then each message received as {"msg": {...}}
        (a transient-local one: the publishers' history too; with --save FILE, into FILE), until
        COUNT have come, its stdin ends, or the deadline; a line {"expect": N} on stdin makes COUNT N
        and restarts the deadline, and the end of stdin no longer ends it (a test that knows after a
        run how many were sent waits for them all, however soon it closes the pipe)
    python sdk_node.py pub PORT TOPIC TYPE [--hash H] [--transient-local DEPTH]
        declares a publisher (--hash e.g. TypeHashNotSupported: as a Humble node; transient local:
        with a cache), prints {"ready": true}, then publishes each JSON message read from stdin,
        one per line, saying {"sent": N} after each; leaves at the end of its input
    python sdk_node.py info PORT TOPIC
        prints the topic's publishers and subscribers as `ros2 topic info --verbose` lists them
"""

import argparse
import json
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
import zenoh.ext
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_registry, get_topic_info
from zenoh_ros2_sdk.qos import QosDurability, QosProfile
from zenoh_ros2_sdk.session import ZenohSession

MSGS = Path(__file__).parent / "msgs"
DEADLINE_S = 20.0
NODE = "sdk_node"
NAMESPACE = "/interop"


def plain(value: Any) -> Any:
    """A deserialized message as JSON-ready data."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {name: plain(getattr(value, name)) for name in value.__dataclass_fields__ if name != "__msgtype__"}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def build(store: Any, typename: str, data: dict[str, Any]) -> dict[str, Any]:
    """The keyword arguments of a message of `typename` from JSON data (nested messages built)."""
    _consts, fields = store.fielddefs[typename]
    kwargs = {}
    for name, (kind, spec) in fields:
        value = data[name]
        if kind == 2:  # a nested message (rosbags Nodetype.NAME)
            kwargs[name] = store.types[spec](**build(store, spec, value))
        elif kind in (3, 4) and spec[0][0] == 1:  # an array or sequence of a base type
            kwargs[name] = np.array(value, dtype=float) if spec[0][1][0].startswith("float") else value
        else:
            kwargs[name] = value
    return kwargs


SAYING = threading.Lock()


def say(doc: dict[str, Any]) -> None:
    """One JSON line, whole: Zenoh's threads and the main one print (print writes the newline apart)."""
    with SAYING:
        sys.stdout.write(json.dumps(doc) + "\n")
        sys.stdout.flush()


class CachedPublisher(ROS2Publisher):
    """The SDK's publisher (its tokens, attachments, CDR) on a zenoh-ext advanced publisher with a
    cache of `depth` samples that late subscriptions can find, as rmw_zenoh declares a
    transient-local one (the SDK's own keeps no cache)."""

    def _declare_zenoh_publisher(self, keyexpr: str) -> Any:
        return zenoh.ext.declare_advanced_publisher(
            self.session_mgr.session,
            keyexpr,
            cache=zenoh.ext.CacheConfig(self.qos_profile.history_depth),
            publisher_detection=True,
        )


class HistorySubscriber(ROS2Subscriber):
    """The SDK's subscription (its tokens, CDR) on a zenoh-ext advanced subscriber that asks the
    publishers it finds, early or late, for their last `depth` samples, as rmw_zenoh declares a
    transient-local one. (The SDK's own history query keeps one sample per key: Zenoh's default
    consolidation.)"""

    def _query_historical_data(self) -> None:
        self.sub.undeclare()  # type: ignore[has-type]  # the SDK's plain subscriber, declared before this runs
        history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=self.qos_profile.history_depth)
        self.sub = zenoh.ext.declare_advanced_subscriber(
            self.session_mgr.session, self.keyexpr, self._listener, history=history, subscriber_detection=True
        )


def arguments() -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    ap.add_argument("command", choices=("sub", "pub", "info"))
    ap.add_argument("port", type=int)
    ap.add_argument("topic")
    ap.add_argument("type", nargs="?")
    ap.add_argument("count", type=int, nargs="?", default=1)
    ap.add_argument("--hash", default=None, help="the type hash to use (default: the SDK's own)")
    ap.add_argument("--transient-local", type=int, metavar="DEPTH", help="durability transient local, depth DEPTH")
    ap.add_argument("--save", metavar="FILE", help="sub: write the messages to FILE (JSON lines), not stdout")
    ap.add_argument(
        "--deadline", type=float, default=DEADLINE_S, help="sub: the longest wait for COUNT, and after each expect (s)"
    )
    return ap.parse_args()


def main() -> int:
    get_registry(str(MSGS))  # the vendored definitions, not a clone from GitHub
    args = arguments()
    port = args.port
    latched = args.transient_local is not None
    qos = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=args.transient_local) if latched else None
    where = {"node_name": NODE, "namespace": NAMESPACE, "router_port": port, "type_hash": args.hash or None, "qos": qos}
    if args.command == "sub":
        got: list[Any] = []
        done = threading.Event()
        saved = open(args.save, "w") if args.save else None  # noqa: SIM115 - closed below, after the subscriber

        count = [args.count]
        lock = threading.Lock()
        restarted = threading.Event()

        def on_msg(msg: Any) -> None:
            if saved is not None:  # a file never blocks the receiving thread as a full pipe would
                saved.write(json.dumps({"msg": plain(msg)}) + "\n")
            else:
                say({"msg": plain(msg)})
            with lock:
                got.append(msg)
                if len(got) >= count[0]:
                    done.set()

        sub = (HistorySubscriber if latched else ROS2Subscriber)(args.topic, args.type, on_msg, **where)
        say({"ready": True})

        def read_stdin() -> None:
            expected = False
            for line in sys.stdin:
                with lock:
                    count[0] = int(json.loads(line)["expect"])
                    expected = True
                    if len(got) >= count[0]:
                        done.set()
                restarted.set()
            if not expected:  # told nothing: the end of the input is the end; told a count: wait for it
                done.set()

        threading.Thread(target=read_stdin, daemon=True).start()
        while not done.wait(args.deadline) and restarted.is_set():
            restarted.clear()
        sub.close()
        if saved is not None:
            saved.close()
    elif args.command == "pub":
        pub = (CachedPublisher if latched else ROS2Publisher)(args.topic, args.type, **where)
        say({"ready": True})
        store = ZenohSession.get_instance("127.0.0.1", port).store
        for sent, line in enumerate(sys.stdin, 1):
            pub.publish(**build(store, args.type, json.loads(line)))
            say({"sent": sent})
        pub.close()
    else:
        info = get_topic_info(args.topic, router_port=port, timeout=2.0, verbose=True)
        ends = {"publishers": info.publishers, "subscribers": info.subscribers} if info else {}
        say({kind: [plain_endpoint(e) for e in found] for kind, found in ends.items()})
    ZenohSession.get_instance("127.0.0.1", port).close()
    return 0


def plain_endpoint(endpoint: Any) -> dict[str, Any]:
    """An endpoint as the SDK lists it, its QoS as the SDK decodes the token's."""
    qos = QosProfile.decode(endpoint.qos)
    return {
        "node": endpoint.node_name,
        "namespace": endpoint.node_namespace,
        "type": endpoint.topic_type,
        "hash": endpoint.type_hash,
        "qos": {
            "reliability": qos.reliability.name,
            "durability": qos.durability.name,
            "history": qos.history_kind.name,
            "depth": qos.history_depth,
        },
    }


if __name__ == "__main__":
    sys.exit(main())
