"""Event-time merging: the release order depends on the streams, never on how they interleave on arrival."""

from __future__ import annotations

import random

from rover.runtime.scheduler import EventTimeMerger


def drain(merger: EventTimeMerger) -> list[tuple[str, int, object]]:
    return list(merger.pop_ready())


def test_holds_back_until_every_port_has_passed():
    m = EventTimeMerger(["imu", "aoa"])
    m.push("imu", 10, "i10")
    m.push("imu", 20, "i20")
    assert drain(m) == []
    m.push("aoa", 15, "a15")
    assert drain(m) == [("imu", 10, "i10"), ("aoa", 15, "a15")]
    m.end("aoa")
    assert drain(m) == [("imu", 20, "i20")]


def test_watermark_releases_a_silent_port():
    m = EventTimeMerger(["imu", "aoa"])
    m.push("imu", 10, "i10")
    m.watermark("aoa", 9)
    assert drain(m) == []
    m.watermark("aoa", 11)
    assert drain(m) == [("imu", 10, "i10")]
    m.watermark("imu", 12)
    assert m.safe_time() == 11


def test_equal_stamps_go_by_port_name():
    m = EventTimeMerger(["b", "a"])
    m.push("b", 5, "b5")
    m.watermark("a", 5)
    assert drain(m) == []
    m.push("a", 5, "a5")
    assert drain(m) == [("a", 5, "a5")]
    m.end("a")
    assert drain(m) == [("b", 5, "b5")]
    m.end("b")
    assert m.finished


def test_arrival_interleaving_does_not_change_the_order():
    rng = random.Random(3)
    streams = {p: sorted(rng.randrange(1000) for _ in range(200)) for p in ("x", "y", "z")}
    orders = []
    for _trial in range(20):
        events = [(p, i) for p, stamps in streams.items() for i in range(len(stamps) + 1)]
        rng.shuffle(events)
        events.sort(key=lambda e: (e[0], e[1]))  # each stream stays in its own order
        cursors = {p: 0 for p in streams}
        m = EventTimeMerger(list(streams))
        out = []
        while any(cursors[p] <= len(streams[p]) for p in streams):
            p = rng.choice([q for q in streams if cursors[q] <= len(streams[q])])
            i = cursors[p]
            cursors[p] += 1
            if i == len(streams[p]):
                m.end(p)
            else:
                m.push(p, streams[p][i], (p, i))
            out += drain(m)
        assert m.finished
        orders.append(out)
    assert all(o == orders[0] for o in orders)
    stamps = [s for _p, s, _ in orders[0]]
    assert stamps == sorted(stamps) and len(stamps) == 600
