"""The MCAP reader: messages in log-time or file order, metadata, summary, and BadInput for unreadable files."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import T0_NS
from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from rover.errors import BadInput, Interrupted
from rover.formats.bag import BagMessage, BagReader, BagWriter, iter_messages, read_metadata
from rover.messages import deserialize, header, make, serialize


def write(path, stamps_by_topic):
    with BagWriter(path, metadata={"rover.setup": {"yaml": "x: 1\n"}, "other": {"a": "b"}}) as bag:
        for topic, stamp in stamps_by_topic:
            bag.write(topic, make("std_msgs/msg/Header", stamp=header(stamp).stamp, frame_id=topic), stamp)
    return path


def test_messages_in_log_time_or_file_order(tmp_path):
    path = write(tmp_path / "d.mcap", [("/a", T0_NS + 2), ("/b", T0_NS + 1), ("/a", T0_NS + 3), ("/b", T0_NS)])
    ordered = list(iter_messages(path))
    assert [(m.topic, m.log_time_ns) for m in ordered] == [
        ("/b", T0_NS),
        ("/b", T0_NS + 1),
        ("/a", T0_NS + 2),
        ("/a", T0_NS + 3),
    ]
    assert all(isinstance(m, BagMessage) and m.schema == "std_msgs/msg/Header" for m in ordered)
    assert deserialize(ordered[0].data, ordered[0].schema).frame_id == "/b"
    in_file = [m.log_time_ns - T0_NS for m in iter_messages(path, log_time_order=False)]
    assert in_file == [2, 1, 3, 0]
    assert [m.log_time_ns - T0_NS for m in iter_messages(path, ["/a"])] == [2, 3]
    topic, stamp, schema, data = ordered[0]
    assert (topic, stamp, schema, data) == tuple(ordered[0])


def test_metadata_and_summary(tmp_path):
    path = write(tmp_path / "d.mcap", [("/a", T0_NS), ("/a", T0_NS + 5), ("/b", T0_NS + 9)])
    assert read_metadata(path) == {"rover.setup": {"yaml": "x: 1\n"}, "other": {"a": "b"}}
    with BagReader(path) as bag:
        summary = bag.summary()
        assert summary is not None and summary.statistics is not None
        assert [(c.topic, c.schema, c.encoding, c.count) for c in summary.channels] == [
            ("/a", "std_msgs/msg/Header", "cdr", 2),
            ("/b", "std_msgs/msg/Header", "cdr", 1),
        ]
        assert (summary.statistics.message_count, summary.statistics.start_ns, summary.statistics.end_ns) == (
            3,
            T0_NS,
            T0_NS + 9,
        )
        assert len(list(bag.messages())) == 3


def test_unreadable_files_are_bad_input_naming_the_file(tmp_path):
    with pytest.raises(BadInput, match=r"none\.mcap: cannot read: .*No such file"):
        list(iter_messages(tmp_path / "none.mcap", failure="cannot read"))
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(BadInput, match=r"junk\.mcap: not a readable MCAP file: "):
        BagReader(junk)
    good = write(tmp_path / "good.mcap", [("/a", T0_NS + i) for i in range(100)])
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(good.read_bytes()[:-40])
    with pytest.raises(BadInput, match=r"truncated\.mcap: gone: "):
        read_metadata(truncated, failure="gone")


def test_errors_of_the_callers_loop_are_not_wrapped(tmp_path):
    path = write(tmp_path / "d.mcap", [("/a", T0_NS)])
    with pytest.raises(ValueError, match="mine"), BagReader(path) as bag:
        for _m in bag.messages():
            raise ValueError("mine")


def full_disk(path: Path) -> None:
    """Make the writer's partial file for `path` a link to /dev/full, so writing it fails with ENOSPC."""
    assert Path("/dev/full").exists(), "this test needs Linux's /dev/full (the device whose writes fail with ENOSPC)"
    path.with_name(f".{path.name}.partial").symlink_to("/dev/full")


def write_frames(path: Path, n: int) -> None:
    """`n` CSI frames of 10 kB each: 200 of them fill the writer's first 1 MB chunk."""
    with BagWriter(path) as bag:
        for i in range(n):
            frame = make("rover_msgs/msg/CsiFrame", header=header(T0_NS + i), bfee=np.full(10_000, i % 256, np.uint8))
            bag.write("/csi", frame, T0_NS + i)
            if i == n - 1 and n > 200:
                raise AssertionError("a full chunk should have failed to write by now")


@pytest.mark.parametrize("n", [3, 300], ids=["fails-at-close", "fails-while-writing"])
def test_a_full_disk_is_bad_input_naming_the_file_and_leaves_no_partial(tmp_path, n):
    path = tmp_path / "d.mcap"
    full_disk(path)
    with pytest.raises(BadInput, match=rf"^{re.escape(str(path))}: cannot write: No space left on device$"):
        write_frames(path, n)
    assert list(tmp_path.iterdir()) == []


def test_an_old_file_stays_intact_until_the_new_one_is_complete(tmp_path):
    path = write(tmp_path / "d.mcap", [("/old", T0_NS)])
    old = path.read_bytes()
    full_disk(path)
    with pytest.raises(BadInput, match="No space left"):
        write_frames(path, 300)
    assert path.read_bytes() == old and list(tmp_path.iterdir()) == [path]
    with BagWriter(path) as bag:
        bag.write("/new", make("std_msgs/msg/Header", stamp=header(T0_NS).stamp), T0_NS)
        assert path.read_bytes() == old
    assert [m.topic for m in iter_messages(path)] == ["/new"]
    assert list(tmp_path.iterdir()) == [path]


@pytest.mark.parametrize(
    "raised", [KeyboardInterrupt(), Interrupted(15), ValueError("mine")], ids=lambda e: type(e).__name__
)
def test_any_exception_through_with_removes_the_partial(tmp_path, raised):
    with pytest.raises(type(raised)), BagWriter(tmp_path / "d.mcap") as bag:
        bag.write("/a", make("std_msgs/msg/Header", stamp=header(T0_NS).stamp), T0_NS)
        raise raised
    assert list(tmp_path.iterdir()) == []
    assert bag.closed


def test_a_directory_is_rejected_before_anything_is_written(tmp_path):
    with pytest.raises(BadInput, match=rf"^{re.escape(str(tmp_path))}: is a directory; name the file to write"):
        BagWriter(tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(BadInput, match=r"a\.mcap: cannot write: .*file is not a directory"):
        BagWriter(tmp_path / "file" / "sub" / "a.mcap")
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_a_writer_never_closed_leaves_no_partial_at_exit(tmp_path):
    """The case of a signal landing between creating a writer and entering its `with` block."""
    code = f"from rover.formats.bag import BagWriter; bag = BagWriter({str(tmp_path / 'd.mcap')!r}); print(bag.closed)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert proc.stdout == "False\n", proc.stderr
    assert list(tmp_path.iterdir()) == []


def raw_mcap(path: Path, compression: CompressionType) -> tuple[Path, int]:
    """A small MCAP file in one chunk of `compression`, and the offset of the chunk's compressed data."""
    with path.open("wb") as f:
        writer = Writer(f, compression=compression)
        writer.start("ros2", "test")
        schema = writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        channel = writer.register_channel("/a", "cdr", schema)
        for i in range(50):
            writer.add_message(
                channel,
                T0_NS + i,
                serialize(make("std_msgs/msg/String", data="abcd"), "std_msgs/msg/String"),
                T0_NS + i,
            )
        writer.finish()
    with path.open("rb") as f:
        summary = make_reader(f).get_summary()
        assert summary is not None
        (chunk,) = summary.chunk_indexes
    # opcode, record length, start and end time, uncompressed size and CRC, the compression's name, data length
    return path, chunk.chunk_start_offset + 1 + 8 + 8 + 8 + 8 + 4 + 4 + len(chunk.compression) + 8


def damage(path: Path, at: int, new: bytes) -> Path:
    data = bytearray(path.read_bytes())
    data[at : at + len(new)] = new
    path.write_bytes(data)
    return path


def read_all(path: Path) -> None:
    with BagReader(path) as bag:
        bag.summary()
        bag.metadata()
        list(bag.messages())


def test_a_six_byte_text_file_is_not_an_mcap_file(tmp_path):
    path = tmp_path / "six.mcap"
    path.write_text("hello\n")
    with pytest.raises(
        BadInput, match=r"^\S*six\.mcap: not a readable MCAP file: not an MCAP file \(no MCAP magic bytes"
    ):
        BagReader(path)


def test_a_chunk_whose_bytes_changed_fails_its_crc(tmp_path):
    path, data_at = raw_mcap(tmp_path / "d.mcap", CompressionType.NONE)
    damage(path, path.read_bytes().index(b"abcd", data_at), b"abce")
    with pytest.raises(BadInput, match=r"d\.mcap: not a readable MCAP file: corrupt chunk \(crc validation failed"):
        read_all(path)


@pytest.mark.parametrize(
    ("compression", "error"), [(CompressionType.ZSTD, "ZstdError"), (CompressionType.LZ4, "RuntimeError: LZ4F_")]
)
def test_a_chunk_that_does_not_decompress(tmp_path, compression, error):
    path, data_at = raw_mcap(tmp_path / "d.mcap", compression)
    damage(path, data_at, b"\x00\x00\x00\x00")
    with pytest.raises(BadInput, match=rf"d\.mcap: not a readable MCAP file: corrupt compressed chunk \({error}"):
        read_all(path)


def test_a_summary_without_the_messages_channel_is_a_corrupt_index(tmp_path):
    path, _data_at = raw_mcap(tmp_path / "d.mcap", CompressionType.NONE)
    channel_record = b"\x01\x00\x01\x00\x02\x00\x00\x00/a"
    in_summary = path.read_bytes().rindex(channel_record)
    damage(path, in_summary, b"\x09\x00")
    message = "corrupt index (a message names channel or schema 1, which the summary lacks)"
    with pytest.raises(BadInput, match=rf"d\.mcap: not a readable MCAP file: {re.escape(message)}$"):
        read_all(path)


def test_a_chunk_claiming_exabytes_is_corrupt_not_a_memory_error(tmp_path):
    path, data_at = raw_mcap(tmp_path / "d.mcap", CompressionType.ZSTD)
    damage(path, data_at - 8, (2**62).to_bytes(8, "little"))
    with pytest.raises(BadInput, match=r"d\.mcap: not a readable MCAP file: corrupt \("):
        read_all(path)


def test_decode_names_the_topic_of_another_type_or_of_bad_bytes(tmp_path):
    path = write(tmp_path / "d.mcap", [("/a", T0_NS)])
    with BagReader(path) as bag:
        (message,) = bag.messages()
        assert bag.decode(message, "std_msgs/msg/Header").frame_id == "/a"
        with pytest.raises(
            BadInput, match=r"d\.mcap: topic /a carries std_msgs/msg/Header, expected rover_msgs/msg/Aoa$"
        ):
            bag.decode(message, "rover_msgs/msg/Aoa")
        with pytest.raises(
            BadInput, match=r"d\.mcap: topic /a: the message logged at \d+ ns is not a valid std_msgs/msg/Header"
        ):
            bag.decode(message._replace(data=b"\x00\x01\x00\x00\x07"), "std_msgs/msg/Header")


def test_a_file_cut_while_being_written_says_so_and_where(tmp_path):
    path = tmp_path / "full.mcap"
    with BagWriter(path) as bag:
        for i in range(2000):
            bag.write("/imu/data", make("std_msgs/msg/String", data="x" * 100), T0_NS + i)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:30_000])
    with pytest.raises(BadInput) as caught:
        BagReader(cut, "not a readable MCAP dataset")
    assert str(caught.value) == (
        f"{cut}: not a readable MCAP dataset: the file ends early, at byte 30,000 (cut while it was being "
        "written? a finished MCAP file ends with its magic bytes)"
    )
