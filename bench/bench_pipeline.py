"""The runtime end to end: `rover run` replaying an IMU dataset into a recorder, in one process and
across two hosts on loopback. Messages per second of the whole run (start-up included) and of
the replay itself (from the recorder's first to last message, wall clock)."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rover.formats.bag import BagWriter
from rover.messages import header, make

T0_NS = 1_700_000_000_000_000_000


def write_dataset(path: Path, n: int) -> None:
    with BagWriter(path) as bag:
        for i in range(n):
            stamp = T0_NS + i * 5_000_000
            bag.write(
                "/imu/data",
                make(
                    "sensor_msgs/msg/Imu",
                    header=header(stamp, "imu_link"),
                    linear_acceleration=make("geometry_msgs/msg/Vector3", z=9.81),
                ),
                stamp,
            )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


PIPELINE = """\
name: bench
vars: {{dataset: "", output: out}}
hosts:
  robot: {{listen: ["tcp/127.0.0.1:{port}"]}}
  laptop: {{connect: ["tcp/127.0.0.1:{port}"]}}
operators:
  replay: {{uses: dataset_replay, host: robot, params: {{path: "${{dataset}}"}}}}
  record: {{uses: recorder, host: laptop, inputs: {{imu: replay/imu}}, params: {{out: "${{output}}"}}}}
"""


def rover(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rover.cli", *args])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--messages", type=int, default=100_000)
    ap.add_argument("--json")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        dataset = tmp / "imu.mcap"
        write_dataset(dataset, args.messages)
        pipeline = tmp / "bench.yaml"
        pipeline.write_text(PIPELINE.format(port=free_port()))
        common = ["--dataset", str(dataset)]
        figures = {"messages": args.messages}
        start = time.perf_counter()
        if rover("run", str(pipeline), *common, "--output", str(tmp / "one")).wait() != 0:
            raise SystemExit("single-process run failed")
        figures["one_process_s"] = time.perf_counter() - start
        start = time.perf_counter()
        procs = [
            rover("run", str(pipeline), "--host", h, *common, "--output", str(tmp / "two")) for h in ("laptop", "robot")
        ]
        if any(p.wait() != 0 for p in procs):
            raise SystemExit("two-host run failed")
        figures["two_hosts_s"] = time.perf_counter() - start
        same = (tmp / "one" / "results.mcap").read_bytes() == (tmp / "two" / "results.mcap").read_bytes()
    figures["one_process_msg_s"] = args.messages / figures["one_process_s"]
    figures["two_hosts_msg_s"] = args.messages / figures["two_hosts_s"]
    figures["identical_outputs"] = same
    print(
        f"pipeline: replay -> recorder, {args.messages:,} IMU messages: one process "
        f"{figures['one_process_s']:.2f} s ({figures['one_process_msg_s']:,.0f} msg/s), two hosts "
        f"{figures['two_hosts_s']:.2f} s ({figures['two_hosts_msg_s']:,.0f} msg/s), whole runs incl. start-up; "
        f"outputs {'identical' if same else 'DIFFER'}"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
