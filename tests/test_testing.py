"""`rover.testing.run_operator`: an operator fed in the runtime's order, and ended as the runtime ends it."""

from __future__ import annotations

import random

import pytest

from rover.messages import header, make, stamp_ns
from rover.operator import Emit, In, Operator, Out
from rover.runtime.scheduler import EventTimeMerger
from rover.testing import run_operator


class Log(Operator):
    """Writes down every call it gets, and emits one message per input and one at the end."""

    inputs = {"imu": In("sensor_msgs/msg/Imu"), "aoa": In("rover_msgs/msg/Aoa")}
    outputs = {"seen": Out("std_msgs/msg/String")}

    def __init__(self, params=None):  # no Operator.__init__, as a user's operator may forget it
        self.calls: list[tuple[str, int, str]] = []

    def on_input(self, port, msg, stamp_ns):
        self.calls.append((port, stamp_ns, msg.header.frame_id))
        if msg.header.frame_id == "drop":
            self.drop("messages marked for dropping")
            return None
        return [Emit("seen", make("std_msgs/msg/String", data=msg.header.frame_id))]

    def on_end(self):
        self.calls.append(("end", 0, ""))
        yield Emit("seen", make("std_msgs/msg/String", data="end"))


def imu(stamp: int, name: str):
    return make("sensor_msgs/msg/Imu", header=header(stamp, name))


def aoa(stamp: int, name: str):
    return make("rover_msgs/msg/Aoa", header=header(stamp, name))


def test_stamp_order_ties_by_port_name_and_the_end_once():
    op = Log()
    out = run_operator(
        op,
        {
            "imu": [imu(10, "i10"), imu(20, "i20a"), imu(20, "i20b"), imu(30, "i30")],
            "aoa": [aoa(5, "a5"), aoa(20, "a20"), aoa(40, "a40")],
        },
    )
    order = ["a5", "i10", "a20", "i20a", "i20b", "i30", "a40"]
    assert [name for _port, _stamp, name in op.calls] == [*order, ""]
    assert [stamp for _port, stamp, _name in op.calls[:-1]] == [5, 10, 20, 20, 20, 30, 40]
    assert op.calls[-1][0] == "end" and [e.msg.data for e in out] == [*order, "end"]


def test_an_empty_input_a_handler_returning_none_and_drops():
    op = Log()
    out = run_operator(op, {"imu": [imu(1, "drop"), imu(2, "kept")], "aoa": []})
    assert [e.msg.data for e in out] == ["kept", "end"]
    assert op.drops == {"messages marked for dropping": 1}
    op.drop("nothing", 0)
    assert "nothing" not in op.drops


def calls(inputs) -> list[tuple[str, int, str]]:
    """The (port, stamp, frame id) of each message run_operator hands the operator, in order."""
    op = Log()
    run_operator(op, inputs)
    return op.calls[:-1]


def test_the_same_order_as_the_runtime_gets_from_streams_arriving_interleaved():
    """Each port's messages arrive in order, each with its watermark (as a source sends them), then
    the port's end; whatever the interleaving of the ports, the merger releases what run_operator gives."""
    rng = random.Random(3)
    made = {"imu": imu, "aoa": aoa}
    inputs = {
        port: [make_msg(s, f"{port}{k}") for k, s in enumerate(sorted(rng.randrange(0, 40, 5) for _ in range(40)))]
        for port, make_msg in made.items()
    }
    expected = calls(inputs)
    for seed in range(20):
        arrivals = [port for port, msgs in inputs.items() for _ in range(len(msgs) + 1)]
        random.Random(seed).shuffle(arrivals)
        merger, sent, seen = EventTimeMerger(list(inputs)), dict.fromkeys(inputs, 0), []
        for port in arrivals:
            if sent[port] < len(inputs[port]):
                msg = inputs[port][sent[port]]
                merger.push(port, stamp_ns(msg), msg)
                merger.watermark(port, stamp_ns(msg))
                sent[port] += 1
            else:
                merger.end(port)
            seen += [(p, s, m.header.frame_id) for p, s, m in merger.pop_ready()]
        assert seen == expected, seed


def test_an_input_the_operator_does_not_have_is_an_error():
    with pytest.raises(ValueError, match="Log has no input 'wheel'"):
        run_operator(Log(), {"wheel": []})
