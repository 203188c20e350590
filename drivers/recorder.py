"""`recorder`: writes every message it receives to an MCAP file that is also a ROS 2 bag.

Inputs take any name and any type; each becomes a topic (`/<port>`, or as mapped by
`topics`). The file is written under a temporary name and renamed when complete, so a run
never leaves a half-written file behind. Log time is the message's event time, so the same
input gives the same bytes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

import rover
from rover.errors import BadInput
from rover.messages import ANY, Raw, ros2_msgdef
from rover.operator import In, Operator


@dataclass(frozen=True)
class RecorderParams:
    out: str = "rover-out"
    file: str = "results.mcap"
    topics: dict[str, str] = field(default_factory=dict)


class Recorder(Operator):
    """Records its inputs to `<out>/<file>`."""

    variadic = In(ANY, raw=True, doc="any message; recorded as the topic named by `topics` or /<port>")
    Params = RecorderParams

    def __init__(self, params: RecorderParams | None = None):
        super().__init__(params)
        p = self.params
        self.path = Path(p.out) / p.file
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmp = self.path.with_name(f".{self.path.name}.partial")
            self._file = self._tmp.open("wb")
        except OSError as exc:
            raise BadInput(f"{self.path}: cannot write: {exc.strerror or exc}") from None
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=f"rover {rover.__version__}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0

    def _channel(self, port: str, typename: str) -> int:
        if port not in self._channels:
            if typename not in self._schemas:
                self._schemas[typename] = self._writer.register_schema(
                    name=typename, encoding="ros2msg", data=ros2_msgdef(typename).encode())
            topic = self.params.topics.get(port, f"/{port}")
            self._channels[port] = self._writer.register_channel(
                topic=topic, message_encoding="cdr", schema_id=self._schemas[typename])
        return self._channels[port]

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        assert isinstance(msg, Raw)
        self._sequence += 1
        self._writer.add_message(self._channel(port, msg.typename), log_time=stamp_ns, data=msg.payload,
                                 publish_time=stamp_ns, sequence=self._sequence)
        return ()

    def close(self) -> None:
        if self._file.closed:
            return
        self._writer.finish()
        self._file.close()
        os.replace(self._tmp, self.path)
