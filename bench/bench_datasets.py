"""Datasets: `rover convert` throughput on a ROS 2 bag of 200,000 messages (goal >= 40,000 msg/s) and
`rover simulate --scenario paper` wall time (goal < 20 s)."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer

from rover.datasets.convert import convert
from rover.datasets.scenario import load_scenario
from rover.datasets.simulate import simulate
from rover.messages import header, make, serialize, typestore

T0_NS = 1_700_000_000_000_000_000
SETUP = """\
receiver: {antenna_positions_m: [[0, 0], [0.0258, 0], [0.0129, -0.0223]]}
excitation: {channel: 165}
tags: [{id: 1, channel: 149}]
"""


def write_bag(path: Path, n: int) -> None:
    """IMU at 200 Hz with a CSI frame every 4th sample, as a robot records them."""
    bfee = np.frombuffer(bytes(213), dtype=np.uint8)
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        imu = writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=typestore)
        csi = writer.add_connection("/csi", "rover_msgs/msg/CsiFrame", typestore=typestore)
        imu_msg = make("sensor_msgs/msg/Imu", linear_acceleration=make("geometry_msgs/msg/Vector3", z=9.81))
        for i in range(n):
            stamp = T0_NS + i * 4_000_000
            if i % 5 == 4:
                writer.write(
                    csi, stamp, serialize(make("rover_msgs/msg/CsiFrame", header=header(stamp), channel=149, bfee=bfee))
                )
            else:
                imu_msg.header = header(stamp, "imu")
                writer.write(imu, stamp, serialize(imu_msg))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--messages", type=int, default=200_000)
    ap.add_argument("--json")
    args = ap.parse_args()
    figures: dict = {"messages": args.messages}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        write_bag(tmp / "bag", args.messages)
        (tmp / "setup.yaml").write_text(SETUP)
        start = time.perf_counter()
        report = convert([tmp / "bag"], tmp / "out.mcap", setup=tmp / "setup.yaml")
        took = time.perf_counter() - start
        assert sum(report.written.values()) == args.messages
        figures["convert_msg_s"] = args.messages / took
        start = time.perf_counter()
        simulate(load_scenario("paper"), 0, tmp / "sim.mcap")
        figures["simulate_paper_s"] = time.perf_counter() - start
    print(f"convert: {figures['convert_msg_s']:,.0f} msg/s on a {args.messages:,}-message ROS 2 bag (goal >= 40,000)")
    print(f"simulate: paper scenario in {figures['simulate_paper_s']:.1f} s (goal < 20 s)")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
