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
from rover.formats.bag import BagReader, BagWriter
from rover.formats.dataset import PROVENANCE_METADATA, RECORD_METADATA, SETUP_METADATA
from rover.formats.output_folder import OutputFolder, claim, release
from rover.formats.run_dir import RUN_FILE, read_run_files
from rover.messages import ANY
from rover.operator import COMPLETE, In, Operator, RunOutcome

RESULTS_METADATA = "rover.results"
"""the metadata record that marks an MCAP file as a run's recording, which a later run may replace"""
DATASET_METADATA = (SETUP_METADATA, PROVENANCE_METADATA, RECORD_METADATA)
"""records a dataset carries (simulate, convert, record write them): never a run's recording"""


def check_replaceable(path: Path) -> None:
    """BadInput unless the file is absent or an earlier run's: a recording (its `rover.results`
    record), a file the folder's run.json lists as that run's, or, in a folder with a run.json, an
    MCAP file with no dataset's records (a recording of a Rover from before the `rover.results`
    record). Anything else there (a dataset, the run's own input, a file of the user's) a run's
    results must never replace (issue 43)."""
    if not path.exists():
        return
    run_folder = (path.parent / RUN_FILE).is_file()
    if path.name in read_run_files(path.parent):
        return
    try:
        with BagReader(path) as bag:
            metadata = bag.metadata()
    except BadInput:
        metadata = None  # not a readable MCAP file: not a recording either
    if metadata is not None and (
        RESULTS_METADATA in metadata or (run_folder and not any(name in metadata for name in DATASET_METADATA))
    ):
        return
    raise BadInput(
        f"{path}: this run would replace it, and no earlier run wrote it (a dataset? this run's input?): "
        "give the run another --output, or move the file away"
    )


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
        """Take the output folder for this run (BadInput when another run has it, or when the file
        this run would write is there and no earlier run wrote it: `check_replaceable`)."""
        self.folder = claim(self.path.parent)
        try:
            check_replaceable(self.path)
        except BadInput:
            release(self.folder)
            self.folder = None
            raise

    def _writer(self) -> BagWriter:
        if self.bag is None:
            if self.folder is None:
                raise OutputFailed(f"{self.path}: the recorder was not started")
            try:
                self.bag = BagWriter(
                    self.folder.stage(self.path.name), metadata={RESULTS_METADATA: {"writer": "recorder"}}
                )
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
