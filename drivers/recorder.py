"""`recorder`: writes every message it receives to an MCAP file that is also a ROS 2 bag.

Inputs take any name and any type; each becomes a topic (`/<port>`, or as mapped by
`topics`; a port mapped to "" is not recorded, as the pipeline does with wall-clock timings
unless `--timing-topic` names a topic). Log time is the message's event time, so the same
input gives the same bytes. The file only appears once complete: a run first removes the one
an earlier run left, and a failed run leaves none.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rover.errors import BadInput, OutputFailed
from rover.formats.atomic_file import remove_outputs
from rover.formats.bag import BagWriter
from rover.messages import ANY
from rover.operator import COMPLETE, In, Operator, RunOutcome


@dataclass(frozen=True)
class RecorderParams:
    out: str = "rover-out"
    file: str = "results.mcap"
    topics: dict[str, str] = field(default_factory=dict)


class Recorder(Operator):
    """Records its inputs to `<out>/<file>`."""

    variadic = In(ANY, raw=True, doc="any message; recorded as the topic named by `topics` or /<port> (none for '')")
    Params = RecorderParams

    def __init__(self, params: RecorderParams | None = None):
        super().__init__(params)
        self.path = Path(self.params.out) / self.params.file
        self.topics = self.params.topics
        self.bag: BagWriter | None = None
        self.finished = False

    def start(self) -> None:
        remove_outputs([self.path])

    def _writer(self) -> BagWriter:
        if self.bag is None:
            try:
                self.bag = BagWriter(self.path)
            except BadInput as exc:
                raise OutputFailed(str(exc)) from None
        return self.bag

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        topic = self.topics.get(port, f"/{port}")
        if topic:
            try:
                self._writer().write(topic, msg, stamp_ns)
            except BadInput as exc:
                raise OutputFailed(str(exc)) from None
        return ()

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Finish the file (an empty one when nothing came); a failed run's is discarded."""
        if not outcome.keeps_outputs:
            if self.bag is not None:
                self.bag.discard()
            return
        try:
            self._writer().close()
        except BadInput as exc:
            raise OutputFailed(str(exc)) from None
        self.finished = True

    def report(self, outcome: RunOutcome) -> None:
        """A run that failed after this file was finished (another output failed) leaves it out too."""
        if not outcome.keeps_outputs and self.finished:
            self.path.unlink(missing_ok=True)
