"""`rover convert`: real ROS 1 and ROS 2 bags and a delivered recording folder to datasets."""

from __future__ import annotations

import json
import math
import re
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers import T0_NS, popen_rover, read_bag, reference_data, run_rover, stop_while_writing
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from rover.datasets.convert import convert
from rover.errors import BadInput
from rover.messages import deserialize, header, make, serialize, typestore

SETUP = """\
receiver: {antenna_positions_m: [[0, 0], [0.0258, 0], [0.0129, -0.0223]]}
excitation: {channel: 165}
tags: [{id: 1, channel: 149}]
"""


def counts(path: Path) -> dict[str, int]:
    out: dict[str, int] = {}
    for topic, _s, _d in read_bag(path):
        out[topic] = out.get(topic, 0) + 1
    return out


def test_the_recording_folder_converts_as_it_is(tmp_path):
    source = reference_data() / "recording_sample"
    out = tmp_path / "rs.mcap"
    proc = run_rover("convert", str(source), "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    with AnyReader([source / "bag"]) as reader:
        source_counts = {c.topic: c.msgcount for c in reader.connections}
    got = counts(out)
    assert {t: got[t] for t in source_counts} == source_counts
    assert got["/groundtruth/tags"] == 1 and got["/groundtruth/pose"] == 11076
    info = json.loads(run_rover("info", "--json", str(out)).stdout)
    assert "0.9834" in info["setup"] and "tags" in info["setup"]
    with AnyReader([out]) as reader:
        assert {c.topic for c in reader.connections} >= {"/csi", "/imu/data", "/odom"}


def test_the_real_ros1_bag_keeps_every_imu_sample(tmp_path):
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP + "topics: {csi: null, imu: /imu/data, odom: /jackal_velocity_controller/odom}\n")
    bag = reference_data() / "bags" / "jackal_imu_odom.bag"
    out = tmp_path / "jackal.mcap"
    report = convert([bag], out, setup=setup)
    assert report.written == {"/imu/data": 3061, "/odom": 3060}
    with AnyReader([bag]) as reader:
        conn = [c for c in reader.connections if c.topic == "/imu/data"]
        source: list[Any] = [reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages(connections=conn)]
    converted = [deserialize(d, "sensor_msgs/msg/Imu") for t, _s, d in read_bag(out) if t == "/imu/data"]
    for a, b in zip(source, converted, strict=True):
        assert (a.header.stamp.sec, a.header.stamp.nanosec) == (b.header.stamp.sec, b.header.stamp.nanosec)
        for f in ("linear_acceleration", "angular_velocity"):
            va, vb = getattr(a, f), getattr(b, f)
            assert (va.x, va.y, va.z) == (vb.x, vb.y, vb.z)
        np.testing.assert_array_equal(a.orientation_covariance, b.orientation_covariance)


def write_ros2_bag(path: Path, storage: StoragePlugin) -> None:
    """CSI and an IMU in g with a NaN sample, a duplicate and two samples out of order."""
    with Writer(path, version=9, storage_plugin=storage) as writer:
        csi = writer.add_connection("/wifi/csi", "rover_msgs/msg/CsiFrame", typestore=typestore)
        imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=typestore)
        stamps = [T0_NS + i * 5_000_000 for i in range(400)]
        stamps[100], stamps[101] = stamps[101], stamps[100]
        stamps.insert(200, stamps[199])
        for i, stamp in enumerate(stamps):
            g = make("geometry_msgs/msg/Vector3", x=0.01, y=-0.02, z=float("nan") if i == 300 else 1.0)
            msg = make("sensor_msgs/msg/Imu", header=header(stamp, "imu"), linear_acceleration=g)
            received = T0_NS + i * 5_000_000 + 1_000
            writer.write(imu, received, serialize(msg))
            if i % 10 == 0:
                frame = make(
                    "rover_msgs/msg/CsiFrame",
                    header=header(stamp + 1, "nic"),
                    channel=149,
                    bfee=np.arange(5, dtype=np.uint8),
                )
                writer.write(csi, received + 1, serialize(frame))


@pytest.mark.parametrize("storage", [StoragePlugin.SQLITE3, StoragePlugin.MCAP])
def test_ros2_bags_with_the_usual_faults(tmp_path, storage, caplog):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, storage)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    out = tmp_path / "out.mcap"
    report = convert([bag], out, setup=setup, command_line="rover convert bag")
    assert report.topics == {"csi": "/wifi/csi", "imu": "/imu"}
    assert report.imu_in_g
    assert report.dropped == {"imu: NaN or infinite sample": 1, "imu: duplicate stamp": 1}
    assert report.resorted["imu"] == 1
    imu = [deserialize(d, "sensor_msgs/msg/Imu") for t, _s, d in read_bag(out) if t == "/imu/data"]
    assert len(imu) == 399
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in imu]
    assert stamps == sorted(stamps) and len(set(stamps)) == 399
    assert all(math.isclose(m.linear_acceleration.z, 9.80665) for m in imu)
    assert sum(1 for t, _s, _d in read_bag(out) if t == "/csi") == 41


def test_trimming_and_explicit_topics(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    out = tmp_path / "out.mcap"
    report = convert([bag], out, setup=setup, start=0.5, end=1.0, topics={"imu": "/imu", "csi": "/wifi/csi"})
    imu = [s for t, s, _d in read_bag(out) if t == "/imu/data"]
    bag_start = T0_NS + 1_000  # the first message's receive time
    assert min(imu) >= bag_start + 500_000_000 and max(imu) <= bag_start + 1_000_000_000
    assert report.written["/imu/data"] == len(imu) == 100


def test_a_bag_without_csi_is_the_documented_error(tmp_path):
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    proc = run_rover(
        "convert",
        str(reference_data() / "bags" / "jackal_imu_odom.bag"),
        "--setup",
        str(setup),
        "-o",
        str(tmp_path / "x.mcap"),
    )
    assert proc.returncode == 2
    assert (
        "no CSI topic (rover_msgs/msg/CsiFrame, or WiROS's rf_msgs/msg/Wifi) found; topics there: /imu/data "
        "(sensor_msgs/msg/Imu)" in proc.stderr
    )
    assert "topics: {csi: null}" in proc.stderr
    assert list(tmp_path.iterdir()) == [setup]


def test_an_interrupted_conversion_leaves_nothing_and_outputs_are_kept(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    out = tmp_path / "out.mcap"

    def interrupt(done: int, total: int) -> None:
        if done:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        convert([bag], out, setup=setup, progress=lambda d, t: interrupt(d + 1, t))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "setup.yaml"]
    convert([bag], out, setup=setup)
    with pytest.raises(BadInput, match="exists"):
        convert([bag], out, setup=setup)
    convert([bag], out, setup=setup, force=True)


def test_truth_from_another_dataset_and_info_on_a_bag_folder(tmp_path):
    source = reference_data() / "recording_sample"
    first = tmp_path / "first.mcap"
    convert([source], first)
    second = tmp_path / "second.mcap"
    report = convert([source / "bag"], second, setup=source / "setup.yaml", truth=first)
    assert report.written["/groundtruth/pose"] == 11076 and report.written["/groundtruth/tags"] == 1
    info = json.loads(run_rover("info", "--json", str(source / "bag")).stdout)
    assert info["message_count"] == 34947


def test_custom_message_definitions_in_the_bag_are_honoured(tmp_path):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    definition = "std_msgs/Header header\nuint8 rssi\nuint16 channel\nuint8[] bfee\nstring note\n"
    store.register(get_types_from_msg(definition, "mylab_msgs/msg/WifiCsi"))
    Custom = store.types["mylab_msgs/msg/WifiCsi"]
    Time, Header = store.types["builtin_interfaces/msg/Time"], store.types["std_msgs/msg/Header"]
    bag = tmp_path / "bag"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        csi = writer.add_connection("/wifi", "mylab_msgs/msg/WifiCsi", typestore=store)
        imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=typestore)
        for i in range(20):
            stamp = T0_NS + i * 10_000_000
            head = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="nic")
            msg = Custom(header=head, rssi=40, channel=149, bfee=np.full(7, i, dtype=np.uint8), note="lab")
            writer.write(csi, stamp, store.serialize_cdr(msg, "mylab_msgs/msg/WifiCsi"))
            writer.write(imu, stamp, serialize(make("sensor_msgs/msg/Imu", header=header(stamp))))
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP + "topics: {csi: /wifi, imu: /imu, odom: null}\n")
    out = tmp_path / "out.mcap"
    convert([bag], out, setup=setup)
    frames = [deserialize(d, "rover_msgs/msg/CsiFrame") for t, _s, d in read_bag(out) if t == "/csi"]
    assert [f.bfee.tolist() for f in frames] == [[i] * 7 for i in range(20)]
    assert {f.channel for f in frames} == {149}


def test_an_output_that_is_a_directory_is_one_line_before_any_work(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    out = tmp_path / "existing_dir"
    out.mkdir()
    proc = run_rover("convert", str(bag), "--setup", str(setup), "-o", str(out), "--force")
    assert proc.returncode == 2
    assert proc.stderr.splitlines() == [
        f"rover: error: {out}: is a directory; name the file to write, e.g. {out / 'dataset.mcap'}"
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "existing_dir", "setup.yaml"]
    assert list(out.iterdir()) == []


def test_converting_onto_one_of_its_own_sources_is_rejected(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    dataset = tmp_path / "dataset.mcap"
    convert([bag], dataset, setup=setup)
    (inner,) = bag.glob("*.mcap")
    before = {p: p.read_bytes() for p in (setup, dataset, inner)}
    with pytest.raises(BadInput, match=re.escape(f"{setup}: is also an input ({setup})")):
        convert([bag], setup, setup=setup, force=True)
    with pytest.raises(BadInput, match=re.escape(f"{dataset}: is also an input ({dataset})")):
        convert([dataset], dataset, setup=setup, force=True)
    with pytest.raises(BadInput, match=re.escape(f"{inner}: is inside the bag folder {bag} being converted")):
        convert([bag], inner, setup=setup, force=True)
    assert {p: p.read_bytes() for p in before} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "dataset.mcap", "setup.yaml"]


def test_force_keeps_the_old_file_when_a_full_disk_fails_the_new_one(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    out = tmp_path / "out.mcap"
    convert([bag], out, setup=setup)
    old = out.read_bytes()
    source = reference_data() / "recording_sample"
    proc = popen_rover("convert", str(source), "-o", str(out), "--force", max_file_bytes=1_000_000)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 2
    assert stderr.splitlines() == [f"rover: error: {out}: cannot write: File too large"]
    assert out.read_bytes() == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "out.mcap", "setup.yaml"]


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["TERM", "INT"])
def test_a_signal_while_writing_leaves_no_partial(tmp_path, signum, status):
    proc = popen_rover("convert", str(reference_data() / "recording_sample"), "-o", str(tmp_path / "x.mcap"))
    assert stop_while_writing(proc, tmp_path / ".x.mcap.partial", signum)[0] == status
    assert list(tmp_path.iterdir()) == []


def imu_bag(bag: Path, cut: frozenset[int] = frozenset(), before_1970: frozenset[int] = frozenset()) -> Path:
    """A ROS 2 bag of 300 IMU samples at 200 Hz; those numbered in `cut` cut to 40 bytes, those in
    `before_1970` stamped 5 s before 1970."""
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        imu = writer.add_connection("/imu", "sensor_msgs/msg/Imu", typestore=typestore)
        for i in range(300):
            received = T0_NS + i * 5_000_000
            stamp = -5_000_000_000 if i in before_1970 else received
            g = make("geometry_msgs/msg/Vector3", z=9.8)
            data = serialize(make("sensor_msgs/msg/Imu", header=header(stamp, "imu"), linear_acceleration=g))
            writer.write(imu, received, data[:40] if i in cut else data)
    return bag


@pytest.mark.parametrize(
    ("faults", "reason", "dropped"),
    [
        # after the first IMU message proves the layout, later ones pass through undecoded: a short one
        # must still be caught (as the CSI and IMU readers of the bag would not notice)
        ({"cut": frozenset({150, 151})}, "imu: undecodable", 2),
        # a header's sec is signed; no MCAP log time holds a negative stamp (it failed with a struct
        # error, found by the contract fuzzing)
        ({"before_1970": frozenset({10})}, "imu: stamp before 1970", 1),
    ],
    ids=["shorter than its type", "stamped before 1970"],
)
def test_a_message_that_cannot_be_converted_is_dropped_and_counted(tmp_path, faults, reason, dropped):
    bag = imu_bag(tmp_path / "bag", **faults)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP + "topics: {csi: null}\n")
    report = convert([bag], tmp_path / "out.mcap", setup=setup)
    assert report.dropped == {reason: dropped}
    assert report.written["/imu/data"] == 300 - dropped


def test_an_empty_window_is_refused_and_the_truth_is_clipped_to_the_window(tmp_path):
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    truth = tmp_path / "truth.tum"
    truth.write_text("".join(f"{(T0_NS + i * 10**8) / 1e9:.9f} {i * 0.1} 0 0 0 0 0 1\n" for i in range(40)))
    out = tmp_path / "out.mcap"
    with pytest.raises(BadInput, match=r"--start 100 is not before --end 50"):
        convert([bag], out, setup=setup, start=100, end=50)
    cli = run_rover("convert", str(bag), "-o", str(out), "--setup", str(setup), "--start", "100", "--end", "50")
    assert cli.returncode == 2 and not out.exists()
    assert cli.stderr.splitlines() == ["rover: error: --start 100 is not before --end 50: the window holds nothing"]
    with pytest.raises(BadInput, match=r"--start/--end hold none of its 442 sensor messages \(it spans 2\.0 s"):
        convert([bag], out, setup=setup, start=100, truth=truth)
    assert not out.exists()
    convert([bag], out, setup=setup, start=0.5, end=1.0, truth=truth)
    poses = [s for t, s, _d in read_bag(out) if t == "/groundtruth/pose"]
    bag_start = T0_NS + 1_000
    assert poses and min(poses) >= bag_start + 500_000_000 and max(poses) <= bag_start + 1_000_000_000
    assert len(poses) == 5


WIFI_MSG = """\
std_msgs/Header header
string ap_id
uint8[6] txmac
uint16 chan
uint16 n_sub
uint8 n_rows
uint8 n_cols
string bw
uint8 mcs
int32 rssi
uint16 fc
uint32 seq_num
float64[] csi_real
float64[] csi_imag
string rx_id
uint32 msg_id
"""
"""a CSI message of another project's (fields as WiROS's rf_msgs/msg/Wifi, with other types), named OTHER_CSI"""
OTHER_CSI = "other_msgs/msg/Csi"


def other_csi_bag(bag: Path, count: int = 50) -> Path:
    """A ROS 2 bag of `count` OTHER_CSI messages on /csi and an IMU on /imu/data."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(get_types_from_msg(WIFI_MSG, OTHER_CSI))
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        csi = writer.add_connection("/csi", OTHER_CSI, typestore=store)
        imu = writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=typestore)
        for i in range(count * 4):
            stamp = T0_NS + i * 5_000_000
            g = make("geometry_msgs/msg/Vector3", z=9.8)
            writer.write(
                imu, stamp, serialize(make("sensor_msgs/msg/Imu", header=header(stamp, "imu"), linear_acceleration=g))
            )
            if i % 4 == 0:
                wifi = store.types[OTHER_CSI]
                values = np.ones(64 * 4 * 4)
                msg = wifi(
                    header=header(stamp, "wifi"), ap_id="ap", txmac=np.arange(6, dtype=np.uint8), chan=36, n_sub=64,
                    n_rows=4, n_cols=4, bw="20", mcs=0, rssi=-40, fc=0, seq_num=i, csi_real=values, csi_imag=values,
                    rx_id="rx", msg_id=i,
                )  # fmt: skip
                writer.write(csi, stamp, store.serialize_cdr(msg, OTHER_CSI))
    return bag


def test_a_conversion_that_drops_every_csi_message_fails_and_writes_nothing(tmp_path):
    """A bag whose CSI topic holds another project's type: every CSI message is dropped, so the
    conversion fails naming the topic, its type and the count, exit 2, and nothing is written (not a
    dataset without CSI); an old output stays as it was."""
    bag = other_csi_bag(tmp_path / "bag")
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP + "topics: {csi: /csi, imu: /imu/data, odom: null}\n")
    out = tmp_path / "out.mcap"
    out.write_bytes(b"before")
    result = run_rover("convert", str(bag), "-o", str(out), "--setup", str(setup), "--force")
    assert result.returncode == 2, result.stderr
    assert result.stderr.splitlines() == [
        f"rover: error: {bag}: topic /csi ({OTHER_CSI}): every CSI message was dropped (50 undecodable); "
        "Rover reads rover_msgs/msg/CsiFrame (the CSI Tool's records): nothing written"
    ]
    assert out.read_bytes() == b"before"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag", "out.mcap", "setup.yaml"]


def test_a_bag_cut_while_being_written_says_where_it_ends_and_writes_nothing(tmp_path):
    """A ROS 2 bag whose MCAP file was cut (the recorder killed): one line saying the file ends early
    and at which byte, exit 2, no output."""
    bag = tmp_path / "bag"
    write_ros2_bag(bag, StoragePlugin.MCAP)
    setup = tmp_path / "setup.yaml"
    setup.write_text(SETUP)
    (mcap,) = bag.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    out = tmp_path / "out.mcap"
    result = run_rover("convert", str(bag), "-o", str(out), "--setup", str(setup))
    assert result.returncode == 2 and not out.exists()
    assert result.stderr.splitlines() == [
        f"rover: error: {mcap}: cannot read as a ROS bag: the file ends early, at byte {len(data) // 2:,} (cut while "
        "it was being written? a finished MCAP file ends with its magic bytes)"
    ]
