"""The command line's promise on bad input, for any bytes in any file a command reads: status 0,
or status 2 with error lines that name the file; never a traceback, never a file left half-written.

`rover.cli.main()` runs in-process, as a user's shell would run it, on files Hypothesis writes."""

from __future__ import annotations

import contextlib
import functools
import io
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from helpers import write_imu_dataset
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer

from rover.cli.app import main
from rover.formats.bag import BagReader
from rover.messages import ros2_msgdef

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

text_or_bytes = st.one_of(st.binary(max_size=400), st.text(max_size=400).map(lambda t: t.encode("utf-8")))


@functools.cache
def real_dataset() -> bytes:
    """A small real dataset (IMU and odometry) whose bytes the fuzzer cuts and flips."""
    with tempfile.TemporaryDirectory() as folder:
        return write_imu_dataset(Path(folder) / "imu.mcap", 300).read_bytes()


@functools.cache
def uncompressed_dataset() -> bytes:
    """The same messages in an MCAP without compression or CRCs, so that overwritten bytes reach
    the messages themselves instead of failing a chunk's decompression."""
    out = io.BytesIO()
    writer = Writer(out, compression=CompressionType.NONE, enable_crcs=False)
    writer.start(profile="ros2")
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "imu.mcap"
        path.write_bytes(real_dataset())
        channels: dict[str, int] = {}
        with BagReader(path) as bag:
            for m in bag.messages():
                if m.topic not in channels:
                    schema = writer.register_schema(m.schema, "ros2msg", ros2_msgdef(m.schema).encode())
                    channels[m.topic] = writer.register_channel(m.topic, "cdr", schema)
                writer.add_message(channels[m.topic], m.log_time_ns, m.data, m.log_time_ns)
    writer.finish()
    return out.getvalue()


def mutated() -> st.SearchStrategy[bytes]:
    """A real dataset (zstd chunks with CRCs, or plain) cut short, or with a few bytes overwritten."""
    return st.one_of(_mutated(real_dataset()), _mutated(uncompressed_dataset()))


def _mutated(data: bytes) -> st.SearchStrategy[bytes]:
    cut = st.integers(0, len(data)).map(lambda n: data[:n])
    flips = st.lists(st.tuples(st.integers(0, len(data) - 1), st.integers(0, 255)), min_size=1, max_size=8)
    return st.one_of(cut, flips.map(lambda fs: _flip(data, fs)))


def _flip(data: bytes, flips: list[tuple[int, int]]) -> bytes:
    out = bytearray(data)
    for at, value in flips:
        out[at] = value
    return bytes(out)


def run_cli(args: Callable[[Path], list[str]], files: dict[str, bytes]) -> tuple[int, list[str], list[str]]:
    """Write `files` into a fresh folder, run `rover ARGS` there; (status, stderr lines, files left)."""
    folder = Path(tempfile.mkdtemp(prefix="rover-contract-"))
    try:
        for name, data in files.items():
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            (folder / name).write_bytes(data)
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            status = main(["-q", *args(folder)])
        left = sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))
        return status, err.getvalue().splitlines(), left
    finally:
        shutil.rmtree(folder)


def assert_contract(status: int, lines: list[str], left: list[str], named: str) -> None:
    assert status in (0, 2), (status, lines)
    assert not any("Traceback" in line for line in lines), lines
    assert not [name for name in left if Path(name).name.startswith(".")], f"left behind: {left}"
    if status == 2:
        problems = [line for line in lines if not line.endswith("problems found") and line != "1 problem found"]
        assert problems, "status 2 without a message"
        assert all(named in line for line in problems), lines


@FUZZ
@given(data=text_or_bytes)
def test_check_on_any_file(data):
    assert_contract(*run_cli(lambda d: ["check", str(d / "p.yaml")], {"p.yaml": data}), named="p.yaml")


@FUZZ
@given(data=text_or_bytes)
def test_run_on_any_pipeline_file(data):
    assert_contract(
        *run_cli(lambda d: ["run", str(d / "p.yaml"), "--output", str(d / "out")], {"p.yaml": data}), "p.yaml"
    )


@FUZZ
@given(data=st.data())
def test_run_on_any_dataset_file(data):
    dataset = data.draw(st.one_of(text_or_bytes, mutated()))
    status, lines, left = run_cli(
        lambda d: ["run", "--dataset", str(d / "d.mcap"), "--output", str(d / "out")], {"d.mcap": dataset}
    )
    assert_contract(status, lines, left, "d.mcap")


@FUZZ
@given(data=st.data())
def test_info_on_any_file(data):
    dataset = data.draw(st.one_of(text_or_bytes, mutated()))
    assert_contract(*run_cli(lambda d: ["info", str(d / "d.mcap")], {"d.mcap": dataset}), named="d.mcap")


RUN_FILES = ("trajectory.tum", "tags.csv", "run.json", "results.mcap")


@FUZZ
@given(which=st.sampled_from(RUN_FILES), data=text_or_bytes)
def test_eval_on_a_run_folder_with_any_file(which, data):
    """A run folder whose files are sound except one, with truth given as a TUM file."""
    sound = {
        "run/trajectory.tum": b"1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n",
        "truth.tum": b"1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n",
        "run/tags.csv": b"id,channel,x,y,z,var_x,cov_xy,var_y\n1,149,1,1,0,0.01,0,0.01\n",
    }
    files = {**sound, f"run/{which}": data}
    assert_contract(*run_cli(lambda d: ["eval", str(d / "run"), "--truth", str(d / "truth.tum")], files), which)


@FUZZ
@given(data=text_or_bytes)
def test_eval_with_any_truth_file(data):
    files = {"run/trajectory.tum": b"1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n", "truth.tum": data}
    assert_contract(*run_cli(lambda d: ["eval", str(d / "run"), "--truth", str(d / "truth.tum")], files), "truth.tum")


SETUP = b"""\
receiver: {antenna_positions_m: [[0, 0], [0.0258, 0], [0.0129, -0.0223]]}
excitation: {channel: 165}
tags: [{id: 1, channel: 149}]
topics: {csi: null}
"""


@FUZZ
@given(data=st.data())
def test_convert_on_any_source_file(data):
    source = data.draw(st.one_of(text_or_bytes, mutated()))
    status, lines, left = run_cli(
        lambda d: ["convert", str(d / "src.mcap"), "--setup", str(d / "setup.yaml"), "-o", str(d / "o.mcap")],
        {"src.mcap": source, "setup.yaml": SETUP},
    )
    assert_contract(status, lines, left, "src.mcap")


@FUZZ
@given(which=st.sampled_from(["setup.yaml", "truth.tum", "tags.csv"]), data=text_or_bytes)
def test_convert_with_any_setup_truth_or_tags_file(which, data):
    files = {
        "src.mcap": real_dataset(),
        "setup.yaml": SETUP,
        "truth.tum": b"1.0 0 0 0 0 0 0 1\n",
        "tags.csv": b"id,channel,x,y,z\n1,149,1,1,0\n",
        which: data,
    }
    status, lines, left = run_cli(
        lambda d: [
            "convert",
            str(d / "src.mcap"),
            "--setup",
            str(d / "setup.yaml"),
            "--truth",
            str(d / "truth.tum"),
            "--tags",
            str(d / "tags.csv"),
            "-o",
            str(d / "o.mcap"),
        ],
        files,
    )
    assert_contract(status, lines, left, which)
