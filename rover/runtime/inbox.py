"""The bounded inbox of one operator: backpressure for its producers, in arrival order.

Zenoh callbacks put items in (in the publisher's thread within one process, in Zenoh's receive
thread across hosts); the operator's thread takes them out. A full inbox makes `put` wait, which
slows the producer down, or, for live sources that must not wait, replaces the port's oldest
queued data item. Control items (watermarks, end-of-stream markers) are small and few, and the
merger needs every one of them, so they bypass the capacity and are never dropped.
"""

from __future__ import annotations

import queue
import threading
import time
from collections import Counter, deque
from typing import Generic, Literal, TypeVar

T = TypeVar("T")

Policy = Literal["block", "drop_oldest"]
"""What a data `put` does on a full inbox: wait for a free slot, or replace the port's oldest data item."""


class _Entry(Generic[T]):
    """One queued item; `dead` marks a data item dropped in place (a tombstone the consumer skips)."""

    __slots__ = ("port", "item", "control", "dead")

    def __init__(self, port: str, item: T, control: bool) -> None:
        self.port = port
        self.item = item
        self.control = control
        self.dead = False


class Inbox(Generic[T]):
    """A FIFO of `(port, item)` for many producers and one consumer, bounded in data items.

    drop_oldest is O(1) amortized: each port keeps a deque of its live queued data entries (in
    order, so the consumer always takes the head of its port's deque), and a dropped entry is only
    marked dead in the main queue. The consumer skips dead entries; when more than `capacity` of
    them pile up (a stalled consumer under a live source), the main queue is compacted once; so
    at most `capacity` dropped items are still held in memory.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"inbox capacity must be at least 1, not {capacity}")
        self._capacity = capacity
        self._lock = threading.Lock()
        self._not_empty = threading.Condition(self._lock)
        self._not_full = threading.Condition(self._lock)
        self._resume_at = capacity // 2
        """blocked producers are woken when the inbox has drained to this depth, not at every free
        slot: waking them per message makes the two threads trade the GIL for every item"""
        self._waiting = 0
        self._queue: deque[_Entry[T]] = deque()
        self._by_port: dict[str, deque[_Entry[T]]] = {}
        self._depth = 0
        self._dead = 0
        self._high_water = 0
        self._dropped: Counter[str] = Counter()
        self._overflowed: Counter[str] = Counter()
        self._closed = False

    @property
    def capacity(self) -> int:
        return self._capacity

    @property
    def depth(self) -> int:
        """Data items queued now."""
        return self._depth

    @property
    def high_water(self) -> int:
        """The most data items ever queued at once."""
        return self._high_water

    @property
    def overflowed(self) -> Counter[str]:
        """Per port, data items appended over the capacity after waiting `max_wait_s` (a copy)."""
        with self._lock:
            return Counter(self._overflowed)

    @property
    def dropped(self) -> Counter[str]:
        """Per port, data items dropped: by drop_oldest overflow and by put after close (a copy)."""
        with self._lock:
            return Counter(self._dropped)

    def put(
        self, port: str, item: T, *, control: bool = False, policy: Policy = "block", max_wait_s: float | None = None
    ) -> None:
        """Append `item` of `port`. Control items never wait; data items follow `policy` when full.
        With `max_wait_s`, a blocked put waits at most that long, then appends over the capacity
        (counted in `overflowed`): for callers that must not stall, such as Zenoh's receive thread.
        After `close`, data items are counted as dropped and control items are discarded."""
        with self._lock:
            if control:
                if not self._closed:
                    self._append(_Entry(port, item, True))
                return
            if self._depth >= self._capacity and not self._closed:
                if policy == "drop_oldest":
                    if not self._drop_oldest(port):
                        self._dropped[port] += 1
                        return
                else:
                    deadline = None if max_wait_s is None else time.monotonic() + max_wait_s
                    while self._depth >= self._capacity and not self._closed:
                        left = None if deadline is None else deadline - time.monotonic()
                        if left is not None and left <= 0:
                            self._overflowed[port] += 1
                            break
                        self._waiting += 1
                        try:
                            self._not_full.wait(left)
                        finally:
                            self._waiting -= 1
            if self._closed:
                self._dropped[port] += 1
                return
            entry = _Entry(port, item, False)
            self._by_port.setdefault(port, deque()).append(entry)
            self._depth += 1
            self._high_water = max(self._high_water, self._depth)
            self._append(entry)

    def get(self, timeout: float) -> tuple[str, T]:
        """The oldest `(port, item)`, waiting up to `timeout` seconds; raises `queue.Empty` after that.
        Still returns what is queued after `close`, so the consumer may drain."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while len(self._queue) == self._dead:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise queue.Empty
                self._not_empty.wait(remaining)
            entry = self._queue.popleft()
            while entry.dead:
                self._dead -= 1
                entry = self._queue.popleft()
            if not entry.control:
                head = self._by_port[entry.port].popleft()
                assert head is entry, "a port's live data entries are in queue order"
                self._depth -= 1
                if self._waiting and self._depth <= self._resume_at:
                    self._not_full.notify_all()
            return entry.port, entry.item

    def close(self) -> None:
        """Release every blocked `put`; from now on data puts are dropped (and counted), never wait."""
        with self._lock:
            self._closed = True
            self._not_full.notify_all()
            self._not_empty.notify_all()

    def _append(self, entry: _Entry[T]) -> None:
        self._queue.append(entry)
        self._not_empty.notify()

    def _drop_oldest(self, port: str) -> bool:
        """Drop the oldest queued data item of `port` in place (counted); False when there is none."""
        mine = self._by_port.get(port)
        if not mine:
            return False
        mine.popleft().dead = True
        self._depth -= 1
        self._dead += 1
        self._dropped[port] += 1
        if self._dead > self._capacity:
            self._queue = deque(e for e in self._queue if not e.dead)
            self._dead = 0
        return True
