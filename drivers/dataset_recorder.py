"""`dataset_recorder`: a live session written as a Rover dataset, the file `rover record` makes.

It writes what `rover convert` writes (rover/formats/dataset.py): `/csi` with the channel each frame
was received on (a live frame's channel 0 becomes the channel of the latest hop handed on before it,
as `channel_sweep` labels it: the channel tuned at its stamp, unless the frame came late), `/imu/data`,
`/odom`, the rig description and the provenance, so `rover run --dataset` replays the session. Every
message that reached this operator is kept (what a full inbox dropped before it is counted by the
runtime, in run.json). One that arrived
after a message stamped later had been handed on (a live source or link that fell behind) is
*late*: a replay, which goes by stamp, would take it earlier than the live run did. It is written
at its stamp with MCAP's publish time set to the latest stamp before it (publish time equals log
time for every other message) and counted per topic in the `rover.record` metadata.

With `path` empty the operator records nothing (a pipeline that can record, run without `rover record`).
The file appears whole at the end of the run, an interrupted one included (a live session ends with
Ctrl-C), and never for a failed run.
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from rover.errors import BadInput, OutputFailed
from rover.formats import dataset
from rover.formats.bag import BagWriter
from rover.formats.rig import RigInput
from rover.messages import make
from rover.operator import COMPLETE, In, Operator, RunOutcome

log = logging.getLogger("rover.dataset_recorder")


@dataclass(frozen=True)
class DatasetRecorderParams:
    path: str = ""
    """the dataset to write (.mcap); empty: record nothing"""
    command: str = ""
    """the command line, for the provenance (`rover record` sets it)"""


class DatasetRecorder(Operator):
    """Records the pipeline's sensor streams and its rig as a dataset."""

    inputs = {
        "csi": In("rover_msgs/msg/CsiFrame", doc="CSI frames, live (channel 0) or labelled with their channel"),
        "hops": In("rover_msgs/msg/ChannelHop", required=False, doc="the receiver's retuning, for live frames"),
        "imu": In("sensor_msgs/msg/Imu", raw=True),
        "odom": In("nav_msgs/msg/Odometry", required=False, raw=True),
        "setup": In("rover_msgs/msg/RigSetup"),
    }
    Params = DatasetRecorderParams

    def __init__(self, params: DatasetRecorderParams | None = None):
        super().__init__(params)
        self.path = Path(self.params.path) if self.params.path else None
        self.bag: BagWriter | None = None
        self.setup = RigInput()
        self.tuned = 0
        self.latest_ns: int | None = None
        self.written: Counter[str] = Counter()
        self.late: Counter[str] = Counter()
        self.pending: list[tuple[str, Any, int]] = []
        """messages that came before the rig description (the file's metadata starts with it)"""

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if self.path is None:
            return ()
        if port == "hops":
            self.tuned = msg.channel
        elif port == "setup":
            self._open(msg)
        else:
            if port == "csi" and not msg.channel:
                msg = make("rover_msgs/msg/CsiFrame", header=msg.header, channel=self.tuned, bfee=msg.bfee)
            self._write(dataset.TOPICS[port], msg, stamp_ns)
        return ()

    def _open(self, msg: Any) -> None:
        if self.bag is not None:
            self.drop("rig descriptions after the first (the dataset keeps the first)")
            return
        assert self.path is not None
        rig = self.setup.update(msg)
        pipeline = Path(self.context.pipeline_file)
        sources = [pipeline] if self.context.pipeline_file and pipeline.is_file() else []
        metadata = {
            dataset.SETUP_METADATA: {"yaml": dataset.setup_yaml(rig)},
            dataset.PROVENANCE_METADATA: dataset.provenance(self.params.command, sources),
        }
        try:
            self.bag = BagWriter(self.path, metadata=metadata)
        except BadInput as exc:
            raise OutputFailed(str(exc)) from None
        pending, self.pending = self.pending, []
        for topic, message, stamp in pending:
            self._write(topic, message, stamp)

    def _write(self, topic: str, msg: Any, stamp_ns: int) -> None:
        if self.bag is None:
            self.pending.append((topic, msg, stamp_ns))
            return
        publish_ns = stamp_ns
        if self.latest_ns is not None and stamp_ns < self.latest_ns:
            self.late[topic] += 1
            publish_ns = self.latest_ns
        else:
            self.latest_ns = stamp_ns
        try:
            self.bag.write(topic, msg, stamp_ns, publish_ns)
        except BadInput as exc:
            raise OutputFailed(str(exc)) from None
        self.written[topic] += 1

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Finish the dataset (with what arrived late) unless the run failed; a session that never
        got its rig description has nothing a replay could use: said, and no file."""
        if self.path is None:
            return
        if self.bag is None:
            if outcome.keeps_outputs:
                log.warning("%s: not written: no rig description arrived (%d messages)", self.path, len(self.pending))
            return
        if not outcome.keeps_outputs:
            self.bag.discard()
            return
        counts = {"messages": dict(self.written), "late": dict(self.late), "session": outcome.status}
        try:
            self.bag.add_metadata(dataset.RECORD_METADATA, {"yaml": yaml.safe_dump(counts, sort_keys=True)})
            self.bag.close()
        except BadInput as exc:
            raise OutputFailed(str(exc)) from None
        late = sum(self.late.values())
        summary = ", ".join(f"{topic} {n:,}" for topic, n in sorted(self.written.items()))
        log.info("wrote %s: %s; %d late", self.path, summary, late)
        if late:
            log.warning(
                "%s: %d messages arrived late (%s): a replay takes them in stamp order",
                self.path,
                late,
                ", ".join(f"{t} {n}" for t, n in sorted(self.late.items())),
            )
