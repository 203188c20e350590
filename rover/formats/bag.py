"""Writing and reading an MCAP file that is also a ROS 2 bag (cdr messages, ros2msg schemas, zstd chunks).

The file appears under its name only when complete: it is written as a hidden `.partial`
file and renamed on `close()`; `discard()` removes it instead.

`BagReader` (and `iter_messages`, `read_metadata`) read any MCAP file back as raw messages;
a file that cannot be read is a `BadInput` naming it, worded by the caller's `failure`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple

from mcap.exceptions import McapError
from mcap.reader import McapReader, make_reader
from mcap.writer import CompressionType, Writer

import rover
from rover.errors import BadInput
from rover.messages import Raw, ros2_msgdef, serialize


class BagWriter:
    """Appends CDR messages to topics; schemas and channels are registered on first use."""

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None):
        self.path = Path(path)
        self._tmp = self.path.with_name(f".{self.path.name}.partial")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = self._tmp.open("wb")
        except OSError as exc:
            raise BadInput(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=f"rover {rover.__version__}")
        for name, values in (metadata or {}).items():
            self._writer.add_metadata(name, values)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self.count = 0

    def _channel(self, topic: str, typename: str) -> int:
        known = self._channels.get(topic)
        if known is not None:
            if known[1] != typename:
                raise ValueError(f"topic {topic} is {known[1]}, cannot also carry {typename}")
            return known[0]
        if typename not in self._schemas:
            self._schemas[typename] = self._writer.register_schema(
                name=typename, encoding="ros2msg", data=ros2_msgdef(typename).encode()
            )
        channel = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=self._schemas[typename])
        self._channels[topic] = (channel, typename)
        return channel

    def write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        """Append a decoded message or a Raw one, logged at its event time."""
        typename = msg.typename if isinstance(msg, Raw) else msg.__msgtype__
        self.count += 1
        self._writer.add_message(
            self._channel(topic, typename),
            log_time=stamp_ns,
            data=serialize(msg, typename),
            publish_time=stamp_ns,
            sequence=self.count,
        )

    @property
    def closed(self) -> bool:
        return self._file.closed

    def close(self) -> None:
        """Finish the file and give it its name."""
        if self._file.closed:
            return
        self._writer.finish()
        self._file.close()
        os.replace(self._tmp, self.path)

    def discard(self) -> None:
        """Drop what was written; no file is left behind."""
        if not self._file.closed:
            self._file.close()
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, _exc: BaseException | None, _tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()


READ_ERRORS = (McapError, OSError, ValueError, EOFError)
"""What reading a missing, truncated or corrupt MCAP file raises; the reader turns them into BadInput."""


class BagMessage(NamedTuple):
    """One recorded message, as its serialized bytes."""

    topic: str
    log_time_ns: int
    schema: str
    """The schema name (the ROS 2 type, e.g. `sensor_msgs/msg/Imu`); "" for a channel without one."""
    data: bytes


@dataclass(frozen=True)
class BagChannel:
    """One channel of the summary."""

    id: int
    topic: str
    schema: str
    """The schema name; "" for a channel without one."""
    encoding: str
    """The message encoding, `cdr` in a ROS 2 bag."""
    count: int
    """Messages on the channel (0 when the file has no statistics)."""


@dataclass(frozen=True)
class BagStatistics:
    message_count: int
    start_ns: int
    end_ns: int


@dataclass(frozen=True)
class BagSummary:
    """The summary section: the channels in file order, and the statistics when written."""

    channels: tuple[BagChannel, ...]
    statistics: BagStatistics | None


class BagReader:
    """Reads an MCAP file: its summary, metadata and messages.

    Every failure to read the file (missing, unreadable, truncated, corrupt) raises
    `BadInput(f"{path}: {failure}: {reason}")`; errors of the caller's own code while it
    iterates are not touched.
    """

    def __init__(self, path: str | Path, failure: str = "not a readable MCAP file"):
        self.path = Path(path)
        self.failure = failure
        with self._reading():
            self._file: IO[bytes] = self.path.open("rb")
        try:
            with self._reading():
                self._reader: McapReader = make_reader(self._file)
        except BaseException:
            self._file.close()
            raise

    @contextmanager
    def _reading(self) -> Iterator[None]:
        try:
            yield
        except READ_ERRORS as exc:
            raise BadInput(f"{self.path}: {self.failure}: {exc}") from None

    def summary(self) -> BagSummary | None:
        """The summary section; None when the file has none (e.g. it was not closed properly)."""
        with self._reading():
            summary = self._reader.get_summary()
        if summary is None:
            return None
        counts = summary.statistics.channel_message_counts if summary.statistics else {}
        channels = []
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            channels.append(
                BagChannel(
                    channel.id,
                    channel.topic,
                    schema.name if schema else "",
                    channel.message_encoding,
                    counts.get(channel.id, 0),
                )
            )
        stats = summary.statistics
        return BagSummary(
            tuple(channels),
            BagStatistics(stats.message_count, stats.message_start_time, stats.message_end_time) if stats else None,
        )

    def metadata(self) -> dict[str, dict[str, str]]:
        """The metadata records by name (a later record of the same name wins)."""
        with self._reading():
            return {m.name: dict(m.metadata) for m in self._reader.iter_metadata()}

    def messages(self, topics: Iterable[str] | None = None, *, log_time_order: bool = True) -> Iterator[BagMessage]:
        """The messages on `topics` (all when None), in log-time order or else in file order."""
        with self._reading():
            records = self._reader.iter_messages(
                topics=None if topics is None else list(topics), log_time_order=log_time_order
            )
        while True:
            with self._reading():
                record = next(records, None)
            if record is None:
                return
            schema, channel, message = record
            yield BagMessage(channel.topic, message.log_time, schema.name if schema else "", message.data)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(
        self, _exc_type: type[BaseException] | None, _exc: BaseException | None, _tb: TracebackType | None
    ) -> None:
        self.close()


def iter_messages(
    path: str | Path,
    topics: Iterable[str] | None = None,
    *,
    log_time_order: bool = True,
    failure: str = "not a readable MCAP file",
) -> Iterator[BagMessage]:
    """The messages of the file at `path`; see `BagReader.messages`. The file is opened on the first `next()`."""
    with BagReader(path, failure) as bag:
        yield from bag.messages(topics, log_time_order=log_time_order)


def read_metadata(path: str | Path, failure: str = "not a readable MCAP file") -> dict[str, dict[str, str]]:
    """The metadata records of the file at `path` by name."""
    with BagReader(path, failure) as bag:
        return bag.metadata()
