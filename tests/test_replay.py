"""`dataset_replay`: every message once, in order, as raw CDR; the rig description first; paced on request."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import pytest
from helpers import T0_NS, read_bag, run_rover, write_imu_dataset
from mcap.reader import make_reader

from rover.cli.app import main
from rover.drivers.replay import DatasetReplay, ReplayParams
from rover.errors import BadInput
from rover.formats.bag import BagWriter
from rover.formats.bearings_csv import HEADER
from rover.messages import Raw, header, make
from rover.operator import Emit
from rover.pipeline.params import ParamValueError

SETUP = "excitation: {channel: 165}\ntags: [{id: 1, channel: 149}]\n"


def test_replays_everything_in_log_order_with_the_setup_first(tmp_path):
    path = tmp_path / "d.mcap"
    with BagWriter(path, metadata={"rover.setup": {"yaml": SETUP}}) as bag:
        for i in range(50):
            stamp = T0_NS + i * 10_000_000
            bag.write("/imu/data", make("sensor_msgs/msg/Imu", header=header(stamp)), stamp)
            if i % 10 == 0:
                bag.write("/other", make("std_msgs/msg/String", data="ignored"), stamp)
    items = list(DatasetReplay(ReplayParams(path=str(path))).run(threading.Event()))
    assert isinstance(items[0], Emit) and items[0].port == "setup"
    assert items[0].msg.setup_yaml == SETUP and items[0].stamp_ns == T0_NS
    imu = [i for i in items if isinstance(i, Emit) and i.port == "imu"]
    assert len(imu) == 50 and all(isinstance(i.msg, Raw) for i in imu)
    assert [i.msg.payload for i in imu] == [d for t, _s, d in read_bag(path) if t == "/imu/data"]


def test_speed_paces_against_the_wall_clock(tmp_path):
    path = write_imu_dataset(tmp_path / "d.mcap", 200, imu_hz=200.0, odom_every=0)  # one second of data
    start = time.monotonic()
    n = sum(1 for _ in DatasetReplay(ReplayParams(path=str(path), speed=4.0)).run(threading.Event()))
    took = time.monotonic() - start
    assert n == 200
    assert 0.2 <= took < 1.0


def test_stop_ends_the_replay(tmp_path):
    path = write_imu_dataset(tmp_path / "d.mcap", 100, odom_every=0)
    stop = threading.Event()
    items = []
    for item in DatasetReplay(ReplayParams(path=str(path))).run(stop):
        items.append(item)
        if len(items) == 10:
            stop.set()
    assert len(items) == 10


def test_bad_datasets_are_bad_input(tmp_path):
    with pytest.raises(BadInput, match="no dataset given"):
        DatasetReplay(ReplayParams(path=""))
    with pytest.raises(BadInput, match="no such dataset file"):
        DatasetReplay(ReplayParams(path=str(tmp_path / "none.mcap")))
    with pytest.raises(BadInput, match=rf"{tmp_path}: is a folder, not a dataset: .* `rover convert {tmp_path} -o"):
        DatasetReplay(ReplayParams(path=str(tmp_path)))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(BadInput, match="not a readable MCAP dataset"):
        DatasetReplay(ReplayParams(path=str(junk)))
    wrong = tmp_path / "wrong.mcap"
    with BagWriter(wrong) as bag:
        bag.write("/imu/data", make("std_msgs/msg/String", data="x"), T0_NS)
    with pytest.raises(BadInput, match=r"topic /imu/data is std_msgs/msg/String \(cdr\), expected sensor_msgs/msg/Imu"):
        DatasetReplay(ReplayParams(path=str(wrong)))
    with pytest.raises(ParamValueError, match="speed: must be > 0, got 0.0"):
        ReplayParams(path=str(wrong), speed=0.0)


def test_speed_from_the_command_line(tmp_path):
    from helpers import run_rover

    path = write_imu_dataset(tmp_path / "d.mcap", 400, odom_every=0)
    proc = run_rover("run", "--dataset", str(path), "--speed", "20", "--output", str(tmp_path / "o"), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert run_rover("run", "--dataset", str(path), "--speed", "fast", cwd=tmp_path).returncode == 2


def corrupt_last_chunk(path: Path) -> Path:
    """Flip bytes in the middle of the file's last chunk; the chunks before it stay intact."""
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        chunks = summary.chunk_indexes
    assert len(chunks) >= 2
    data = bytearray(path.read_bytes())
    middle = chunks[-1].chunk_start_offset + chunks[-1].chunk_length // 2
    data[middle : middle + 16] = bytes(b ^ 0xFF for b in data[middle : middle + 16])
    path.write_bytes(data)
    return path


def test_run_of_a_six_byte_text_file_is_one_line(tmp_path, capsys):
    path = tmp_path / "six.mcap"
    path.write_text("hello\n")
    assert main(["run", "--dataset", str(path), "--output", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert (
        err
        == f"rover: error: {path}: not a readable MCAP dataset: not an MCAP file (no MCAP magic bytes at its start)\n"
    )


def test_a_corrupt_chunk_met_while_replaying_is_bad_input(tmp_path):
    path = corrupt_last_chunk(write_imu_dataset(tmp_path / "d.mcap", 6000, odom_every=0))
    replay = DatasetReplay(ReplayParams(path=str(path)))
    items = []
    with pytest.raises(BadInput, match=r"d\.mcap: not a readable MCAP dataset: corrupt "):
        for item in replay.run(threading.Event()):
            items.append(item)
    assert len(items) > 1000, "the intact chunks before the corrupt one are replayed"


def test_a_corrupt_chunk_ends_rover_run_with_status_2_and_one_line(tmp_path):
    from helpers import run_rover

    path = corrupt_last_chunk(write_imu_dataset(tmp_path / "d.mcap", 6000, odom_every=0))
    proc = run_rover("-q", "run", "--dataset", str(path), "--output", str(tmp_path / "out"), cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.startswith(f"rover: error: {path}: not a readable MCAP dataset: corrupt "), proc.stderr


def test_a_message_too_short_for_a_header_is_dropped_and_counted(tmp_path):
    path = tmp_path / "d.mcap"
    with BagWriter(path) as bag:
        for i in range(5):
            stamp = T0_NS + i * 10_000_000
            payload = Raw("sensor_msgs/msg/Imu", b"\x00\x01\x00\x00\x07") if i == 2 else None
            bag.write("/imu/data", payload or make("sensor_msgs/msg/Imu", header=header(stamp)), stamp)
    replay = DatasetReplay(ReplayParams(path=str(path)))
    items = list(replay.run(threading.Event()))
    assert [i.stamp_ns for i in items if isinstance(i, Emit)] == [T0_NS + i * 10_000_000 for i in (0, 1, 3, 4)]
    assert replay.drops == {"messages on /imu/data too short to carry a header": 1}


def test_bearings_from_a_csv_leave_on_aoa_in_stamp_order_among_the_datasets_messages(tmp_path):
    """A bearings file's rows, given out of order, leave sorted by time, each before the first
    dataset message stamped at or after it (those after the dataset's end last; those before its
    start dropped and counted), as one-candidate Aoa messages in the robot's frame."""
    path = tmp_path / "d.mcap"
    with BagWriter(path, metadata={"rover.setup": {"yaml": SETUP}}) as bag:
        for i in range(10):
            stamp = T0_NS + i * 100_000_000
            bag.write("/imu/data", make("sensor_msgs/msg/Imu", header=header(stamp)), stamp)
    csv = tmp_path / "bearings.csv"
    t0 = T0_NS / 1e9
    csv.write_text(
        "time_s,tag,angle_deg,std_deg\n"
        f"{t0 + 0.35:.9f},2,-90,5\n{t0 + 0.05:.9f},1,30,4\n{t0 + 0.3:.9f},1,31,4\n{t0 + 2.0:.9f},3,180,6\n"
        f"{t0 - 1.0:.9f},4,0,5\n"  # before the dataset: dropped and counted
    )
    replay = DatasetReplay(ReplayParams(path=str(path), bearings=str(csv)))
    items = list(replay.run(threading.Event()))
    assert replay.drops == {"bearings before the dataset's first message": 1}
    ports = [i.port for i in items if isinstance(i, Emit)]
    # IMU every 0.1 s from 0; bearings at 0.05, 0.3, 0.35 and 2.0 s
    assert ports == ["setup", "imu", "aoa", "imu", "imu", "aoa", "imu", "aoa", "imu", *["imu"] * 5, "aoa"]
    stamps = [i.stamp_ns for i in items if isinstance(i, Emit) and i.stamp_ns is not None]
    assert stamps == sorted(stamps)
    aoa = [i.msg for i in items if isinstance(i, Emit) and i.port == "aoa"]
    assert [a.tag_id for a in aoa] == [1, 1, 2, 3]
    assert [round(math.degrees(a.angle_rad)) for a in aoa] == [30, 31, -90, 180]
    assert all(list(a.candidate_angles_rad) == [a.angle_rad] and a.chosen == -1 for a in aoa)
    assert math.degrees(aoa[2].std_rad) == pytest.approx(5.0)


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("time,tag,angle,std\n1,1,0,1\n", "line 1: the header must be time_s,tag,angle_deg,std_deg"),
        ("time_s,tag,angle_deg,std_deg\n1,1,0,1\n2,1,zero,1\n", "line 3: not a number in '2,1,zero,1'"),
        ("time_s,tag,angle_deg,std_deg\n1,1,0,1\n2,1,0\n", f"line 3: 3 fields, expected 4 ({HEADER})"),
        ("time_s,tag,angle_deg,std_deg\n1,-1,0,1\n", "line 2: tag -1 is not a non-negative integer id"),
        ("time_s,tag,angle_deg,std_deg\n1,1,0,0\n", "line 2: std_deg 0 is not positive"),
        ("time_s,tag,angle_deg,std_deg\n1,1,nan,1\n", "line 2: a value that is not finite"),
        ("time_s,tag,angle_deg,std_deg\n", "no bearings after the header"),
    ],
    ids=["header", "word", "short row", "negative tag", "zero std", "nan", "empty"],
)
def test_a_bearings_file_that_breaks_the_format_is_refused_naming_its_line(tmp_path, text, why):
    dataset = write_imu_dataset(tmp_path / "d.mcap", 20)
    csv = tmp_path / "bearings.csv"
    csv.write_text(text)
    with pytest.raises(BadInput) as caught:
        DatasetReplay(ReplayParams(path=str(dataset), bearings=str(csv)))
    assert str(caught.value).startswith(str(csv)) and str(caught.value).endswith(why)


def test_run_of_a_folder_as_its_dataset_says_to_convert_it_in_one_line(tmp_path):
    """`rover run --dataset DIR` (a ROS 2 bag folder, say): exit 2, one line saying how it becomes a
    dataset, nothing written."""
    folder = tmp_path / "bag"
    folder.mkdir()
    out = tmp_path / "out"
    result = run_rover("run", "--dataset", str(folder), "--output", str(out))
    assert result.returncode == 2 and not out.exists()
    assert result.stderr.splitlines() == [
        f"rover: error: {folder}: is a folder, not a dataset: a ROS 2 bag or a recording folder becomes one "
        f"with `rover convert {folder} -o DATASET.mcap`"
    ]
