"""Writing and reading an MCAP file that is also a ROS 2 bag (cdr messages, ros2msg schemas, zstd chunks).

The file appears under its name only when complete: it is written as a hidden `.partial`
file and renamed on `close()` (over any old file of that name); `discard()`, a failure to
write (`BadInput` naming the file) or an exception through `with` removes it instead.

`BagReader` (and `iter_messages`, `read_metadata`) read any MCAP file back as raw messages;
a file that cannot be read is a `BadInput` naming it, worded by the caller's `failure`.
"""

from __future__ import annotations

import atexit
import errno
import os
import struct
from collections.abc import Iterable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, NamedTuple

from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.reader import McapReader, make_reader
from mcap.stream_reader import CRCValidationError
from mcap.writer import CompressionType, Writer
from rosbags.serde import SerdeError
from zstandard import ZstdError

import rover
from rover.errors import BadInput
from rover.formats.atomic_file import partial_path
from rover.messages import Raw, deserialize, ros2_msgdef, serialize

_PARTIALS: set[Path] = set()
"""The `.partial` files of writers neither closed nor discarded. A signal that lands between
creating a writer and entering its `with` block cannot leave one behind: they go at exit."""


@atexit.register
def _remove_partials() -> None:
    for tmp in list(_PARTIALS):
        with suppress(OSError):
            tmp.unlink(missing_ok=True)


def _cannot_write(path: Path, exc: OSError) -> BadInput:
    return BadInput(f"{path}: cannot write: {exc.strerror or exc}")


def check_output(path: str | Path, *, force: bool = False) -> Path:
    """Reject an output file that cannot be written, before any work is done: a directory, a
    parent that is a file or not writable, or an existing file without `force`."""
    path = Path(path)
    if path.is_dir():
        raise BadInput(f"{path}: is a directory; name the file to write, e.g. {path / 'dataset.mcap'}")
    folder = path.absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise BadInput(f"{path}: cannot write: {folder} is not a directory")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise BadInput(f"{path}: cannot write: permission denied in {folder}")
    if path.exists() and not force:
        raise BadInput(f"{path}: exists (use --force to replace it)")
    return path


class BagWriter:
    """Appends CDR messages to topics; schemas and channels are registered on first use.

    A failure to write (a full disk, a file size limit) is a `BadInput` naming the file, and
    removes the partial file; an existing file at `path` stays intact until `close()` renames
    the complete one over it.
    """

    def __init__(self, path: str | Path, metadata: dict[str, dict[str, str]] | None = None):
        self.path = Path(path)
        self._tmp = partial_path(self.path)
        check_output(self.path, force=True)
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, tuple[int, str]] = {}
        self.count = 0
        _PARTIALS.add(self._tmp)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = self._tmp.open("wb")
        except OSError as exc:
            _PARTIALS.discard(self._tmp)
            raise _cannot_write(self.path, exc) from None
        with self._or_discard():
            self._writer = Writer(self._file, compression=CompressionType.ZSTD)
            self._writer.start(profile="ros2", library=f"rover {rover.__version__}")
            for name, values in (metadata or {}).items():
                self._writer.add_metadata(name, values)

    @contextmanager
    def _or_discard(self) -> Iterator[None]:
        """Any failure, even an interrupt, removes the partial file; an OSError becomes a BadInput naming the output."""
        try:
            yield
        except OSError as exc:
            self.discard()
            raise _cannot_write(self.path, exc) from None
        except BaseException:
            self.discard()
            raise

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

    def write(self, topic: str, msg: Any, stamp_ns: int, publish_ns: int | None = None) -> None:
        """Append a decoded message or a Raw one, logged at its event time; `publish_ns` (default the
        event time) is MCAP's publish time, which a live recording uses to flag a message that came late."""
        typename = msg.typename if isinstance(msg, Raw) else msg.__msgtype__
        try:
            channel = self._channel(topic, typename)
            self.count += 1
            self._writer.add_message(
                channel,
                log_time=stamp_ns,
                data=serialize(msg, typename),
                publish_time=stamp_ns if publish_ns is None else publish_ns,
                sequence=self.count,
            )
        except OSError as exc:
            self.discard()
            raise _cannot_write(self.path, exc) from None

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record known only once the messages are written (what a live recording counted)."""
        with self._or_discard():
            self._writer.add_metadata(name, values)

    @property
    def closed(self) -> bool:
        return self._file.closed

    def close(self) -> None:
        """Finish the file and give it its name (replacing any file of that name); on any
        failure, even an interrupt, the partial file is removed instead."""
        if self._file.closed:
            return
        with self._or_discard():
            self._writer.finish()
            self._file.close()
            os.replace(self._tmp, self.path)
        _PARTIALS.discard(self._tmp)

    def discard(self) -> None:
        """Drop what was written; no file is left behind."""
        try:
            with suppress(OSError):
                self._file.close()
        finally:
            with suppress(OSError):
                self._tmp.unlink(missing_ok=True)
            _PARTIALS.discard(self._tmp)

    def __enter__(self) -> BagWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, _exc: BaseException | None, _tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()


READ_ERRORS: tuple[type[Exception], ...] = (
    McapError,
    OSError,
    ValueError,
    EOFError,
    struct.error,
    KeyError,
    OverflowError,
    RuntimeError,
    ZstdError,
    MemoryError,
)
"""What the mcap library raises on a missing, truncated or corrupt file (found by fuzzing): its own
McapError (bad magic, end of file, a record longer than the file can hold), OSError (a seek before the
start), struct.error (a file shorter than a record), ValueError (CRC mismatch, a name that is not
UTF-8, an offset too large), OverflowError (a length too large), KeyError (a chunk naming a channel or
schema the summary lacks), ZstdError and RuntimeError (lz4.frame) for a chunk that does not
decompress, MemoryError (a record claiming a terabyte). The reader turns them into BadInput; they
are caught only around the library's calls."""


MAGIC = b"\x89MCAP0\r\n"
"""The first (and last) eight bytes of an MCAP file."""


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
    iterates are not touched. Chunk CRCs are checked, so a corrupt chunk is an error rather
    than garbage messages.
    """

    def __init__(self, path: str | Path, failure: str = "not a readable MCAP file"):
        self.path = Path(path)
        self.failure = failure
        with self._reading():
            self._file: IO[bytes] = self.path.open("rb")
        try:
            with self._reading():
                if self._file.read(len(MAGIC)) != MAGIC:
                    raise BadInput(f"{self.path}: {failure}: not an MCAP file (no MCAP magic bytes at its start)")
                size = self._file.seek(0, os.SEEK_END)
                self._file.seek(max(size - len(MAGIC), 0))
                if size < 2 * len(MAGIC) or self._file.read(len(MAGIC)) != MAGIC:
                    raise BadInput(
                        f"{self.path}: {failure}: the file ends early, at byte {size:,} (cut while it was being "
                        "written? a finished MCAP file ends with its magic bytes)"
                    )
                self._file.seek(0)
                self._reader: McapReader = make_reader(self._file, validate_crcs=True)
        except BaseException:
            self._file.close()
            raise

    @contextmanager
    def _reading(self) -> Iterator[None]:
        try:
            yield
        except READ_ERRORS as exc:
            raise BadInput(f"{self.path}: {self.failure}: {_reason(exc)}") from None

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

    def decode(self, message: BagMessage, typename: str) -> Any:
        """The message deserialized as `typename`; BadInput naming the file and topic when the topic
        carries another type or the bytes do not deserialize."""
        if message.schema != typename:
            got = shown(message.schema) if message.schema else "no schema"
            raise BadInput(f"{self.path}: topic {message.topic} carries {got}, expected {typename}")
        try:
            return deserialize(message.data, typename)
        except SerdeError as exc:
            raise BadInput(
                f"{self.path}: topic {message.topic}: the message logged at {message.log_time_ns} ns is not a "
                f"valid {typename} ({exc})"
            ) from None

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> BagReader:
        return self

    def __exit__(
        self, _exc_type: type[BaseException] | None, _exc: BaseException | None, _tb: TracebackType | None
    ) -> None:
        self.close()


def shown(name: str) -> str:
    """A name read from a file, as a message shows it: quoted and escaped when it holds control
    characters (a corrupt file's schema name could hold a newline and break the one-line error)."""
    return name if name.isprintable() else repr(name)


def _reason(exc: Exception) -> str:
    """Why the file could not be read, in words, with the library's own message when it says more."""
    detail = str(exc)
    if isinstance(exc, OSError) and exc.errno == errno.EINVAL and exc.filename is None:
        return "truncated (too short for an MCAP footer)"
    if isinstance(exc, OSError):
        return exc.strerror or detail
    if isinstance(exc, (EOFError, EndOfFile, struct.error)):
        return "truncated (it ends inside a record)"
    if isinstance(exc, InvalidMagic):
        return "truncated (it does not end with the MCAP magic bytes)"
    if isinstance(exc, CRCValidationError):
        return f"corrupt chunk ({detail})"
    if isinstance(exc, (ZstdError, RuntimeError)):
        return f"corrupt compressed chunk ({type(exc).__name__}: {detail})"
    if isinstance(exc, MemoryError):
        return "corrupt (a record claims a size larger than memory)"
    if isinstance(exc, KeyError):
        return f"corrupt index (a message names channel or schema {detail}, which the summary lacks)"
    if isinstance(exc, McapError):
        return f"corrupt ({detail or type(exc).__name__})"
    return f"corrupt ({type(exc).__name__}: {detail})"


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
