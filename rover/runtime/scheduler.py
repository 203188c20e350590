"""Event-time merging of an operator's inputs, so results never depend on arrival timing.

Each input port is a stream in its producer's order. A message is released when no other
port can still produce an earlier one: every other open port has a queued message, or a
watermark past it, or has ended. Equal stamps go by port name. The decisions depend only
on the streams' contents, so one process and three hosts release the same sequence.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from typing import Any

INF = float("inf")


class EventTimeMerger:
    """Buffers per-port streams and releases messages in (stamp, port) order."""

    def __init__(self, ports: list[str]):
        self._ports = sorted(ports)
        self._queues: dict[str, deque[tuple[int, Any]]] = {p: deque() for p in self._ports}
        self._watermark: dict[str, float] = {p: -INF for p in self._ports}
        self._ended: set[str] = set()

    def push(self, port: str, stamp_ns: int, item: Any) -> None:
        self._queues[port].append((stamp_ns, item))

    def watermark(self, port: str, stamp_ns: int) -> None:
        self._watermark[port] = max(self._watermark[port], stamp_ns)

    def end(self, port: str) -> None:
        self._ended.add(port)

    def ended(self, port: str) -> bool:
        return port in self._ended

    @property
    def finished(self) -> bool:
        return len(self._ended) == len(self._ports) and not any(self._queues.values())

    @property
    def pending(self) -> int:
        return sum(len(q) for q in self._queues.values())

    def safe_time(self) -> float:
        """No message released later is stamped before this (inf once everything has ended)."""
        low = INF
        for port in self._ports:
            queue = self._queues[port]
            if queue:
                low = min(low, queue[0][0])
            elif port not in self._ended:
                low = min(low, self._watermark[port])
        return low

    def _may_release(self, stamp: int, port: str) -> bool:
        for other in self._ports:
            if other == port or self._queues[other] or other in self._ended:
                continue
            mark = self._watermark[other]
            if mark < stamp or (mark == stamp and other < port):
                return False
        return True

    def pop_ready(self) -> Iterator[tuple[str, int, Any]]:
        """Release every message that can be released now, in order."""
        queues = self._queues
        if len(self._ports) == 1:
            (port,) = self._ports
            queue = queues[port]
            while queue:
                stamp, item = queue.popleft()
                yield port, stamp, item
            return
        while True:
            best_port, best_stamp = None, None
            for port in self._ports:
                queue = queues[port]
                if queue and (best_stamp is None or queue[0][0] < best_stamp):
                    best_port, best_stamp = port, queue[0][0]
            if best_port is None or best_stamp is None or not self._may_release(best_stamp, best_port):
                return
            stamp, item = queues[best_port].popleft()
            yield best_port, stamp, item
