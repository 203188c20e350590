"""The operator model: declared typed ports, typed params, and pure handlers.

An operator never touches the transport or files: the runtime delivers each input message
to `on_input` in event-time order and publishes what the handler yields. Sources (drivers
at the edge of the graph) yield messages from `run` instead.
"""

from __future__ import annotations

import dataclasses
import re
import threading
import time
from collections import Counter
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, NamedTuple

from rover.errors import OperatorDefinitionError
from rover.messages import ANY, known_type


@dataclass(frozen=True)
class In:
    """An input port: its message type, whether it must be wired, whether it gets raw CDR bytes, and
    whether it gets a mutable message of its own (`writable`) instead of the read-only one the
    process's other consumers of the stream share (rover.frozen)."""

    type: str
    required: bool = True
    raw: bool = False
    doc: str = ""
    writable: bool = False


@dataclass(frozen=True)
class Out:
    """An output port and its message type."""

    type: str
    doc: str = ""


@dataclass(frozen=True)
class Ports:
    """An operator's ports once its params are known: the class's own, or those its params declare
    (a bridge whose topics are params). `variadic` takes any input name."""

    inputs: Mapping[str, In]
    outputs: Mapping[str, Out]
    variadic: In | None = None
    known: bool = True
    """False when params that name the ports failed their own checks: wiring is then not judged"""

    def input_spec(self, port: str) -> In | None:
        return self.inputs.get(port) or self.variadic

    def problems(self) -> list[str]:
        """What is wrong with these ports: a bad name, an unknown message type, an untyped output."""
        found = []
        for kind, ports in (("input", self.inputs), ("output", self.outputs)):
            for name, port in ports.items():
                if not (isinstance(name, str) and PORT_NAME_RE.match(name)):
                    found.append(f"{kind} name {name!r} must start with a letter and use letters, digits or _")
                elif not known_type(port.type):
                    found.append(f"{kind} {name!r}: unknown message type {port.type!r}")
                elif kind == "output" and port.type == ANY:
                    found.append(f"output {name!r} needs a concrete type")
        for name, port in [*self.inputs.items(), *([("*", self.variadic)] if self.variadic else [])]:
            if port.raw and port.writable:
                found.append(f"input {name!r}: a raw port gets bytes, not a message: raw excludes writable")
        if self.variadic is not None and not known_type(self.variadic.type):
            found.append(f"inputs of any name: unknown message type {self.variadic.type!r}")
        return found


PORT_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


class Emit(NamedTuple):
    """A message an operator sends on one of its output ports; `stamp_ns` defaults to the header stamp."""

    port: str
    msg: Any
    stamp_ns: int | None = None


class Watermark(NamedTuple):
    """A promise from a source: nothing it sends later is stamped before `stamp_ns`."""

    stamp_ns: int


@dataclass(frozen=True)
class NoParams:
    """Parameters of an operator that takes none."""


@dataclass(frozen=True)
class RunContext:
    """What an operator may know of the run it is part of: set by the runtime, empty when called in a test."""

    pipeline_file: str = ""
    pipeline_name: str = ""
    command_line: Mapping[str, Any] = field(default_factory=dict)
    """what the command line changed: {"vars": {...}, "params": {"OPERATOR.PARAM": value}}"""


RunStatus = Literal["complete", "partial", "interrupted", "failed"]
"""How a run ended: to the end of its input; without a host that left; stopped by a signal; failed."""


@dataclass(frozen=True)
class OperatorCounts:
    """What one operator received, sent and dropped, per port (drops per `port:reason`, or per the
    reason the operator gave `Operator.drop`)."""

    received: Mapping[str, int] = field(default_factory=dict)
    sent: Mapping[str, int] = field(default_factory=dict)
    dropped: Mapping[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class OperatorProfile:
    """Where one operator's thread spent its wall-clock seconds, so a run shows where time goes.

    The parts add up to the thread's life. In one process the operators' threads share the
    interpreter: time another thread held it counts where this one was waiting for it."""

    decode_s: float = 0.0
    """deserializing its inputs"""
    handler_s: float = 0.0
    """its handler (a source: producing its items, a wait on a device included)"""
    encode_s: float = 0.0
    """serializing what it emitted"""
    send_s: float = 0.0
    """putting that on Zenoh: in one process this runs the subscribers' enqueue, which waits while
    an inbox downstream is full; toward another host it waits for credit"""
    idle_s: float = 0.0
    """waiting for input (its inbox empty)"""
    runtime_s: float = 0.0
    """the rest: attachments, event-time merging, watermarks, bookkeeping"""
    close_s: float = 0.0
    """its `close` after the run (finishing outputs, figures), in the main thread"""
    cpu_s: float = 0.0
    """the CPU time its thread used: far below its busy parts when it mostly waited for the
    interpreter, or for a device"""


@dataclass(frozen=True)
class LostHost:
    """A host of a distributed run that left before it was done, as this host saw it."""

    host: str
    reason: str
    time: str
    """UTC, ISO 8601, when this host noticed"""


@dataclass(frozen=True)
class RunOutcome:
    """How the run ended, given to `Operator.close` and `Operator.report`."""

    status: RunStatus = "complete"
    reason: str = ""
    counts: Mapping[str, OperatorCounts] = field(default_factory=dict)
    """per operator of this process, and of the other hosts that reported theirs (`hosts`)"""
    deadline: float | None = None
    """`time.monotonic()` by which closing must be done (after an interrupt); None: no limit"""
    lost: tuple[LostHost, ...] = ()
    """the hosts lost during a `partial` run"""
    profile: Mapping[str, OperatorProfile] = field(default_factory=dict)
    """per operator that ran, as `counts`, where its time went (`close_s` is filled in for `report`,
    for this process's operators)"""
    hosts: Mapping[str, str] = field(default_factory=dict)
    """in a run across hosts (or worker processes), the host of each operator in `counts`"""

    @property
    def keeps_outputs(self) -> bool:
        """Outputs are finished and kept unless the run failed (an interrupted run keeps what it has)."""
        return self.status != "failed"

    def time_left_s(self) -> float:
        """Seconds left before the deadline (infinite without one)."""
        return float("inf") if self.deadline is None else self.deadline - time.monotonic()


COMPLETE = RunOutcome()
"""The outcome of a run that reached the end of its input (the default of `Operator.close`)."""


class Operator:
    """Base class of every operator.

    Subclasses declare `inputs`, `outputs` and a `Params` dataclass, and implement `on_input`.
    `variadic` accepts input ports under any name with the given spec (recorders).
    `lateness_s` bounds how far before the input being handled an output may be stamped
    (the runtime sends watermarks that much behind). What a handler discards it counts with
    `drop`; the runtime reports the counts at the end of the run.
    """

    inputs: ClassVar[Mapping[str, In]] = {}
    outputs: ClassVar[Mapping[str, Out]] = {}
    variadic: ClassVar[In | None] = None
    Params: ClassVar[type] = NoParams
    lateness_s: ClassVar[float] = 0.0
    cpu_weight: ClassVar[float] = 1.0
    """the CPU seconds this operator takes per minute of a typical dataset (bench/bench_end_to_end.py's
    profile): how operators are spread over worker processes before a run has measured them"""
    folder_param: ClassVar[str | None] = None
    """the param naming a folder this operator writes: operators writing one folder share a process"""
    context: RunContext = RunContext()
    """the run this operator is part of (pipeline file, command-line settings)"""

    _drops: Counter[str]

    def __init__(self, params: Any = None) -> None:
        self.params = params if params is not None else self.Params()

    @property
    def drops(self) -> Counter[str]:
        """What this operator dropped so far, per reason (made on first use: subclasses need not call
        `Operator.__init__`)."""
        try:
            return self._drops
        except AttributeError:
            self._drops = Counter()
            return self._drops

    def drop(self, reason: str, count: int = 1) -> None:
        """Count `count` messages dropped for `reason`, a plural noun phrase that reads after the count
        ("AoAs without an IMU epoch"); the runtime reports each reason once, at the end of the run."""
        if count > 0:
            self.drops[reason] += count

    def on_input(self, port: str, msg: Any, stamp_ns: int) -> Iterable[Emit]:
        """Handle one message; yield or return the messages to send."""
        return ()

    def held_since_ns(self) -> float | None:
        """The stamp of the earliest input this operator holds without having sent what it makes of
        it (math.inf: it holds none), for an operator that batches its inputs: the runtime then
        promises downstream exactly that no output comes before it, instead of `lateness_s` behind
        the input (None, the default: it does not say). Outputs must not be stamped before the
        inputs they come from."""
        return None

    def has_idle_work(self) -> bool:
        """Whether the operator has work it can do ahead, while nothing waits (`on_idle`), that it
        would otherwise do in a later handler: the SLAM's tag search steps. Done while the operator
        would wait, it does not hold up the next input (default: none)."""
        return False

    def on_idle(self) -> Iterable[Emit]:
        """Called while the operator holds inputs (`held_since_ns`) or has work to do ahead
        (`has_idle_work`), and has nothing more to handle: it may send what it holds, as
        `csi_decode` decodes its batch (live, frames trickle in; a batch that waited for the next
        dwell would hold every AoA and pose behind it), or do a bounded part of that work (it is
        called again while nothing waits). Only for what is for speed: what it sends must not
        depend on when it is called."""
        return ()

    def on_end(self) -> Iterable[Emit]:
        """All inputs reached end of stream: flush what is pending."""
        return ()

    def start(self) -> None:
        """Called once before the first message, when every operator of the run was built: an
        operator that writes files removes what a previous run left there that it would overwrite."""

    def close(self, outcome: RunOutcome = COMPLETE) -> None:
        """Release resources and finish outputs; called once at the end of the run. When the run
        failed (`not outcome.keeps_outputs`) outputs are discarded rather than left half-written.
        Raising here fails the run."""

    def report(self, outcome: RunOutcome) -> None:
        """Called once after every operator closed, with the run's final outcome (a failure to
        close fails the run): write a description of the run, or remove outputs of a failed one."""

    @classmethod
    def input_spec(cls, port: str) -> In | None:
        return cls.inputs.get(port) or cls.variadic

    @classmethod
    def declared_ports(cls, params: Any) -> Ports:
        """The ports of an operator with these (checked) params: the class's by default. An operator
        whose ports are named by its params (a ROS 2 bridge's topics) overrides this; the pipeline
        check then validates wiring and types against them, as for declared ones. Raise ValueError
        with a message naming the param for params that declare no valid ports."""
        return Ports(cls.inputs, cls.outputs, cls.variadic)

    @classmethod
    def check_definition(cls) -> None:
        """Raise OperatorDefinitionError when the class's declarations are inconsistent."""
        if not (isinstance(cls.Params, type) and dataclasses.is_dataclass(cls.Params)):
            raise OperatorDefinitionError(f"{cls.__qualname__}.Params must be a dataclass")
        for problem in Ports(cls.inputs, cls.outputs, cls.variadic).problems():
            raise OperatorDefinitionError(f"{cls.__qualname__}: {problem}")


class Source(Operator):
    """An operator with no inputs that produces messages (dataset replay, live drivers).

    `run` yields Emit items in non-decreasing stamp order, and Watermark items when it is
    silent, until it is exhausted or `stop` is set. A `live` source (a device) cannot wait for
    slow consumers: their inboxes drop its oldest messages when full (counted); any other source
    (a file) is made to wait, so nothing is lost.
    """

    live: ClassVar[bool] = False

    @classmethod
    def is_live(cls, params: Any) -> bool:
        """Whether a source with these params reads a device (or a growing file) rather than a file."""
        return cls.live

    def run(self, stop: threading.Event) -> Iterator[Emit | Watermark]:
        raise NotImplementedError

    def span_ns(self) -> tuple[int, int] | None:
        """(first, last) event time this source will emit, when it knows it before it starts (a
        replay): the run's progress is the event time its last stages reach within this span."""
        return None
