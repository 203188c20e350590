"""`dataset_recorder` and `rover record`: a live session written as a dataset `dataset_replay` plays back."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import yaml
from helpers import ROOT, T0_NS, run_rover
from mcap.reader import make_reader

from rover.drivers.dataset_recorder import DatasetRecorder, DatasetRecorderParams
from rover.drivers.replay import DatasetReplay, ReplayParams
from rover.formats.bag import BagReader
from rover.messages import Raw, deserialize, header, make, serialize
from rover.operator import Emit, RunContext, RunOutcome

RIG = """\
receiver:
  antenna_positions_m: [[0.0, 0.0], [0.0258, 0.0], [0.0129, 0.0223]]
  channel: 165
tags:
  - {id: 1, channel: 149}
  - {id: 2, channel: 153}
"""


def rig(stamp: int = 0):
    return make("rover_msgs/msg/RigSetup", header=header(stamp, "base_link"), setup_yaml=RIG)


def frame(stamp: int, channel: int = 0, fill: int = 1):
    return make(
        "rover_msgs/msg/CsiFrame",
        header=header(stamp, "base_link"),
        channel=channel,
        bfee=np.full(8, fill, dtype=np.uint8),
    )


def hop(stamp: int, channel: int):
    return make("rover_msgs/msg/ChannelHop", header=header(stamp, "base_link"), interface="wlan0", channel=channel)


def imu(stamp: int) -> Raw:
    return Raw("sensor_msgs/msg/Imu", serialize(make("sensor_msgs/msg/Imu", header=header(stamp, "imu_link"))))


def recorder(path: Path, command: str = "rover record live.yaml -o x.mcap") -> DatasetRecorder:
    op = DatasetRecorder(DatasetRecorderParams(path=str(path), command=command))
    op.context = RunContext(pipeline_file=str(ROOT / "pipelines" / "live.yaml"))
    return op


def test_live_frames_take_the_channel_tuned_at_their_stamp(tmp_path):
    path = tmp_path / "session.mcap"
    op = recorder(path)
    op.on_input("setup", rig(0), 0)
    for port, msg, stamp in [
        ("csi", frame(T0_NS), T0_NS),  # before any hop: the NIC's channel is unknown, kept as 0
        ("hops", hop(T0_NS + 1, 149), T0_NS + 1),
        ("csi", frame(T0_NS + 2), T0_NS + 2),
        ("imu", imu(T0_NS + 3), T0_NS + 3),
        ("hops", hop(T0_NS + 4, 153), T0_NS + 4),
        ("csi", frame(T0_NS + 5), T0_NS + 5),
        ("csi", frame(T0_NS + 6, channel=157), T0_NS + 6),  # labelled already: kept
    ]:
        op.on_input(port, msg, stamp)
    op.close()
    with BagReader(path) as bag:
        frames = [(m.log_time_ns, bag.decode(m, "rover_msgs/msg/CsiFrame").channel) for m in bag.messages(["/csi"])]
        summary = bag.summary()
        assert summary is not None
        topics = {c.topic: c.schema for c in summary.channels}
        metadata = bag.metadata()
    assert frames == [(T0_NS, 0), (T0_NS + 2, 149), (T0_NS + 5, 153), (T0_NS + 6, 157)]
    assert topics == {"/csi": "rover_msgs/msg/CsiFrame", "/imu/data": "sensor_msgs/msg/Imu"}
    stored = yaml.safe_load(metadata["rover.setup"]["yaml"])
    assert stored["topics"] == {"csi": "/csi", "imu": "/imu/data", "odom": "/odom"}
    assert stored["tags"] == yaml.safe_load(RIG)["tags"]
    provenance = metadata["rover.provenance"]
    assert provenance["command"] == "rover record live.yaml -o x.mcap"
    assert yaml.safe_load(provenance["sources"])[0]["path"].endswith("pipelines/live.yaml")
    assert yaml.safe_load(metadata["rover.record"]["yaml"]) == {
        "messages": {"/csi": 4, "/imu/data": 1},
        "late": {},
        "session": "complete",
    }


def test_a_late_message_is_kept_flagged_and_counted(tmp_path):
    path = tmp_path / "session.mcap"
    op = recorder(path)
    op.on_input("setup", rig(0), 0)
    for stamp in (10, 20, 30):
        op.on_input("imu", imu(T0_NS + stamp), T0_NS + stamp)
    op.on_input("csi", frame(T0_NS + 25, channel=149), T0_NS + 25)  # its producer fell behind
    op.on_input("imu", imu(T0_NS + 40), T0_NS + 40)
    op.close(RunOutcome("interrupted", "stopped by SIGINT"))
    with path.open("rb") as f:
        reader = make_reader(f)
        stored = [(c.topic, m.log_time, m.publish_time) for _s, c, m in reader.iter_messages(log_time_order=False)]
    with BagReader(path) as bag:
        record = yaml.safe_load(bag.metadata()["rover.record"]["yaml"])
    assert ("/csi", T0_NS + 25, T0_NS + 30) in stored  # logged at its stamp, published at the latest before it
    assert all(log == pub for topic, log, pub in stored if topic != "/csi")
    assert record["late"] == {"/csi": 1}
    assert record["session"] == "interrupted"
    shown = run_rover("info", str(path), check=True).stdout
    assert "Recorded live (interrupted session); late messages: /csi 1" in shown.splitlines()


def test_the_recording_replays_as_recorded(tmp_path):
    path = tmp_path / "session.mcap"
    op = recorder(path)
    op.on_input("setup", rig(0), 0)
    op.on_input("hops", hop(T0_NS, 153), T0_NS)
    sent = [imu(T0_NS + 5 * k) for k in range(1, 5)]
    for k, sample in enumerate(sent, start=1):
        op.on_input("imu", sample, T0_NS + 5 * k)
        op.on_input("csi", frame(T0_NS + 5 * k + 1, fill=k), T0_NS + 5 * k + 1)
    op.close()
    replay = DatasetReplay(ReplayParams(path=str(path)))
    played = [item for item in replay.run(threading.Event()) if isinstance(item, Emit)]
    ports = [item.port for item in played]
    assert ports[0] == "setup" and ports[1:] == ["imu", "csi"] * 4
    assert [e.msg.payload for e in played if e.port == "imu"] == [s.payload for s in sent]
    frames = [deserialize(e.msg.payload, "rover_msgs/msg/CsiFrame") for e in played if e.port == "csi"]
    assert [(f.channel, int(f.bfee[0])) for f in frames] == [(153, k) for k in range(1, 5)]
    assert played[0].msg.setup_yaml.startswith("receiver:")


def test_messages_before_the_rig_wait_for_it(tmp_path):
    path = tmp_path / "session.mcap"
    op = recorder(path)
    op.on_input("imu", imu(T0_NS), T0_NS)
    assert not path.exists()
    op.on_input("setup", rig(T0_NS + 1), T0_NS + 1)
    op.close()
    with BagReader(path) as bag:
        assert [m.topic for m in bag.messages()] == ["/imu/data"]


def test_no_rig_no_file_and_a_failed_run_leaves_nothing(tmp_path, caplog):
    path = tmp_path / "session.mcap"
    op = recorder(path)
    op.on_input("imu", imu(T0_NS), T0_NS)
    op.close(RunOutcome("interrupted", "stopped by SIGINT"))
    assert not path.exists()
    assert "no rig description arrived (1 messages)" in caplog.text
    op = recorder(path)
    op.on_input("setup", rig(0), 0)
    op.on_input("imu", imu(T0_NS), T0_NS)
    op.close(RunOutcome("failed", "boom"))
    assert list(tmp_path.iterdir()) == []


def test_without_a_path_nothing_is_recorded(tmp_path):
    op = DatasetRecorder(DatasetRecorderParams())
    op.on_input("setup", rig(0), 0)
    op.on_input("imu", imu(T0_NS), T0_NS)
    op.close()
    assert list(tmp_path.iterdir()) == []


def test_record_names_where_the_recorder_runs(tmp_path):
    live = ROOT / "pipelines" / "live.yaml"
    proc = run_rover("record", str(live), "--host", "laptop", "-o", str(tmp_path / "x.mcap"))
    assert proc.returncode == 2
    where = "no dataset_recorder operator on host laptop ('dataset' runs on host nuc: record there)"
    assert proc.stderr.strip().splitlines() == [f"rover: error: {live}: {where}"]


def test_record_refuses_an_existing_dataset_and_a_pipeline_without_recorder(tmp_path):
    existing = tmp_path / "x.mcap"
    existing.write_bytes(b"keep")
    live = str(ROOT / "pipelines" / "live.yaml")
    proc = run_rover("record", live, "--host", "nuc", "-o", str(existing))
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"rover: error: {existing}: exists (use --force to replace it)"
    assert existing.read_bytes() == b"keep"
    default = str(ROOT / "pipeline.yaml")
    proc = run_rover("record", default, "-o", str(tmp_path / "y.mcap"))
    assert proc.returncode == 2
    assert "no dataset_recorder operator: add one wired to the CSI, IMU, odometry and rig sources" in proc.stderr
