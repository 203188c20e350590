"""The bounded operator inbox: arrival order, backpressure, control items past a full inbox, drops."""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable

import pytest

from rover.runtime.inbox import Inbox

WAIT_S = 5.0
"""Upper bound on any wait in these tests: a hang fails the test instead."""


def drain(inbox: Inbox[object]) -> list[tuple[str, object]]:
    """Everything queued now, in order."""
    items = []
    while True:
        try:
            items.append(inbox.get(timeout=0))
        except queue.Empty:
            return items


def start(target: Callable[[], None]) -> threading.Thread:
    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread


def blocked_put(inbox: Inbox[object], port: str, item: object) -> threading.Event:
    """Put from another thread, once it is blocked on the full inbox; the event is set when it returns."""
    done = threading.Event()

    def produce() -> None:
        inbox.put(port, item)
        done.set()

    wait_blocked(inbox, start(produce))
    assert not done.is_set()
    return done


def wait_blocked(inbox: Inbox[object], thread: threading.Thread) -> None:
    """Wait, at most WAIT_S, until `thread` waits in `put` on the inbox's not-full condition: its
    waiter list (CPython's) is the proof that the producer is blocked, not merely slow."""
    cond = inbox._not_full
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        with cond:
            if cond._waiters:  # type: ignore[attr-defined]
                return
        assert thread.is_alive(), "the producer returned instead of blocking"
        time.sleep(0.0005)  # a poll of the waiter list; nothing is synchronized by the sleep
    pytest.fail("the producer never blocked")


def test_fifo_across_ports():
    inbox: Inbox[object] = Inbox(capacity=10)
    inbox.put("a", 1)
    inbox.put("b", 2)
    inbox.put("a", 3, control=True)
    inbox.put("c", 4)
    assert drain(inbox) == [("a", 1), ("b", 2), ("a", 3), ("c", 4)]
    with pytest.raises(queue.Empty):
        inbox.get(timeout=0.01)


def test_blocked_producer_resumes_when_the_consumer_takes_one():
    inbox: Inbox[object] = Inbox(capacity=2)
    inbox.put("a", 1)
    inbox.put("a", 2)
    done = blocked_put(inbox, "a", 3)
    assert inbox.get(timeout=WAIT_S) == ("a", 1)
    assert done.wait(WAIT_S)
    assert drain(inbox) == [("a", 2), ("a", 3)]
    assert inbox.high_water == 2
    assert not inbox.dropped


def test_control_items_pass_a_full_inbox_without_blocking():
    inbox: Inbox[object] = Inbox(capacity=2)
    inbox.put("a", 1)
    inbox.put("b", 2)
    for n in range(100):
        inbox.put("a", f"wm{n}", control=True)  # returns at once, in this thread
    assert inbox.depth == 2
    items = drain(inbox)
    assert items[:3] == [("a", 1), ("b", 2), ("a", "wm0")]
    assert len(items) == 102


def test_drop_oldest_replaces_the_oldest_of_the_same_port():
    inbox: Inbox[object] = Inbox(capacity=3)
    inbox.put("a", 1)
    inbox.put("b", 2)
    inbox.put("a", "wm", control=True)
    inbox.put("a", 3)
    inbox.put("a", 4, policy="drop_oldest")
    assert inbox.dropped == {"a": 1}
    assert inbox.depth == 3
    assert drain(inbox) == [("b", 2), ("a", "wm"), ("a", 3), ("a", 4)]


def test_drop_oldest_drops_the_new_item_of_a_port_with_none_queued():
    inbox: Inbox[object] = Inbox(capacity=2)
    inbox.put("a", 1)
    inbox.put("a", 2)
    inbox.put("b", 3, policy="drop_oldest")
    assert inbox.dropped == {"b": 1}
    assert drain(inbox) == [("a", 1), ("a", 2)]


def test_drop_oldest_under_constant_overflow_keeps_the_newest():
    inbox: Inbox[object] = Inbox(capacity=4)
    inbox.put("a", "wm", control=True)
    for n in range(10_000):
        inbox.put("live", n, policy="drop_oldest")
    assert inbox.depth == 4
    assert inbox.dropped == {"live": 10_000 - 4}
    assert len(inbox._queue) <= 1 + 4 + 4 + 1  # tombstones are compacted away
    assert drain(inbox) == [("a", "wm")] + [("live", n) for n in range(9_996, 10_000)]


def test_close_releases_a_blocked_producer_and_counts_the_drop():
    inbox: Inbox[object] = Inbox(capacity=1)
    inbox.put("a", 1)
    done = blocked_put(inbox, "b", 2)
    inbox.close()
    assert done.wait(WAIT_S)
    assert inbox.dropped == {"b": 1}
    inbox.put("a", 3)  # later puts neither block nor raise
    inbox.put("a", "end", control=True)
    assert inbox.dropped == {"a": 1, "b": 1}
    assert inbox.get(timeout=WAIT_S) == ("a", 1)  # the consumer may still drain
    with pytest.raises(queue.Empty):
        inbox.get(timeout=0.01)


def test_high_water():
    inbox: Inbox[object] = Inbox(capacity=10)
    for n in range(3):
        inbox.put("a", n)
    inbox.put("a", "wm", control=True)
    drain(inbox)
    inbox.put("a", 9)
    assert inbox.depth == 1
    assert inbox.high_water == 3


def test_many_producers_one_consumer_lose_nothing_and_keep_port_order():
    producers, per_producer, capacity = 8, 12_500, 64
    inbox: Inbox[object] = Inbox(capacity=capacity)
    gate = threading.Barrier(producers + 1, timeout=WAIT_S)
    received: dict[str, list[object]] = {f"p{i}": [] for i in range(producers)}
    deepest = 0

    def produce(port: str) -> None:
        gate.wait()
        for n in range(per_producer):
            inbox.put(port, n)
        inbox.put(port, "end", control=True)

    threads = [threading.Thread(target=produce, args=(port,), daemon=True) for port in received]
    for thread in threads:
        thread.start()
    gate.wait()
    ended = 0
    while ended < producers:
        deepest = max(deepest, inbox.depth)
        port, item = inbox.get(timeout=WAIT_S)
        if item == "end":
            ended += 1
        received[port].append(item)
    for thread in threads:
        thread.join(WAIT_S)
        assert not thread.is_alive()
    assert all(items == [*range(per_producer), "end"] for items in received.values())
    assert deepest <= capacity
    assert inbox.high_water <= capacity
    assert not inbox.dropped
    assert inbox.depth == 0


def test_mixed_policies_account_for_every_item_and_stay_within_capacity():
    capacity, per_port = 8, 5_000
    inbox: Inbox[object] = Inbox(capacity=capacity)
    ports = {"block0": "block", "block1": "block", "live0": "drop_oldest", "live1": "drop_oldest"}
    gate = threading.Barrier(len(ports) + 1, timeout=WAIT_S)

    def produce(port: str) -> None:
        gate.wait()
        for n in range(per_port):
            inbox.put(port, n, policy="drop_oldest" if ports[port] == "drop_oldest" else "block")
        inbox.put(port, "end", control=True)

    threads = [threading.Thread(target=produce, args=(port,), daemon=True) for port in ports]
    for thread in threads:
        thread.start()
    gate.wait()
    received: dict[str, list[object]] = {port: [] for port in ports}
    ended = 0
    while ended < len(ports):
        assert inbox.depth <= capacity
        port, item = inbox.get(timeout=WAIT_S)
        ended += item == "end"
        received[port].append(item)
    for thread in threads:
        thread.join(WAIT_S)
        assert not thread.is_alive()
    dropped = inbox.dropped
    for port, items in received.items():
        assert items[-1] == "end"
        data = [n for n in items[:-1] if isinstance(n, int)]
        assert len(data) == len(items) - 1
        assert all(a < b for a, b in zip(data, data[1:], strict=False))  # order kept for what survived
        assert len(data) + dropped[port] == per_port
    assert dropped["block0"] == dropped["block1"] == 0
    assert inbox.high_water <= capacity


def test_a_put_with_max_wait_appends_over_the_bound_after_waiting_and_counts_it():
    """Zenoh's receive thread must not freeze on a stalled consumer: it waits at most max_wait_s."""
    inbox: Inbox[int] = Inbox(2)
    inbox.put("a", 1)
    inbox.put("a", 2)
    started = time.monotonic()
    inbox.put("a", 3, max_wait_s=0.05)
    assert time.monotonic() - started >= 0.05
    assert inbox.depth == 3 and inbox.overflowed == {"a": 1} and not inbox.dropped
    assert [inbox.get(1.0)[1] for _ in range(3)] == [1, 2, 3]
