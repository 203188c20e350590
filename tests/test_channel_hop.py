"""`channel_hop`: the sweep applied to an interface, in dry-run (prints the commands) as on a robot
without a NIC here."""

from __future__ import annotations

import threading

import pytest
from helpers import read_bag, run_rover

from rover.drivers.channel_hop import ChannelHop, HopParams
from rover.errors import BadInput
from rover.messages import deserialize, stamp_ns
from rover.operator import Watermark

SETUP = """\
receiver: {antenna_positions_m: [[0, 0], [0.0258, 0], [0.0129, -0.0223]], interface: wlp1s0}
excitation: {channel: 165}
tags: [{id: 2, channel: 153}, {id: 1, channel: 149}]
"""


def test_dry_run_prints_the_iw_commands_and_announces_each_hop(tmp_path):
    (tmp_path / "setup.yaml").write_text(SETUP)
    (tmp_path / "hop.yaml").write_text("""\
name: hop
operators:
  hop: {uses: channel_hop, params: {setup: setup.yaml, dwell_s: 0.02, dry_run: true, rounds: 2}}
  record: {uses: recorder, inputs: {hops: hop/hops}, params: {out: out}}
""")
    proc = run_rover("run", "hop.yaml", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["iw dev wlp1s0 set channel 149 HT20", "iw dev wlp1s0 set channel 153 HT20"] * 2
    hops = [
        deserialize(data, "rover_msgs/msg/ChannelHop") for _t, _s, data in read_bag(tmp_path / "out" / "results.mcap")
    ]
    assert [h.channel for h in hops] == [149, 153, 149, 153] and {h.interface for h in hops} == {"wlp1s0"}


def test_custom_command_template_and_failures():
    ran: list[list[str]] = []
    hop = ChannelHop(
        HopParams(
            channels=[36, 40],
            interface="wlan1",
            dwell_s=0.001,
            rounds=1,
            command="sudo iw dev {interface} set freq {channel} HT20",
        ),
        runner=ran.append,
    )
    assert sum(1 for _ in hop.run(threading.Event())) >= 2
    assert ran == [
        ["sudo", "iw", "dev", "wlan1", "set", "freq", "36", "HT20"],
        ["sudo", "iw", "dev", "wlan1", "set", "freq", "40", "HT20"],
    ]
    failing = ChannelHop(HopParams(channels=[36], command="false {channel}", rounds=1))
    with pytest.raises(BadInput, match="false 36 failed"):
        list(failing.run(threading.Event()))
    with pytest.raises(BadInput, match="no channels"):
        ChannelHop(HopParams())
    with pytest.raises(BadInput, match="bad command template"):
        ChannelHop(HopParams(channels=[36], command="iw {nope}"))


def test_each_hop_promises_the_next_one_a_dwell_later():
    """After a hop stamped T, nothing comes before T + dwell (less a millisecond): the sweep may label
    the frames of the dwell at once; the next hop keeps the promise."""
    hop = ChannelHop(HopParams(channels=[36, 40], dwell_s=0.02, rounds=2), runner=lambda _argv: None)
    items = list(hop.run(threading.Event()))
    promised, hops = 0, 0
    for item, after in zip(items, [*items[1:], None], strict=True):
        if isinstance(item, Watermark):
            promised = max(promised, item.stamp_ns)
            continue
        hops += 1
        stamp = stamp_ns(item.msg)
        assert stamp >= promised, "a hop came before what the last watermark promised"
        assert isinstance(after, Watermark) and after.stamp_ns == stamp + 19_000_000
    assert hops == 4
