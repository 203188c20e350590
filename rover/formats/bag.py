"""Writing an MCAP file that is also a ROS 2 bag (cdr messages, ros2msg schemas, zstd chunks).

The file appears under its name only when complete: it is written as a hidden `.partial`
file and renamed on `close()`; `discard()` removes it instead.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

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

    def __exit__(self, exc_type, _exc, _tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.discard()
