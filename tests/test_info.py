"""`rover info`: topics, counts, rates and CSI packets per channel, as text and as JSON."""

from __future__ import annotations

import json

from conftest import T0_NS, reference_data, run_rover, write_imu_dataset

from rover.formats.bag import BagWriter
from rover.messages import header, make

SETUP = (
    "receiver: {antenna_positions_m: [[0, 0], [0.0258, 0]]}\nexcitation: {channel: 165}\n"
    "tags: [{id: 7, channel: 149}]\n"
)


def test_json_of_a_dataset_with_csi_and_setup(tmp_path):
    path = tmp_path / "d.mcap"
    with BagWriter(path, metadata={"rover.setup": {"yaml": SETUP}}) as bag:
        for i in range(30):
            stamp = T0_NS + i * 100_000_000
            bag.write(
                "/csi", make("rover_msgs/msg/CsiFrame", header=header(stamp), channel=149 if i % 3 else 153), stamp
            )
    proc = run_rover("info", "--json", str(path))
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["message_count"] == 30 and info["duration_s"] == 2.9
    assert info["topics"] == [{"name": "/csi", "type": "rover_msgs/msg/CsiFrame", "count": 30, "rate_hz": 30 / 2.9}]
    assert info["csi_packets_per_channel"] == {"149": 20, "153": 10}
    assert info["setup"] == SETUP
    text = run_rover("info", str(path)).stdout
    assert "channel 149:       20  (tag 7)" in text and "channel 153:       10  (no tag)" in text


def test_the_sample_recording():
    info = json.loads(
        run_rover("info", "--json", str(reference_data() / "recording_sample" / "bag" / "bag.mcap")).stdout
    )
    counts = {t["name"]: t["count"] for t in info["topics"]}
    assert counts == {"/csi": 10579, "/imu/data": 22152, "/odom": 2216}
    assert sum(info["csi_packets_per_channel"].values()) == 10579


def test_bad_paths(tmp_path):
    assert run_rover("info", str(tmp_path / "none.mcap")).returncode == 2
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + b"junk" * 10)
    proc = run_rover("info", str(junk))
    assert proc.returncode == 2 and "junk.mcap" in proc.stderr and "Traceback" not in proc.stderr
    assert run_rover("info", str(write_imu_dataset(tmp_path / "ok.mcap", 10))).returncode == 0
