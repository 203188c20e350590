"""`recorder`: a ROS 2 MCAP that appears only when complete, and is dropped when the run failed."""

from __future__ import annotations

from typing import Any

import pytest
from helpers import T0_NS, read_bag
from rosbags.highlevel import AnyReader

from rover.drivers.recorder import Recorder, RecorderParams
from rover.errors import BadInput
from rover.formats.bag import BagWriter
from rover.messages import Raw, header, make, serialize
from rover.operator import COMPLETE, RunOutcome


def imu(i: int) -> Raw:
    return Raw("sensor_msgs/msg/Imu", serialize(make("sensor_msgs/msg/Imu", header=header(T0_NS + i))))


def test_writes_a_ros2_bag_other_tools_read(tmp_path):
    rec = Recorder(RecorderParams(out=str(tmp_path), topics={"imu": "/imu/data"}))
    rec.start()
    for i in range(5):
        rec.on_input("imu", imu(i), T0_NS + i)
    rec.on_input("tags", Raw("std_msgs/msg/String", serialize(make("std_msgs/msg/String", data="x"))), T0_NS + 9)
    rec.close()
    assert not (tmp_path / "results.mcap").exists(), "staged until the run's end"
    rec.report(COMPLETE)
    path = tmp_path / "results.mcap"
    assert [(t, s) for t, s, _ in read_bag(path)] == [("/imu/data", T0_NS + i) for i in range(5)] + [
        ("/tags", T0_NS + 9)
    ]
    with AnyReader([path]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
        assert topics == {"/imu/data": "sensor_msgs/msg/Imu", "/tags": "std_msgs/msg/String"}
        msgs: list[Any] = [reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages()]
        assert msgs[-1].data == "x"
    assert [p.name for p in tmp_path.iterdir()] == ["results.mcap"], "no lock, no staging folder left"


def earlier_recording(folder) -> bytes:
    """An earlier run's results.mcap in `folder` (one IMU sample), as the recorder wrote it; its bytes."""
    rec = Recorder(RecorderParams(out=str(folder)))
    rec.start()
    rec.on_input("imu", imu(7), T0_NS)
    rec.close()
    rec.report(COMPLETE)
    return (folder / "results.mcap").read_bytes()


def test_a_failed_run_leaves_the_earlier_file_as_it_was(tmp_path):
    earlier = earlier_recording(tmp_path)
    rec = Recorder(RecorderParams(out=str(tmp_path)))
    rec.start()
    rec.on_input("imu", imu(0), T0_NS)
    rec.close(RunOutcome("failed", "boom"))
    rec.report(RunOutcome("failed", "boom"))
    assert [p.name for p in tmp_path.iterdir()] == ["results.mcap"]
    assert (tmp_path / "results.mcap").read_bytes() == earlier


def test_a_failed_run_into_a_new_folder_leaves_no_folder(tmp_path):
    rec = Recorder(RecorderParams(out=str(tmp_path / "new")))
    rec.start()
    rec.close(RunOutcome("failed", "boom"))
    rec.report(RunOutcome("failed", "boom"))
    assert list(tmp_path.iterdir()) == []


def test_a_run_replaces_the_earlier_file_and_an_empty_run_writes_an_empty_bag(tmp_path):
    earlier = earlier_recording(tmp_path)
    rec = Recorder(RecorderParams(out=str(tmp_path)))
    rec.start()
    assert (tmp_path / "results.mcap").read_bytes() == earlier, "nothing removed at the start"
    rec.close()
    rec.report(COMPLETE)
    assert read_bag(tmp_path / "results.mcap") == []


def test_a_file_no_earlier_run_wrote_is_never_replaced(tmp_path):
    """A file of the recording's name that is not an earlier run's (no `rover.results` record, not
    listed in the folder's run.json): refused at the start, the file as it was, nothing left behind;
    listed in run.json it is an earlier run's and may be replaced."""
    (tmp_path / "results.mcap").write_bytes(b"a dataset, or anything of the user's")
    with pytest.raises(BadInput, match=r"results\.mcap: this run would replace it, and no earlier run wrote it"):
        Recorder(RecorderParams(out=str(tmp_path))).start()
    assert [p.name for p in tmp_path.iterdir()] == ["results.mcap"]
    (tmp_path / "run.json").write_text('{"status": "complete", "files": ["results.mcap"]}')
    rec = Recorder(RecorderParams(out=str(tmp_path)))
    rec.start()
    rec.close()
    rec.report(COMPLETE)
    assert read_bag(tmp_path / "results.mcap") == []


def test_an_older_runs_recording_is_replaced_and_a_dataset_beside_a_run_json_is_not(tmp_path):
    """In a run's folder (it has a run.json), an MCAP file without the `rover.results` record is an
    older Rover's recording when it carries no dataset's records, and is replaced; a dataset (its
    `rover.setup` record) is refused, the file as it was."""
    (tmp_path / "run.json").write_text('{"status": "complete"}')
    with BagWriter(tmp_path / "results.mcap") as bag:  # a recording, as written before the record
        bag.write("/imu", imu(0), T0_NS)
    rec = Recorder(RecorderParams(out=str(tmp_path)))
    rec.start()
    rec.close()
    rec.report(COMPLETE)
    assert read_bag(tmp_path / "results.mcap") == []
    with BagWriter(tmp_path / "results.mcap", metadata={"rover.setup": {"yaml": "tags: []"}}) as bag:
        bag.write("/imu", imu(0), T0_NS)
    before = (tmp_path / "results.mcap").read_bytes()
    with pytest.raises(BadInput, match="no earlier run wrote it"):
        Recorder(RecorderParams(out=str(tmp_path))).start()
    assert (tmp_path / "results.mcap").read_bytes() == before


def test_a_port_mapped_to_no_topic_is_not_recorded(tmp_path):
    rec = Recorder(RecorderParams(out=str(tmp_path), topics={"timing": ""}))
    rec.start()
    rec.on_input("timing", imu(0), T0_NS)
    rec.on_input("imu", imu(1), T0_NS + 1)
    rec.close()
    rec.report(COMPLETE)
    assert [t for t, _s, _ in read_bag(tmp_path / "results.mcap")] == ["/imu"]


def test_a_run_that_fails_after_the_file_was_finished_leaves_it_out(tmp_path):
    rec = Recorder(RecorderParams(out=str(tmp_path)))
    rec.start()
    rec.on_input("imu", imu(0), T0_NS)
    rec.close()
    rec.report(RunOutcome("failed", "another output failed"))
    assert list(tmp_path.iterdir()) == []
