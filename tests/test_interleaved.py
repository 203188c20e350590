"""Bursts of interleaved transmitters (operators/aoa/interleaved.py) and the `aoa` operator's
`capture` input: each transmitter its own bursts, the AoAs in stamp order."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
from test_aoa_capture import SQUARE_19MM, plane_wave, rig
from test_wiros import BINS, CENTRE_HZ, CHANNEL, EMPTY

from rover.messages import header, make
from rover.operators.aoa.interleaved import InterleavedBursts
from rover.operators.aoa.operator import Aoa, AoaParams
from rover.testing import run_operator

MS = 1_000_000


def packet(tag: int, channel: int = CHANNEL) -> SimpleNamespace:
    return SimpleNamespace(tag_id=tag, channel=channel)


def test_each_transmitter_closes_its_own_burst_by_time_gap_or_count():
    bursts = InterleavedBursts(max_burst_ns=500 * MS, burst_packets=4)
    closed = [bursts.add(packet(tag), t * MS) for tag, t in [(1, 0), (2, 10), (1, 100), (2, 110), (1, 200)]]
    assert closed == [[], [], [], [], []] and set(bursts.open) == {1, 2}
    assert bursts.held_open_ns() == 0
    # tag 2 has fallen silent: 260 ms after its last packet (more than half of 500) it is closed;
    # tag 1's fourth packet fills its burst; both closed, oldest first
    done = bursts.add(packet(1), 370 * MS)
    assert [[s // MS for _m, s in b] for b in done] == [[0, 100, 200, 370], [10, 110]] and not bursts.open
    bursts = InterleavedBursts(max_burst_ns=500 * MS, burst_packets=0)
    for t in range(0, 500, 100):
        assert bursts.add(packet(1), t * MS) == []
    (timed_out,) = bursts.add(packet(1), 501 * MS)  # more than 500 ms after the burst's first
    assert len(timed_out) == 5 and [s for _m, s in bursts.open[1]] == [501 * MS]
    # a receiver that sweeps: a packet on another channel ends the dwell's burst
    (swept,) = bursts.add(packet(2, CHANNEL + 4), 510 * MS)
    assert [s for _m, s in swept] == [501 * MS] and set(bursts.open) == {2}


def test_results_leave_in_stamp_order_once_no_open_burst_can_precede_them():
    bursts = InterleavedBursts(max_burst_ns=500 * MS, burst_packets=0)
    bursts.add(packet(1), 0)
    bursts.add(packet(2), 50 * MS)
    bursts.queue(120 * MS, "second")
    bursts.queue(80 * MS, "first")
    assert bursts.ready(130 * MS) == [] and bursts.held_since_ns() == 0  # tag 1's burst began at 0
    del bursts.open[1]
    assert bursts.ready(130 * MS) == []  # tag 2's began at 50: an AoA of it may come at 50 or later
    del bursts.open[2]
    assert bursts.ready(100 * MS) == ["first"] and bursts.held_since_ns() == 120 * MS
    assert bursts.ready(math.inf) == ["second"] and bursts.held_since_ns() == math.inf


def test_the_operator_gives_each_interleaved_transmitter_its_angle_in_stamp_order():
    """Two transmitters at -130 and 40 deg, their packets alternating 5 ms apart on the capture input:
    one AoA per transmitter per 0.5 s, each within 3 deg of its wave, in stamp order."""
    waves = {7: plane_wave(SQUARE_19MM, -130.0, CENTRE_HZ, BINS, EMPTY, seed=1), 9: plane_wave(
        SQUARE_19MM, 40.0, CENTRE_HZ, BINS, EMPTY, seed=2
    )}  # fmt: skip
    kept = ~np.isin(BINS, EMPTY)
    packets = []
    for p in range(60):
        for k, (tag, wave) in enumerate(waves.items()):
            stamp = p * 20 * MS + k * 5 * MS
            c = wave.csi[p][kept]
            packets.append(
                make(
                    "rover_msgs/msg/Csi",
                    header=header(stamp, "base_link"),
                    tag_id=tag,
                    channel=CHANNEL,
                    nrx=4,
                    ntx=1,
                    csi_real=c.real.astype(np.float32).ravel(),
                    csi_imag=c.imag.astype(np.float32).ravel(),
                    subcarriers=BINS[kept].astype(np.int16),
                    centre_freq_hz=CENTRE_HZ,
                )  # fmt: skip
            )
    setup = make("rover_msgs/msg/RigSetup", setup_yaml=rig(SQUARE_19MM).text)
    out = [e.msg for e in run_operator(Aoa(AoaParams()), {"setup": [setup], "capture": packets})]
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in out]
    assert stamps == sorted(stamps)
    assert sorted({m.tag_id for m in out}) == [7, 9] and len(out) >= 4
    truth = {7: -130.0, 9: 40.0}
    errors = [abs((math.degrees(m.angle_rad) - truth[m.tag_id] + 180) % 360 - 180) for m in out]
    assert max(errors) < 3.0, errors
    assert all(len(m.candidate_angles_rad) == 1 for m in out)  # no jump combinations: not the Intel 5300's
