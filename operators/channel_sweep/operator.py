"""`channel_sweep`: plan the receiver's channel hops from the rig and label each CSI frame with its tag.

Each tag backscatters into its own channel, so the channel a frame was received on names the
tag. Conflicts between tags (overlapping channels, mirror sidebands, harmonics) are logged as
warnings when labelling recorded data and are errors when planning a live sweep.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from rover.errors import BadInput
from rover.formats.rig import Rig, RigInput
from rover.formats.wifi import INTEL5300_CHANNELS_5GHZ
from rover.messages import header, make
from rover.operator import Emit, In, Operator, Out
from rover.operators.channel_sweep.channel_plan import conflicts, max_tags, propose
from rover.pipeline.params import Checked, PositiveFloat

log = logging.getLogger("rover.channel_sweep")


@dataclass(frozen=True)
class SweepParams(Checked):
    dwell_s: PositiveFloat = 0.05
    channels: list[int] = field(default_factory=lambda: list(INTEL5300_CHANNELS_5GHZ))
    mode: Literal["label", "live"] = "label"
    max_shift_hz: PositiveFloat | None = None


class ChannelSweep(Operator):
    """Labels CSI frames with the tag owning their channel; sends the sweep schedule once the rig is known."""

    cpu_weight = 0.4

    inputs = {
        "frames": In("rover_msgs/msg/CsiFrame"),
        "setup": In("rover_msgs/msg/RigSetup"),
        "hops": In(
            "rover_msgs/msg/ChannelHop",
            required=False,
            doc="live retuning events; frames with channel 0 take the channel tuned at their stamp",
        ),
    }
    outputs = {"labelled": Out("rover_msgs/msg/LabelledCsiFrame"), "schedule": Out("rover_msgs/msg/SweepSchedule")}
    Params = SweepParams

    def __init__(self, params: SweepParams | None = None):
        super().__init__(params)
        self.setup = RigInput()
        self.rig: Rig | None = None
        self.owner: dict[int, int] = {}
        self.waiting: list[tuple[Any, int]] = []
        self.tuned = 0

    def on_input(self, port: str, msg: Any, stamp_ns: int):
        if port == "hops":
            self.tuned = msg.channel
        elif port == "setup":
            yield from self._configure(msg, stamp_ns)
            for frame, stamp in self.waiting:
                yield from self._label(frame, stamp)
            self.waiting.clear()
        elif self.rig is None:
            self.waiting.append((msg, stamp_ns))
        else:
            yield from self._label(msg, stamp_ns)

    def _configure(self, msg: Any, stamp_ns: int):
        rig = self.setup.update(msg)
        self.rig = rig
        p = self.params
        if rig.excitation_channel is None and p.mode == "label":
            return  # a bare receiver (another tool's capture): nothing to sweep unless CSI Tool frames come
        excitation = rig.require_excitation("channel_sweep")
        wanted = {t.id: t.channel for t in rig.tags}
        found = conflicts(excitation, wanted, p.channels)
        best = max_tags(excitation, p.channels, p.max_shift_hz)
        if found:
            plan = propose(excitation, wanted, p.channels, p.max_shift_hz)
            advice = (
                f"a conflict-free assignment: {', '.join(f'tag {t} -> {c}' for t, c in sorted(plan.channels.items()))}"
                if plan
                else "no conflict-free assignment exists for these tags on this excitation channel"
            )
            lines = [c.message for c in found]
            if p.mode == "live":
                raise BadInput(f"channel plan has {len(found)} conflict(s): {'; '.join(lines)}; {advice}")
            for line in lines:  # each with -v; one warning line on every run of the same rig
                log.info("channel plan: %s", line)
            log.warning(
                "channel plan: %d conflict(s) between the tags' channels (-v lists them); %s", len(lines), advice
            )
        log.info("excitation channel %d allows at most %d tags at once", excitation, len(best))
        self.owner = dict(sorted((t.channel, t.id) for t in rig.tags))
        dwell = rig.dwell_s or p.dwell_s
        yield Emit(
            "schedule",
            make(
                "rover_msgs/msg/SweepSchedule",
                header=header(stamp_ns, "base_link"),
                excitation_channel=excitation,
                channels=np.array(list(self.owner), dtype=np.uint16),
                tag_ids=np.array(list(self.owner.values()), dtype=np.uint32),
                dwell_s=dwell,
                max_tags=len(best),
            ),
        )

    def _label(self, frame: Any, stamp_ns: int):
        if self.rig is not None and self.rig.excitation_channel is None:
            self.rig.require_excitation("channel_sweep")
        channel = frame.channel or self.tuned
        tag = self.owner.get(channel)
        if tag is None:
            self.drop(f"CSI frames on channel {channel} no tag owns")
            return
        yield Emit(
            "labelled",
            make("rover_msgs/msg/LabelledCsiFrame", header=frame.header, tag_id=tag, channel=channel, bfee=frame.bfee),
            stamp_ns,
        )

    def on_end(self):
        self.drop("CSI frames (no rig description arrived)", len(self.waiting))
        return ()
