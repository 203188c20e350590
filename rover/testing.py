"""Running one operator on lists of messages exactly as the runtime would, for tests and benchmarks.

The messages go through the runtime's own event-time merger (rover.runtime.scheduler), each
stamped with its header as a publisher stamps it: the operator sees them in (stamp, port name)
order, each port's messages in the order given, and then the end of every input. Like the runtime,
it hands the operator read-only copies (rover.frozen), or mutable ones on a `writable` port: an
operator that edits its input fails here as it would in a pipeline, and the caller's messages
are never changed.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from rover.frozen import freeze, thaw
from rover.messages import Raw, stamp_ns
from rover.operator import Emit, In, Operator
from rover.runtime.scheduler import EventTimeMerger


def run_operator(op: Operator, inputs: Mapping[str, Sequence[Any]], idle: bool = False) -> list[Emit]:
    """Deliver the messages of each input port to `op.on_input` in event-time order, then call `op.on_end`;
    return what it emitted, in order and as it emitted it. Only the ports given are wired, as in a
    pipeline that leaves the others unconnected; the operator's drops stay in `op.drops`. With
    `idle`, after each message `op.on_idle` is called for as long as it has work to do ahead
    (`has_idle_work`), as the runtime does while inputs come slower than they are handled."""
    ports = type(op).declared_ports(getattr(op, "params", None))
    specs: dict[str, In] = {}
    for port in inputs:
        if (spec := ports.input_spec(port)) is None:
            raise ValueError(f"{type(op).__name__} has no input {port!r}")
        specs[port] = spec
    merger = EventTimeMerger(list(inputs))
    for port, messages in inputs.items():
        spec = specs[port]
        for msg in messages:
            merger.push(port, stamp_ns(msg), _as_delivered(msg, spec))
        merger.end(port)
    out: list[Emit] = []
    for port, stamp, msg in merger.pop_ready():
        out.extend(op.on_input(port, msg, stamp) or ())
        while idle and op.has_idle_work():
            out.extend(op.on_idle() or ())
    out.extend(op.on_end() or ())
    return out


def _as_delivered(msg: Any, spec: In) -> Any:
    """What the runtime would hand the port: bytes as they are, else a copy, read-only unless writable."""
    if isinstance(msg, Raw):
        return msg
    return thaw(msg) if spec.writable else freeze(thaw(msg))
