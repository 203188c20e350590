"""`recorder`: writes every message it receives to an MCAP file that is also a ROS 2 bag.

Inputs take any name and any type; each becomes a topic (`/<port>`, or as mapped by
`topics`). Log time is the message's event time, so the same input gives the same bytes,
and the file only appears once complete.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rover.formats.bag import BagWriter
from rover.messages import ANY
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
        self.bag = BagWriter(Path(self.params.out) / self.params.file)
        self.topics = self.params.topics

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        self.bag.write(self.topics.get(port, f"/{port}"), msg, stamp_ns)
        return ()

    def close(self, complete: bool = True) -> None:
        if complete:
            self.bag.close()
        else:
            self.bag.discard()
