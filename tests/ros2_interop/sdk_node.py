"""A ROS 2 node of the independent client, zenoh-ros2-sdk, for tests/test_ros2_interop.py. Runs in the
interop environment (its own Zenoh), with the message definitions vendored beside it (msgs/: no
network). One command per run, everything it saw printed as JSON lines on stdout:

    python sdk_node.py sub PORT TOPIC TYPE COUNT [HASH]
        prints {"ready": true} once subscribed, then each message received as {"msg": {...}},
        until COUNT have come, its stdin ends, or the deadline
    python sdk_node.py pub PORT TOPIC TYPE HASH
        declares a publisher (HASH: "" for its own, or e.g. TypeHashNotSupported as Humble), prints
        {"ready": true}, then publishes each JSON message read from stdin, one per line, saying
        {"sent": N} after each; leaves at the end of its input
    python sdk_node.py info PORT TOPIC
        prints the topic's publishers and subscribers as `ros2 topic info --verbose` lists them
"""

import json
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np
from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, get_registry, get_topic_info
from zenoh_ros2_sdk.qos import QosProfile
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


def say(doc: dict[str, Any]) -> None:
    print(json.dumps(doc), flush=True)


def main() -> int:
    get_registry(str(MSGS))  # the vendored definitions, not a clone from GitHub
    command, port = sys.argv[1], int(sys.argv[2])
    if command == "sub":
        topic, typename, count = sys.argv[3], sys.argv[4], int(sys.argv[5])
        type_hash = sys.argv[6] if len(sys.argv) > 6 else None
        got: list[Any] = []
        done = threading.Event()

        def on_msg(msg: Any) -> None:
            say({"msg": plain(msg)})
            got.append(msg)
            if len(got) >= count:
                done.set()

        sub = ROS2Subscriber(topic, typename, on_msg, node_name=NODE, namespace=NAMESPACE, router_port=port,
                             type_hash=type_hash)  # fmt: skip
        say({"ready": True})

        def until_stdin_ends() -> None:
            sys.stdin.read()
            done.set()

        threading.Thread(target=until_stdin_ends, daemon=True).start()
        done.wait(DEADLINE_S)
        sub.close()
    elif command == "pub":
        topic, typename, type_hash = sys.argv[3], sys.argv[4], sys.argv[5] or None
        pub = ROS2Publisher(topic, typename, node_name=NODE, namespace=NAMESPACE, router_port=port, type_hash=type_hash)
        say({"ready": True})
        store = ZenohSession.get_instance("127.0.0.1", port).store
        for sent, line in enumerate(sys.stdin, 1):
            pub.publish(**build(store, typename, json.loads(line)))
            say({"sent": sent})
        pub.close()
    elif command == "info":
        info = get_topic_info(sys.argv[3], router_port=port, timeout=2.0, verbose=True)
        ends = {"publishers": info.publishers, "subscribers": info.subscribers} if info else {}
        say({kind: [plain_endpoint(e) for e in found] for kind, found in ends.items()})
    else:
        raise SystemExit(f"unknown command {command!r}")
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
