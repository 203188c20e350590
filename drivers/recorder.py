"""`recorder`: writes every message it receives to an MCAP file that is also a ROS 2 bag.

Inputs take any name and any type; each becomes a topic (`/<port>`, or as mapped by
`topics`; a port mapped to "" is not recorded, as the pipeline does with wall-clock timings
unless `--timing-topic` names a topic). Log time is the message's event time, so the same
input gives the same bytes. The file is written into the run's staging folder and appears only
once the run ended with results, replacing an earlier run's (rover.formats.output_folder); a failed
run leaves the earlier one as it was.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rover.errors import BadInput, OutputFailed
from rover.formats.bag import BagWriter
from rover.formats.output_folder import OutputFolder, claim, release
from rover.messages import ANY
from rover.operator import COMPLETE, In, Operator, RunOutcome


@dataclass(frozen=True)
class RecorderParams:
    out: str = "rover-out"
    file: str = "results.mcap"
    topics: dict[str, str] = field(default_factory=dict)


class Recorder(Operator):
    """Records its inputs to `<out>/<file>`."""

    cpu_weight = 0.5
    folder_param = "out"

    variadic = In(ANY, raw=True, doc="any message; recorded as the topic named by `topics` or /<port> (none for '')")
    Params = RecorderParams

    def __init__(self, params: RecorderParams | None = None):
        super().__init__(params)
        self.path = Path(self.params.out) / self.params.file
        self.topics = self.params.topics
        self.bag: BagWriter | None = None
        self.finished = False
        self.folder: OutputFolder | None = None

    def start(self) -> None:
        """Take the output folder for this run (BadInput when another run has it)."""
        self.folder = claim(self.path.parent)

    def _writer(self) -> BagWriter:
        if self.bag is None:
            if self.folder is None:
                raise OutputFailed(f"{self.path}: the recorder was not started")
            try:
                self.bag = BagWriter(self.folder.stage(self.path.name))
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
        """The finished file renamed into place when the run ended with results; dropped when it
        failed (after this file was finished too: another output failed)."""
        folder, self.folder = self.folder, None
        if folder is None:
            return
        try:
            if outcome.keeps_outputs and self.finished:
                folder.commit([self.path.name])
            else:
                folder.discard([self.path.name])
        finally:
            release(folder)
