"""`channel_sweep`: frames labelled with the tag owning their channel, the schedule, conflicts by mode."""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest
from helpers import T0_NS

from rover.errors import BadInput
from rover.messages import header, make
from rover.operators.channel_sweep.operator import ChannelSweep, SweepParams
from rover.testing import run_operator

SETUP = """\
receiver: {antenna_positions_m: [[0, 0], [0.0258, 0], [0.0129, -0.0223]]}
excitation: {channel: 165}
tags: [{id: 1, channel: 149}, {id: 2, channel: 153}, {id: 3, channel: 157}, {id: 4, channel: 161}]
"""


def frame(channel: int, i: int):
    return make(
        "rover_msgs/msg/CsiFrame",
        header=header(T0_NS + i),
        channel=channel,
        bfee=np.array([0xBB, i % 256], dtype=np.uint8),
    )


def setup_msg(text: str = SETUP):
    return make("rover_msgs/msg/RigSetup", header=header(T0_NS), setup_yaml=text)


def test_labels_frames_and_sends_the_schedule(caplog):
    op = ChannelSweep()
    early = frame(153, 0)  # as early as the setup: frames go first at a tie (port names), so it waits for it
    frames = [early] + [frame(ch, i + 1) for i, ch in enumerate([149, 161, 100, 157, 100])]
    with caplog.at_level(logging.INFO):
        out = run_operator(op, {"frames": frames, "setup": [setup_msg()]})
    schedule = [e.msg for e in out if e.port == "schedule"]
    assert len(schedule) == 1
    assert schedule[0].channels.tolist() == [149, 153, 157, 161] and schedule[0].tag_ids.tolist() == [1, 2, 3, 4]
    assert schedule[0].dwell_s == 0.05 and schedule[0].excitation_channel == 165
    labelled = [(e.msg.channel, e.msg.tag_id, int(e.msg.bfee[1])) for e in out if e.port == "labelled"]
    assert labelled == [(153, 2, 0), (149, 1, 1), (161, 4, 2), (157, 3, 4)]
    assert op.drops == {"CSI frames on channel 100 no tag owns": 2}
    warnings = [
        r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING and "channel plan" in r.getMessage()
    ]
    assert warnings == [
        "channel plan: 1 conflict(s) between the tags' channels (-v lists them); a conflict-free assignment: "
        "tag 1 -> 149, tag 2 -> 104, tag 3 -> 157, tag 4 -> 161"
    ], "one line on every run of the same rig"
    details = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    assert any("tag 4's 3rd harmonic" in line for line in details)


def test_conflicts_are_errors_when_planning_a_live_sweep():
    op = ChannelSweep(SweepParams(mode="live"))
    with pytest.raises(BadInput, match="1 conflict.*tag 4's 3rd harmonic.*tag 4 -> "):
        list(op.on_input("setup", setup_msg(), T0_NS))
    clean = ChannelSweep(SweepParams(mode="live"))
    out = list(clean.on_input("setup", setup_msg(SETUP.replace(", {id: 4, channel: 161}", "")), T0_NS))
    assert [e.port for e in out] == ["schedule"]


def test_a_bad_rig_on_the_wire_is_bad_input():
    with pytest.raises(BadInput, match="rig description on the setup input"):
        list(ChannelSweep().on_input("setup", setup_msg("excitation: {channel: nope}"), T0_NS))


def test_live_frames_take_the_channel_tuned_at_their_stamp():
    op = ChannelSweep()

    def hop(ch: int, i: int) -> Any:
        return make("rover_msgs/msg/ChannelHop", header=header(T0_NS + i), interface="wlan0", channel=ch)

    out = run_operator(
        op,
        {
            "setup": [setup_msg()],
            "hops": [hop(149, 1), hop(157, 4), hop(100, 6)],
            "frames": [frame(0, 2), frame(0, 3), frame(0, 5), frame(0, 7)],
        },
    )
    labelled = [(e.msg.channel, e.msg.tag_id) for e in out if e.port == "labelled"]
    assert labelled == [(149, 1), (149, 1), (157, 3)]
    assert op.drops == {"CSI frames on channel 100 no tag owns": 1}
