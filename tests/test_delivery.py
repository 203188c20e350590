"""One subscriber per key per process, and one decoded, read-only message for all its consumers."""

from __future__ import annotations

import threading
from typing import Any, cast

import pytest

from rover.frozen import ReadOnlyMessage, is_frozen
from rover.messages import header, make, serialize
from rover.runtime.delivery import Delivery, Fanout, decode
from rover.transport import codec
from rover.transport.session import SessionSpec, open_session

IMU = "sensor_msgs/msg/Imu"


def imu(z: float) -> bytes:
    msg = make(IMU, header=header(1_000_000_000))
    msg.angular_velocity.z = z
    return serialize(msg)


def test_every_consumer_of_a_key_gets_the_same_delivery_and_the_same_read_only_message():
    got: dict[str, list[Delivery]] = {"a": [], "b": [], "other": []}
    with open_session(SessionSpec()) as session:
        fanout = Fanout(session)
        fanout.add("t/imu", got["a"].append)
        fanout.add("t/imu", got["b"].append)
        fanout.add("t/other", got["other"].append)
        fanout.declare()
        assert len(fanout.subscribers) == 2  # one per key, not one per consumer
        att = codec.attachment(codec.Kind.DATA, 1_000_000_000, 0)
        session.put("t/imu", imu(0.5), encoding=codec.encoding(IMU), attachment=att)
        fanout.undeclare()
    assert len(got["a"]) == len(got["b"]) == 1 and not got["other"]
    (a,), (b,) = got["a"], got["b"]
    assert a is b and a.attachment == att and codec.schema_of(a.encoding) == IMU
    msg = cast(Any, a.message(IMU))
    assert is_frozen(msg) and msg.angular_velocity.z == 0.5
    with pytest.raises(ReadOnlyMessage, match="Vector3.z"):
        msg.angular_velocity.z = 1.0
    mine = cast(Any, a.private_message(IMU))
    mine.angular_velocity.z = 2.0  # a writable port's own copy
    assert not is_frozen(mine) and msg.angular_velocity.z == 0.5
    assert b.message(IMU) is msg  # decoded once: the other consumer gets the same object


def test_consumers_in_many_threads_decode_once():
    delivery = Delivery(str(codec.encoding(IMU)), imu(0.25), None)
    seen: list[object] = []
    threads = [threading.Thread(target=lambda: seen.append(delivery.message(IMU))) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(seen) == 8 and all(m is seen[0] for m in seen)


def test_bytes_that_do_not_decode_give_none():
    assert decode(b"\x00\x01\x00\x00\x01", IMU) is None
    assert Delivery("", b"\x00\x01", None).message(IMU) is None
