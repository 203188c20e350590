"""Bursts of a capture whose transmitters interleave (another tool's CSI, `aoa`'s `capture` input): a
router on one channel hears every transmitter in turn, so each transmitter's packets make their own
burst, closed by time or count, and the bursts' AoAs leave in stamp order.

A sweep's bursts end when the tag changes (one tag per dwell); here a transmitter's burst ends when
a packet arrives more than `max_burst_ns` after its first, or half that after its last (it fell
silent), or on another channel (a receiver that sweeps the tags' channels: its dwell is over), or
once it holds `burst_packets` packets. An AoA is stamped at its burst's median packet,
so one burst's may come before another's that closed earlier: the AoAs wait in a queue until no
open burst could still give an earlier one.
"""

from __future__ import annotations

import heapq
import itertools
import math
from typing import Any

Packet = tuple[Any, int]
"""a Csi message and its stamp (ns)"""


class InterleavedBursts:
    """Open bursts per transmitter (`tag_id`), and the AoAs of closed ones waiting for their turn."""

    def __init__(self, max_burst_ns: int, burst_packets: int):
        self.max_burst_ns = max_burst_ns
        self.burst_packets = burst_packets
        self.open: dict[int, list[Packet]] = {}
        self._queue: list[tuple[int, int, Any]] = []
        self._order = itertools.count()

    def add(self, msg: Any, stamp_ns: int) -> list[list[Packet]]:
        """Take a packet; the bursts it closes (timed out before it, or full with it), oldest first."""
        closed = [
            tag
            for tag, burst in self.open.items()
            if stamp_ns - burst[0][1] > self.max_burst_ns
            or stamp_ns - burst[-1][1] > self.max_burst_ns / 2
            or burst[-1][0].channel != msg.channel
        ]
        done = [self.open.pop(tag) for tag in closed]
        burst = self.open.setdefault(msg.tag_id, [])
        burst.append((msg, stamp_ns))
        if len(burst) == self.burst_packets:
            done.append(self.open.pop(msg.tag_id))
        return sorted(done, key=lambda b: b[0][1])

    def rest(self) -> list[list[Packet]]:
        """Every open burst (at the end of the stream), oldest first."""
        done, self.open = sorted(self.open.values(), key=lambda b: b[0][1]), {}
        return done

    def queue(self, stamp_ns: int, item: Any) -> None:
        """An AoA (or anything) stamped `stamp_ns`, to leave in stamp order."""
        heapq.heappush(self._queue, (stamp_ns, next(self._order), item))

    def ready(self, now_ns: float) -> list[Any]:
        """The queued items no open burst can precede: stamped at or before `now_ns` (the latest
        packet's stamp; math.inf at the end) and every open burst's first packet."""
        until = min(self.held_open_ns(), now_ns)
        out = []
        while self._queue and self._queue[0][0] <= until:
            out.append(heapq.heappop(self._queue)[2])
        return out

    def held_open_ns(self) -> float:
        """The first stamp of the open bursts (math.inf when none)."""
        return min((burst[0][1] for burst in self.open.values()), default=math.inf)

    def held_since_ns(self) -> float:
        """The earliest stamp still to leave: a queued AoA's or an open burst's first packet's."""
        queued = self._queue[0][0] if self._queue else math.inf
        return min(queued, self.held_open_ns())
