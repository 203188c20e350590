"""Transport between two processes on loopback: CDR sensor_msgs/msg/Imu throughput and round-trip latency.

Both ends use Rover's own path: messages serialized with the typestore, the type name in the
encoding, the attachment with kind and stamps, reliable and blocking. The receiver takes each
sample's bytes and checks its attachment; a second pass also deserializes every message, as an
operator that reads the fields does. Prints figures and, with --json, writes them to a file.
Goals (issue 2): throughput >= 50,000 msg/s, round-trip p50 <= 0.5 ms.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import zenoh

from rover.messages import deserialize, header, make, serialize
from rover.transport import codec
from rover.transport.session import SessionSpec, open_session

IMU = "sensor_msgs/msg/Imu"
DATA_KEY, PING_KEY, PONG_KEY, READY_KEY = "bench/imu", "bench/ping", "bench/pong", "bench/ready"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def imu(i: int):
    return make(
        IMU,
        header=header(1_700_000_000_000_000_000 + i * 5_000_000, "imu_link"),
        angular_velocity=make("geometry_msgs/msg/Vector3", z=0.001 * i),
        linear_acceleration=make("geometry_msgs/msg/Vector3", z=9.81),
    )


def peer(port: int, n: int, decode: bool) -> None:
    """The other process: receives `n` data messages (decoding them if asked), and echoes pings."""
    done = threading.Event()
    times: list[float] = []
    with open_session(SessionSpec(connect=[f"tcp/127.0.0.1:{port}"], label="peer")) as session:
        pong = session.declare_publisher(
            PONG_KEY, encoding=codec.encoding(IMU), congestion_control=zenoh.CongestionControl.BLOCK
        )

        def on_data(sample: zenoh.Sample) -> None:
            att = sample.attachment
            codec.read_attachment(att.to_bytes() if att is not None else None)
            payload = sample.payload.to_bytes()
            if decode:
                deserialize(payload, codec.schema_of(str(sample.encoding)))
            times.append(time.perf_counter())
            if len(times) == n:
                done.set()

        def on_ping(sample: zenoh.Sample) -> None:
            pong.put(sample.payload.to_bytes(), attachment=sample.attachment)

        data_sub = session.declare_subscriber(DATA_KEY, on_data)
        ping_sub = session.declare_subscriber(PING_KEY, on_ping)
        token = session.liveliness().declare_token(READY_KEY)
        done.wait(timeout=600)
        print(json.dumps({"received": len(times), "seconds": times[-1] - times[0] if times else 0.0}), flush=True)
        time.sleep(0.2)
        token.undeclare()
        data_sub.undeclare()
        ping_sub.undeclare()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--messages", type=int, default=200_000)
    ap.add_argument("--pings", type=int, default=5_000)
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--peer", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--decode", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.peer:
        peer(args.peer, args.messages, args.decode)
        return
    figures = measure(args.messages, args.pings, decode=False)
    decoded = measure(args.messages, 0, decode=True)
    figures["throughput_decoded_msg_s"] = decoded["throughput_msg_s"]
    print(
        f"transport: {figures['throughput_msg_s']:,.0f} msg/s CDR Imu between two processes "
        f"({figures['received']:,}/{args.messages:,} received; goal >= 50,000)"
    )
    print(
        f"transport: {figures['throughput_decoded_msg_s']:,.0f} msg/s when the receiver also deserializes "
        f"every message ({decoded['received']:,}/{args.messages:,} received)"
    )
    print(
        f"transport: round trip p50 {figures['rtt_p50_ms']:.3f} ms, p99 {figures['rtt_p99_ms']:.3f} ms "
        "(goal p50 <= 0.5 ms)"
    )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(figures, f, indent=2)


def measure(n_messages: int, n_pings: int, decode: bool) -> dict:
    port = free_port()
    with open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="bench")) as session:
        child = subprocess.Popen(
            [sys.executable, __file__, "--peer", str(port), "--messages", str(n_messages)]
            + (["--decode"] if decode else []),
            stdout=subprocess.PIPE,
            text=True,
        )
        while not list(session.liveliness().get(READY_KEY)):
            time.sleep(0.05)
        pub = session.declare_publisher(
            DATA_KEY,
            encoding=codec.encoding(IMU),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        ping = session.declare_publisher(
            PING_KEY, encoding=codec.encoding(IMU), congestion_control=zenoh.CongestionControl.BLOCK
        )
        got = threading.Event()
        session.declare_subscriber(PONG_KEY, lambda _s: got.set())
        time.sleep(0.3)

        rtts = []
        msg = imu(0)
        for i in range(n_pings):
            got.clear()
            start = time.perf_counter()
            ping.put(serialize(msg, IMU), attachment=codec.attachment(codec.Kind.DATA, i, i))
            if not got.wait(timeout=5):
                raise SystemExit("no pong within 5 s")
            rtts.append(time.perf_counter() - start)

        messages = [imu(i) for i in range(n_messages)]
        start = time.perf_counter()
        for i, m in enumerate(messages):
            pub.put(serialize(m, IMU), attachment=codec.attachment(codec.Kind.DATA, i, i))
        sent_s = time.perf_counter() - start
        assert child.stdout is not None  # stdout=PIPE
        report = json.loads(child.stdout.readline())
        child.wait(timeout=30)

    rtt_ms = np.array(rtts[len(rtts) // 10 :] or [np.nan]) * 1e3
    return {
        "messages": n_messages,
        "received": report["received"],
        "throughput_msg_s": report["received"] / max(report["seconds"], sent_s),
        "rtt_p50_ms": float(np.percentile(rtt_ms, 50)),
        "rtt_p99_ms": float(np.percentile(rtt_ms, 99)),
    }


if __name__ == "__main__":
    main()
