"""WiROS's bearings (rover.formats.wiros_bearings, `dataset_replay`'s `bearings` given a bag): ROS 1
and ROS 2 bags of rf_msgs/msg/Bearing written here with rosbags from the message's public field
list (the definition below, not Rover's copy)."""

from __future__ import annotations

import math
import threading
from pathlib import Path

import numpy as np
import pytest
from helpers import T0_NS
from rosbags.rosbag1 import Writer as Ros1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Ros2Writer
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from test_replay import SETUP

from rover.drivers.replay import DatasetReplay, ReplayParams
from rover.errors import BadInput
from rover.formats.bag import BagWriter
from rover.formats.wiros_bearings import read_wiros_bearings
from rover.messages import header, make
from rover.operator import Emit

BEARING_MSG = """\
std_msgs/Header header
uint8 ap_id
uint8[] txmac
uint8 n_tx
uint8 n_rx
uint32 seq
int32[] rssi
float64[] aoa
float64[] aod
"""
"""rf_msgs/msg/Bearing as its public field list gives it"""
TAG_7 = bytes.fromhex("0a1b00000007")
TAG_9 = bytes.fromhex("0a1b00000009")
STD = math.radians(8.0)


def store():
    s = get_typestore(Stores.ROS2_HUMBLE)
    s.register(get_types_from_msg(BEARING_MSG, "rf_msgs/msg/Bearing"))
    return s


def bearing(s, stamp_ns: int, mac: bytes, aoa: list[float]):
    cls = s.types["rf_msgs/msg/Bearing"]
    header_cls, time_cls = s.types["std_msgs/msg/Header"], s.types["builtin_interfaces/msg/Time"]
    return cls(
        header=header_cls(stamp=time_cls(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id="asus"),
        ap_id=0,
        txmac=np.frombuffer(mac, np.uint8),
        n_tx=len(aoa),
        n_rx=4,
        seq=stamp_ns % 1000,
        rssi=np.full(4, -45, np.int32),
        aoa=np.array(aoa, np.float64),
        aod=np.zeros(len(aoa)),
    )


ROWS = [
    # (seconds after T0, MAC, aoa per transmit antenna in the radio's frame)
    (0.30, TAG_9, [2.0, 2.0]),
    (0.10, TAG_7, [0.5]),  # stamped earlier than it was logged: sorted by stamp
    (0.20, TAG_7, [3.1, -3.1]),  # across +-pi: the circular mean is pi, not 0
    (0.40, TAG_7, [math.nan]),  # no angle: dropped and counted
    (0.50, bytes.fromhex("0a1b0000"), [1.0]),  # a MAC of 4 bytes: dropped and counted
    (0.60, TAG_9, [-1.0, math.nan, -1.2]),
]


def write(path: Path, rows=ROWS, ros1: bool = False, topic: str = "/bearing") -> Path:
    s = store()
    writer = Ros1Writer(path) if ros1 else Ros2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        conn = writer.add_connection(topic, "rf_msgs/msg/Bearing", typestore=s)
        for k, (after_s, mac, aoa) in enumerate(rows):
            msg = bearing(s, T0_NS + round(after_s * 1e9), mac, aoa)
            data = s.serialize_ros1(msg, "rf_msgs/msg/Bearing") if ros1 else s.serialize_cdr(msg, "rf_msgs/msg/Bearing")
            writer.write(conn, T0_NS + k * 100_000_000, data)
    return path


@pytest.mark.parametrize("ros1", [True, False], ids=["ROS 1", "ROS 2 MCAP"])
def test_a_bags_bearings_are_the_robots_by_stamp_with_their_tag_from_the_mac(tmp_path, ros1):
    """Each bearing: its header's stamp, the tag the MAC's last four bytes name, the circular mean of
    its finite angles turned by the radio's yaw on the robot, the std given; what has no angle or
    no MAC is counted, not kept."""
    bag = write(tmp_path / ("b.bag" if ros1 else "b"), ros1=ros1)
    b, dropped = read_wiros_bearings(bag, STD, radio_yaw_rad=math.pi / 2)
    assert list((b.stamp_ns - T0_NS) // 10**7) == [10, 20, 30, 60]
    assert list(b.tag) == [7, 7, 9, 9]
    expected = np.array([0.5, math.pi, 2.0, -1.1]) + math.pi / 2
    np.testing.assert_allclose(np.angle(np.exp(1j * (b.angle_rad - expected))), 0.0, atol=1e-12)
    assert np.all(np.abs(b.angle_rad) <= math.pi)
    assert np.all(b.std_rad == STD)
    assert sum(dropped.values()) == 2
    assert {k.split(" ", 1)[1] for k in dropped} == {
        "bearings without a finite aoa",
        "bearings whose txmac is not 6 bytes",
    }


def test_transmitters_sharing_their_last_four_bytes_are_refused(tmp_path):
    rows = [(0.1, TAG_7, [0.1]), (0.2, bytes.fromhex("ffff00000007"), [0.2])]
    shared = "0a:1b:00:00:00:07 and ff:ff:00:00:00:07 share their last 4 bytes, the tag id 7"
    with pytest.raises(BadInput, match=shared):
        read_wiros_bearings(write(tmp_path / "b", rows), STD)


def test_a_bag_without_a_usable_bearing_names_the_file_and_topic(tmp_path):
    bag = write(tmp_path / "b", [(0.1, TAG_7, [math.nan])], topic="/aoa")
    with pytest.raises(BadInput, match=r"/aoa: no bearing with a transmitter and a finite angle \(1 messages\)"):
        read_wiros_bearings(bag, STD)
    with pytest.raises(BadInput, match=r"no rf_msgs/msg/Bearing on /bearing; topics there: /aoa"):
        read_wiros_bearings(bag, STD, topic="/bearing")


def test_a_bag_of_bearings_leaves_the_replay_as_its_csv_would(tmp_path):
    """Given the same bearings as a bag or as a CSV, the replay sends the same Aoa messages at the
    same places among the dataset's: the SLAM cannot tell them apart (the CSV's run end to end:
    test_bearings_pipeline.py)."""
    dataset = tmp_path / "d.mcap"
    with BagWriter(dataset, metadata={"rover.setup": {"yaml": SETUP}}) as bag:
        for i in range(10):
            stamp = T0_NS + i * 100_000_000
            bag.write("/imu/data", make("sensor_msgs/msg/Imu", header=header(stamp)), stamp)
    bearings = write(tmp_path / "b")
    yaw_deg = 30.0
    b, _ = read_wiros_bearings(bearings, STD, math.radians(yaw_deg))
    csv = tmp_path / "b.csv"
    csv.write_text(
        "time_s,tag,angle_deg,std_deg\n"
        + "".join(
            f"{s // 10**9}.{s % 10**9:09d},{t},{math.degrees(a)!r},8\n"
            for s, t, a in zip(b.stamp_ns, b.tag, b.angle_rad, strict=True)
        )
    )

    def sent(**kw) -> list[tuple[str, int | None, int, float, float]]:
        replay = DatasetReplay(ReplayParams(path=str(dataset), **kw))
        out = [i for i in replay.run(threading.Event()) if isinstance(i, Emit)]
        return [
            (i.port, i.stamp_ns, int(i.msg.tag_id), round(i.msg.angle_rad, 12), round(i.msg.std_rad, 12))
            if i.port == "aoa"
            else (i.port, i.stamp_ns, -1, 0.0, 0.0)
            for i in out
        ]

    from_bag = sent(bearings=str(bearings), bearing_std_deg=8.0, radio_yaw_deg=yaw_deg)
    assert [p for p, *_ in from_bag].count("aoa") == 4
    assert from_bag == sent(bearings=str(csv))
