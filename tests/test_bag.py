"""The MCAP reader: messages in log-time or file order, metadata, summary, and BadInput for unreadable files."""

from __future__ import annotations

import pytest
from conftest import T0_NS

from rover.errors import BadInput
from rover.formats.bag import BagMessage, BagReader, BagWriter, iter_messages, read_metadata
from rover.messages import deserialize, header, make


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
