"""`rover info`: topics, counts, rates and CSI packets per channel, as text and as JSON."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import T0_NS, reference_data, run_rover, write_imu_dataset
from mcap.reader import make_reader

from rover.cli.app import main
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


def one_error_line(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    """Run the CLI in-process: status 2 and exactly one line on stderr, which is returned."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("rover: error: ") and "Traceback" not in err, err
    return err.rstrip("\n")


def csi_dataset(path: Path, n: int = 300) -> Path:
    with BagWriter(path, metadata={"rover.setup": {"yaml": SETUP}}) as bag:
        for i in range(n):
            stamp = T0_NS + i * 10_000_000
            frame = make(
                "rover_msgs/msg/CsiFrame", header=header(stamp), channel=149, bfee=np.arange(i % 200, dtype=np.uint8)
            )
            bag.write("/csi", frame, stamp)
    return path


def test_info_of_a_six_byte_text_file_is_one_line(tmp_path, capsys):
    path = tmp_path / "notes.mcap"
    path.write_text("hello\n")
    assert one_error_line(capsys, ["info", str(path)]) == (
        f"rover: error: {path}: not a readable MCAP dataset: not an MCAP file (no MCAP magic bytes at its start)"
    )


def test_info_of_a_dataset_with_a_corrupt_chunk_is_one_line(tmp_path, capsys):
    path = csi_dataset(tmp_path / "d.mcap")
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        (chunk,) = summary.chunk_indexes
    data = bytearray(path.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    data[middle : middle + 8] = bytes(b ^ 0xFF for b in data[middle : middle + 8])
    path.write_bytes(data)
    line = one_error_line(capsys, ["info", str(path)])
    assert line.startswith(f"rover: error: {path}: not a readable MCAP dataset: corrupt "), line


def test_info_of_a_csi_topic_of_another_type_lists_it_without_packet_counts(tmp_path, capsys, caplog):
    path = tmp_path / "d.mcap"
    with BagWriter(path) as bag:
        for i in range(3):
            bag.write("/csi", make("std_msgs/msg/String", data="not csi"), T0_NS + i)
    assert main(["info", "--json", str(path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["topics"][0]["type"] == "std_msgs/msg/String" and info["csi_packets_per_channel"] == {}
    assert f"{path}: topic /csi carries std_msgs/msg/String, not rover_msgs/msg/CsiFrame" in caplog.text
