"""Every file reader, on any bytes: a result or a one-line `BadInput` naming the file, never another exception.

The MCAP readers also get a real small dataset with bytes flipped or cut off, so that the damage
lands in its header, chunk, summary and footer rather than only before the magic bytes.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from helpers import T0_NS
from hypothesis import given, settings
from hypothesis import strategies as st

from rover.datasets.info import dataset_info
from rover.drivers.replay import DatasetReplay, ReplayParams
from rover.errors import BadInput
from rover.formats import run_dir
from rover.formats.bag import MAGIC, BagReader, BagWriter
from rover.formats.truth import read_tags_csv, read_tum
from rover.messages import header, make

FUZZ = settings(max_examples=200, deadline=None)

SETUP = (
    "receiver: {antenna_positions_m: [[0, 0], [0.0258, 0]]}\nexcitation: {channel: 165}\n"
    "tags: [{id: 1, channel: 149}]\n"
)
TAGS_CSV = "id,channel,x,y,z,nlos\n1,149,2.0,3.0,0,0\n"
TUM = "".join(f"{1_700_000_000 + i}.5 {i}.0 0 0 0 0 0 1\n" for i in range(5))
RUN_TAGS = "id,channel,x,y,z,var_x,cov_xy,var_y\n1,149,2.1,3.0,0,0.01,0,0.01\n2,153,,,,1,0,1\n"


def expect_result_or_bad_input(read: Callable[[], Any], name: str) -> None:
    """`read()` returns, or raises BadInput whose one-line message names `name`."""
    try:
        read()
    except BadInput as exc:
        message = str(exc)
        assert name in message, message
        assert "\n" not in message, message


def tag_array(stamp: int) -> Any:
    tag = make(
        "rover_msgs/msg/Tag",
        id=1,
        channel=149,
        position=make("geometry_msgs/msg/Point", x=2.0, y=3.0),
        observable=True,
    )
    return make("rover_msgs/msg/TagArray", header=header(stamp, "world"), tags=[tag])


@pytest.fixture(scope="module")
def real(tmp_path_factory) -> Path:
    """A small dataset with every topic the readers look at."""
    path = tmp_path_factory.mktemp("fuzz") / "real.mcap"
    metadata = {"rover.setup": {"yaml": SETUP}, "rover.truth": {"tags_csv": TAGS_CSV}}
    with BagWriter(path, metadata=metadata) as bag:
        for i in range(40):
            stamp = T0_NS + i * 50_000_000
            bag.write("/imu/data", make("sensor_msgs/msg/Imu", header=header(stamp, "imu_link")), stamp)
            bag.write("/csi", make("rover_msgs/msg/CsiFrame", header=header(stamp), channel=149 + 4 * (i % 2)), stamp)
            pose = make("geometry_msgs/msg/PoseStamped", header=header(stamp, "world"))
            pose.pose.position.x, pose.pose.orientation.w = 0.01 * i, 1.0
            bag.write("/groundtruth/pose", pose, stamp)
            aoa = make("rover_msgs/msg/Aoa", header=header(stamp, "base_link"), tag_id=1, angle_rad=0.3, std_rad=0.1)
            bag.write("/rover/aoa", aoa, stamp)
            if i % 10 == 0:
                bag.write("/groundtruth/tags", tag_array(stamp), stamp)
                bag.write("/rover/tags", tag_array(stamp), stamp)
    return path


def damaged(data: bytes) -> st.SearchStrategy[bytes]:
    """`data` cut short, with bytes flipped, or with a stretch overwritten."""
    n = len(data)

    def flip(changes: list[tuple[int, int]]) -> bytes:
        out = bytearray(data)
        for at, mask in changes:
            out[at] ^= mask
        return bytes(out)

    def overwrite(args: tuple[int, bytes]) -> bytes:
        at, junk = args
        return data[:at] + junk + data[at + len(junk) :]

    return st.one_of(
        st.integers(0, n - 1).map(lambda cut: data[:cut]),
        st.lists(st.tuples(st.integers(0, n - 1), st.integers(1, 255)), min_size=1, max_size=8).map(flip),
        st.tuples(st.integers(0, n - 1), st.binary(min_size=1, max_size=64)).map(overwrite),
    )


ANY_MCAP = st.one_of(
    st.binary(max_size=200),
    st.binary(max_size=200).map(lambda b: MAGIC + b),
    st.binary(max_size=200).map(lambda b: MAGIC + b + MAGIC),
)


@pytest.fixture(scope="module")
def place(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("examples")


# ---------------------------------------------------------------------------------------------
# Text files

NUMBERISH = st.text(alphabet="0123456789.-+eE naif,#\t\n\r\x00\xff", max_size=200)


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), NUMBERISH.map(str.encode)))
def test_read_tum_of_any_bytes(place, data):
    path = place / "any.tum"
    path.write_bytes(data)
    expect_result_or_bad_input(lambda: read_tum(path), "any.tum")


@FUZZ
@given(data=st.one_of(st.binary(max_size=300), NUMBERISH.map(lambda t: ("id,channel,x,y,z,nlos\n" + t).encode())))
def test_read_tags_csv_of_any_bytes(place, data):
    path = place / "any.csv"
    path.write_bytes(data)
    expect_result_or_bad_input(lambda: read_tags_csv(path), "any.csv")


RUN_FILES = {"trajectory.tum": TUM, "trajectory_live.tum": TUM, "tags.csv": RUN_TAGS}


def write_run(folder: Path, dataset: bytes) -> None:
    folder.mkdir(exist_ok=True)
    for name, text in RUN_FILES.items():
        (folder / name).write_text(text)
    (folder / "results.mcap").write_bytes(dataset)
    (folder / run_dir.RUN_FILE).write_text(json.dumps({"dataset": str(folder / "results.mcap")}))


@FUZZ
@given(
    name=st.sampled_from(["trajectory.tum", "trajectory_live.tum", "tags.csv", "results.mcap"]),
    data=st.one_of(st.binary(max_size=300), NUMBERISH.map(str.encode), ANY_MCAP),
)
def test_load_run_with_any_bytes_in_one_file(place, real, name, data):
    folder = place / "run"
    write_run(folder, real.read_bytes())
    (folder / name).write_bytes(data)
    expect_result_or_bad_input(lambda: run_dir.load_run(folder), name)


@FUZZ
@given(data=st.data())
def test_load_run_with_a_damaged_results_mcap(place, real, data):
    folder = place / "run-damaged"
    write_run(folder, real.read_bytes())
    (folder / "results.mcap").write_bytes(data.draw(damaged(real.read_bytes())))
    expect_result_or_bad_input(lambda: run_dir.load_run(folder), "results.mcap")


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.sampled_from(["dataset", "x"]), inner, max_size=2),
    max_leaves=6,
)


@FUZZ
@given(data=st.one_of(st.binary(max_size=200), JSON.map(lambda v: json.dumps(v).encode())))
def test_run_description_of_any_run_json(place, data):
    folder = place / "run-json"
    folder.mkdir(exist_ok=True)
    (folder / run_dir.RUN_FILE).write_bytes(data)
    expect_result_or_bad_input(lambda: run_dir.read_run_description(folder), run_dir.RUN_FILE)


@FUZZ
@given(
    suffix=st.sampled_from([".tum", ".mcap"]),
    data=st.one_of(st.binary(max_size=300), NUMBERISH.map(str.encode), ANY_MCAP),
    tags=st.none() | st.binary(max_size=100),
)
def test_load_truth_of_any_bytes(place, suffix, data, tags):
    source = place / f"truth{suffix}"
    source.write_bytes(data)
    tags_path = place / "truth_tags.csv"
    if tags is not None:
        tags_path.write_bytes(b"id,channel,x,y,z\n" + tags)
    try:
        run_dir.load_truth(source, tags_path if tags is not None else None)
    except BadInput as exc:
        assert source.name in str(exc) or tags_path.name in str(exc), str(exc)
        assert "\n" not in str(exc)


# ---------------------------------------------------------------------------------------------
# MCAP files


def read_everything(path: Path) -> None:
    """Everything the readers of a dataset do: summary, metadata, messages in both orders, decoding."""
    with BagReader(path) as bag:
        summary = bag.summary()
        bag.metadata()
        types = {c.topic: c.schema for c in summary.channels} if summary else {}
        for message in bag.messages():
            if message.topic in types and types[message.topic] in ("rover_msgs/msg/TagArray", "rover_msgs/msg/Aoa"):
                bag.decode(message, types[message.topic])
        for _ in bag.messages(["/csi", "/imu/data"], log_time_order=False):
            pass


@FUZZ
@given(data=ANY_MCAP)
def test_bag_reader_of_any_bytes(place, data):
    path = place / "any.mcap"
    path.write_bytes(data)
    expect_result_or_bad_input(lambda: read_everything(path), "any.mcap")


@FUZZ
@given(data=st.data())
def test_bag_reader_of_a_damaged_dataset(place, real, data):
    path = place / "damaged.mcap"
    path.write_bytes(data.draw(damaged(real.read_bytes())))
    expect_result_or_bad_input(lambda: read_everything(path), "damaged.mcap")


@FUZZ
@given(data=st.data())
def test_truth_and_info_of_a_damaged_dataset(place, real, data):
    path = place / "truth.mcap"
    path.write_bytes(data.draw(damaged(real.read_bytes())))
    expect_result_or_bad_input(lambda: run_dir.load_truth(path), "truth.mcap")
    expect_result_or_bad_input(lambda: dataset_info(path), "truth.mcap")


@FUZZ
@given(data=ANY_MCAP)
def test_info_of_any_bytes(place, data):
    path = place / "info.mcap"
    path.write_bytes(data)
    expect_result_or_bad_input(lambda: dataset_info(path), "info.mcap")


@settings(max_examples=100, deadline=None)
@given(data=st.data())
def test_replay_of_a_damaged_dataset(place, real, data):
    path = place / "replay.mcap"
    path.write_bytes(data.draw(damaged(real.read_bytes())))
    expect_result_or_bad_input(
        lambda: list(DatasetReplay(ReplayParams(path=str(path))).run(threading.Event())), "replay.mcap"
    )


def test_the_undamaged_dataset_reads_whole(place, real):
    """The fixture itself is valid, so the damage tests start from a file every reader accepts."""
    path = place / "whole.mcap"
    path.write_bytes(real.read_bytes())
    read_everything(path)
    truth = run_dir.load_truth(path)
    assert truth is not None and len(truth.trajectory.stamp_ns) == 40 and set(truth.tags) == {1}
    assert dataset_info(path).csi_packets_per_channel == {149: 20, 153: 20}
    folder = place / "whole-run"
    write_run(folder, real.read_bytes())
    run = run_dir.load_run(folder)
    assert len(run.aoa[0]) == 40 and len(run.tag_history[0]) == 4
