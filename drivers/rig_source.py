"""`rig_source`: a rig description (setup.yaml) sent once into the pipeline.

For pipelines without a dataset, such as a CSI Tool log replayed by `csi_file`: the operators that
need the rig (`aoa`, `channel_sweep`, `preintegration`) get it on their `setup` input as they get
a dataset's from `dataset_replay`, as a RigSetup message (frame `base_link`) holding the file's
text verbatim. It is stamped at `stamp_ns`, 0 by default, before anything a source sends (a log
replayed with `csi_file`'s default `start_ns: 0` starts there too), so the rig is known before
the first frame.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Iterator
from dataclasses import dataclass

from rover.errors import BadInput, SpecError
from rover.formats.rig import load_rig
from rover.messages import header, make
from rover.operator import Emit, Out, Source, Watermark
from rover.pipeline.params import Checked, NonNegativeInt

log = logging.getLogger("rover.rig_source")


@dataclass(frozen=True)
class RigSourceParams(Checked):
    path: str = ""
    """the setup.yaml to send"""
    stamp_ns: NonNegativeInt = 0
    """the RigSetup's stamp: 0 comes before every other message"""


class RigSource(Source):
    """Sends the rig description of a setup.yaml once, at the start."""

    outputs = {"setup": Out("rover_msgs/msg/RigSetup", "the rig description, once at the start")}
    Params = RigSourceParams

    def __init__(self, params: RigSourceParams | None = None):
        super().__init__(params)
        if not self.params.path:
            raise BadInput("rig_source: no setup file given (params.path)")
        try:
            self.rig = load_rig(self.params.path)
        except SpecError as exc:
            raise BadInput("; ".join(str(d) for d in exc.diagnostics)) from None
        for warning in self.rig.warnings:
            log.warning("%s", warning)

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        if stop.is_set():
            return
        stamp = self.params.stamp_ns
        setup = make("rover_msgs/msg/RigSetup", header=header(stamp, "base_link"), setup_yaml=self.rig.text)
        yield Emit("setup", setup, stamp)
