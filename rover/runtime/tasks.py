"""What runs one operator or source in its own thread: its inputs taken in event-time order, its
outputs published with their watermarks, and what it received, sent, dropped and spent its time on.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import zenoh

from rover.errors import OperatorFailed, RoverError
from rover.messages import Raw, cdr_stamp_ns, has_header, serialize, stamp_ns, typestore
from rover.operator import Emit, Operator, OperatorCounts, OperatorProfile, Source, Watermark
from rover.pipeline.validation import Node
from rover.runtime.credit import Acks, Credits
from rover.runtime.delivery import Delivery, Fanout
from rover.runtime.inbox import Inbox, Policy
from rover.runtime.scheduler import INF, EventTimeMerger
from rover.transport import codec, keys

log = logging.getLogger("rover")

WATERMARK_INTERVAL_NS = 100_000_000
"""Event time between watermarks on an output that has nothing else to say."""
POLL_S = 0.05
_KNOWN = typestore.fielddefs
INBOX_DROP = "inbox full (a live source's oldest) or after the operator ended"


@dataclass
class Stats:
    """What one operator received, sent and dropped, per port."""

    received: Counter[str] = field(default_factory=Counter)
    sent: Counter[str] = field(default_factory=Counter)
    dropped: Counter[str] = field(default_factory=Counter)
    late: Counter[str] = field(default_factory=Counter)

    def counts(self, operator_drops: Counter[str]) -> OperatorCounts:
        """A copy for the run's outcome, with the operator's own drops by reason."""
        return OperatorCounts(dict(self.received), dict(self.sent), {**self.dropped, **operator_drops})

    def line(self, name: str) -> str:
        def fmt(c: Counter[str]) -> str:
            return ", ".join(f"{k}={v}" for k, v in sorted(c.items())) or "-"

        text = f"{name}: in {fmt(self.received)}; out {fmt(self.sent)}"
        if self.dropped:
            text += f"; DROPPED {fmt(self.dropped)}"
        if self.late:
            text += f"; late {fmt(self.late)}"
        return text


@dataclass
class Clock:
    """A task's wall-clock nanoseconds by part (see OperatorProfile), kept by its own thread."""

    decode: int = 0
    handler: int = 0
    encode: int = 0
    send: int = 0
    idle: int = 0
    started: int = 0
    ended: int = 0
    cpu: int = 0
    """the thread's CPU time when it ended (time.thread_time_ns)"""

    def profile(self) -> OperatorProfile:
        """The parts in seconds; the runtime's share is what the others leave of the thread's life."""
        life = (self.ended or time.perf_counter_ns()) - self.started if self.started else 0
        rest = life - (self.decode + self.handler + self.encode + self.send + self.idle)
        return OperatorProfile(
            decode_s=self.decode / 1e9,
            handler_s=self.handler / 1e9,
            encode_s=self.encode / 1e9,
            send_s=self.send / 1e9,
            idle_s=self.idle / 1e9,
            runtime_s=max(rest, 0) / 1e9,
            cpu_s=self.cpu / 1e9,
        )


class Output:
    """One output port: its publisher, and the watermark promised on it so far."""

    def __init__(self, session: zenoh.Session, key: str, typename: str):
        self.key = key
        self.typename = typename
        self.publisher = session.declare_publisher(
            key,
            encoding=codec.encoding(typename),
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
        self.last_ns: float = -INF
        self.mark_ns: int = -(2**63)
        self.sent_mark_ns: int = self.mark_ns
        """the promise the last message on this port carried"""
        self.count = 0
        self.credits: Credits | None = None
        """flow control toward consumers on other hosts (None: none, or a live stream that must not wait)"""

    def send(self, payload: bytes, stamp: int) -> None:
        self.count += 1
        if self.credits is not None:
            self.credits.wait(self.count)
        self.publisher.put(payload, attachment=codec.attachment(codec.Kind.DATA, stamp, self.mark_ns))
        self.last_ns = max(self.last_ns, stamp)
        self.sent_mark_ns = self.mark_ns

    def promise(self, mark: int) -> None:
        """Nothing sent from now on is stamped before `mark`; rides on the next sample."""
        self.mark_ns = max(self.mark_ns, mark)

    def heartbeat(self) -> None:
        """Send the promise on its own when this port has been silent for a while of event time."""
        if self.mark_ns - self.last_ns >= WATERMARK_INTERVAL_NS:
            self._send_mark()

    def idle(self) -> None:
        """Send the promise on its own if it moved on since the last message: the operator has
        nothing more to handle, and a consumer may be waiting for this promise to go on (a live
        pose waits for the AoAs' promise to pass its IMU epoch)."""
        if self.mark_ns > self.sent_mark_ns:
            self._send_mark()

    def _send_mark(self) -> None:
        self.publisher.put(
            b"",
            encoding=codec.control_encoding(),
            attachment=codec.attachment(codec.Kind.WATERMARK, self.mark_ns, self.mark_ns),
        )
        self.last_ns = max(self.last_ns, self.mark_ns)
        self.sent_mark_ns = self.mark_ns

    def end(self, cut: bool) -> None:
        """End of stream; `cut` when it ends before the end of the input (a stop, a lost host upstream)."""
        last = int(self.last_ns) if self.last_ns != -INF else 0
        kind = codec.Kind.CUT if cut else codec.Kind.END
        att = codec.attachment(kind, last, self.mark_ns)
        self.publisher.put(b"", encoding=codec.control_encoding(), attachment=att)


class Task:
    """An operator (or source) running in its own thread."""

    def __init__(
        self,
        node: Node,
        op: Operator,
        pipeline: str,
        session: zenoh.Session,
        stop: threading.Event,
        abort: threading.Event,
    ):
        self.node = node
        self.name = node.name
        self.op = op
        self.stats = Stats()
        self.clock = Clock()
        self.stop = stop
        self.abort = abort
        self.error: BaseException | None = None
        self.cut_inputs: set[str] = set()
        """input ports whose stream was cut short (its producer stopped, or its host was lost)"""
        self.handled_ns: int | None = None
        """stamp of the last message handled (for `rover status`)"""
        self.input_ns: int | None = None
        """latest stamp received on any input"""
        self.reached_ns: float = -INF
        """event time this task has finished with: nothing it handles later is stamped before it
        (inf once its inputs have ended), for the run's progress"""
        self.done = threading.Event()
        self.ended_cut = False
        """whether its outputs ended cut short (decided once, when the task ended)"""
        self.outputs = {
            port: Output(session, keys.port_key(pipeline, node.name, port), out.type)
            for port, out in node.ports.outputs.items()
        }
        self.thread = threading.Thread(target=self._main, name=f"rover-{node.name}", daemon=True)

    def _main(self) -> None:
        self.clock.started = time.perf_counter_ns()
        try:
            self.run()
        except BaseException as exc:  # noqa: BLE001 - reported by the runner as one line
            self.error = exc
            self.stop.set()
        finally:
            cut = self.ended_cut = self.cut_short()
            self.release()  # first: sending the ends may wait on a congested link
            for out in self.outputs.values():
                with contextlib.suppress(zenoh.ZError):
                    out.end(cut)
            self.clock.ended, self.clock.cpu = time.perf_counter_ns(), time.thread_time_ns()
            self.done.set()

    def cut_short(self) -> bool:
        """Whether this task's outputs end before the end of its input: it failed, the run was aborted,
        or an input was cut. A stop alone is not a cut: operators drain what their inputs sent."""
        return self.error is not None or self.abort.is_set() or bool(self.cut_inputs)

    def undeclare(self) -> None:
        """Withdraw this task's publishers (and subscribers) before the session closes: a router
        whose neighbour closes with entities still declared may panic unregistering them
        (Zenoh 1.10, `unregister_router_entities`)."""
        for out in self.outputs.values():
            with contextlib.suppress(zenoh.ZError):
                out.publisher.undeclare()
                if out.credits is not None:
                    out.credits.close()

    def release(self) -> None:
        """Let go of what producers may be waiting on, once this task handles nothing more."""

    def run(self) -> None:
        raise NotImplementedError

    def handle(self, handler: Callable[[], Iterable[Emit] | None], default_stamp: int) -> None:
        """Call a handler and `publish` what it returned, its time counted as the handler's (less the
        encoding and sending): a handler may be a generator, whose work happens as `publish` draws."""
        clock = self.clock
        start, coded = time.perf_counter_ns(), clock.encode + clock.send
        self.publish(handler(), default_stamp)
        clock.handler += time.perf_counter_ns() - start - (clock.encode + clock.send - coded)

    def publish(self, emitted: Iterable[Emit] | None, default_stamp: int) -> None:
        clock = self.clock
        for item in emitted or ():
            port, msg, stamp = item
            out = self.outputs.get(port)
            if out is None:
                raise OperatorFailed(f"operator {self.name!r} emitted on unknown output {port!r}")
            typename = msg.typename if isinstance(msg, Raw) else getattr(msg, "__msgtype__", None)
            if typename != out.typename:
                raise OperatorFailed(
                    f"operator {self.name!r} emitted {typename} on output {port!r}, which is declared {out.typename}"
                )
            if stamp is None:
                stamp = stamp_ns(msg) if has_header(typename) else default_stamp
            if stamp < out.mark_ns:
                self.stats.late[port] += 1
            start = time.perf_counter_ns()
            payload = serialize(msg, typename)
            encoded = time.perf_counter_ns()
            out.send(payload, stamp)
            clock.encode += encoded - start
            clock.send += time.perf_counter_ns() - encoded
            self.stats.sent[port] += 1

    def advance(self, mark: float) -> None:
        if mark == INF or mark == -INF:
            return
        for out in self.outputs.values():
            out.promise(int(mark))
            out.heartbeat()


class SourceTask(Task):
    """Drives a source. Its items come in stamp order, so each stamp is also a promise on every port."""

    op: Source

    def cut_short(self) -> bool:
        """A file stopped before its end is cut; a live source (a device, a growing log) stopped by the
        run's stop has simply ended: a live session ends when its sources are stopped."""
        stopped = self.stop.is_set() and not self.op.is_live(self.op.params)
        return super().cut_short() or stopped

    def run(self) -> None:
        clock = 0
        items = iter(self.op.run(self.stop))
        while True:
            start = time.perf_counter_ns()
            item = next(items, None)
            self.clock.handler += time.perf_counter_ns() - start
            if item is None or self.abort.is_set():
                break
            if isinstance(item, Watermark):
                clock = max(clock, item.stamp_ns)
            else:
                stamp = item.stamp_ns if item.stamp_ns is not None else stamp_ns(item.msg)
                clock = max(clock, stamp)
                self.handled_ns = self.input_ns = clock
                for out in self.outputs.values():
                    out.promise(clock)
                self.publish((item._replace(stamp_ns=stamp),), clock)
            self.advance(clock)
            if isinstance(item, Watermark):  # the source waits now: its promise goes out at once
                for out in self.outputs.values():
                    out.idle()
            self.reached_ns = clock
            if self.stop.is_set():
                break
        self.handle(self.op.on_end, clock)


class OperatorTask(Task):
    """Runs an operator's handler on its inputs, in event-time order. `wire_types` is the declared
    type of the output each input port is wired to: anything else on that key is dropped."""

    def __init__(
        self,
        node: Node,
        op: Operator,
        pipeline: str,
        session: zenoh.Session,
        stop: threading.Event,
        abort: threading.Event,
        wire_types: dict[str, str],
        policies: dict[str, Policy],
    ):
        super().__init__(node, op, pipeline, session, stop, abort)
        self.wire_types = wire_types
        self.policies = policies
        self.acks: Acks | None = None
        """acknowledgements of what was taken on inputs fed from other hosts (flow control)"""
        self.local_threads: frozenset[threading.Thread] = frozenset()
        """the threads of this process's tasks: their puts may wait on a full inbox for as long as it takes"""
        self.inbox: Inbox[Delivery] = Inbox(node.spec.inbox)
        self.merger = EventTimeMerger(list(node.spec.inputs))
        self.ports = {port: spec for port in node.spec.inputs if (spec := node.ports.input_spec(port)) is not None}

    def subscribe(self, fanout: Fanout, pipeline: str) -> None:
        """Have the process's subscribers hand this task every sample of each of its inputs."""
        for port, wire in self.node.spec.inputs.items():
            fanout.add(keys.port_key(pipeline, wire.source, wire.source_port), self._enqueue_for(port))

    def _enqueue_for(self, port: str) -> Callable[[Delivery], None]:
        inbox, policy = self.inbox, self.policies[port]

        def enqueue(delivery: Delivery) -> None:
            """Runs in the producer's thread (in one process), where a full inbox makes it wait; or in
            Zenoh's receive thread (from another host), which never waits: the producer there waits
            for credit instead (`rover/runtime/credit.py`), so the inbox does not overflow."""
            local = threading.current_thread() in self.local_threads
            control = codec.is_control(delivery.attachment)
            inbox.put(port, delivery, control=control, policy=policy, max_wait_s=None if local else 0.0)

        return enqueue

    def _drop(self, port: str, reason: str) -> None:
        self.stats.dropped[f"{port}:{reason}"] += 1
        n = self.stats.dropped[f"{port}:{reason}"]
        if n == 1 or n % 1000 == 0:
            log.warning("operator %r, input %r: dropped %d message(s): %s", self.name, port, n, reason)

    def release(self) -> None:
        self.inbox.close()

    def undeclare(self) -> None:
        if self.acks is not None:
            with contextlib.suppress(zenoh.ZError):
                self.acks.close()
        super().undeclare()

    def inbox_drops(self) -> dict[str, int]:
        """What the inbox dropped (a live source's oldest, or anything after this task ended), keyed
        like the stats' own drops."""
        return {f"{port}:{INBOX_DROP}": n for port, n in self.inbox.dropped.items()}

    def cut(self, port: str) -> None:
        """End an input's stream here: its producer's host was lost (what is queued is still handled)."""
        self.inbox.put(port, Delivery("", b"", codec.attachment(codec.Kind.CUT, 0, 0)), control=True)

    def _accept(self, port: str, delivery: Delivery) -> None:
        try:
            kind, stamp, mark = codec.read_attachment(delivery.attachment)
        except codec.CodecError as exc:
            self._drop(port, str(exc))
            return
        if kind in (codec.Kind.END, codec.Kind.CUT):
            if kind == codec.Kind.CUT and not self.merger.ended(port):
                self.cut_inputs.add(port)
            self.merger.end(port)
            return
        if self.merger.ended(port):
            self._drop(port, "after the end of its stream (its host was lost)")
            return
        self.merger.watermark(port, mark)
        if kind == codec.Kind.WATERMARK:
            return
        spec = self.ports[port]
        typename = codec.schema_of(delivery.encoding)
        if typename != self.wire_types[port]:
            self._drop(port, f"type {typename or 'unknown'} where {self.wire_types[port]} was expected")
            return
        start = time.perf_counter_ns()
        if spec.raw:
            payload = delivery.payload
            msg = Raw(typename, payload) if _plausible_cdr(payload, typename, stamp) else None
        elif spec.writable:
            msg = delivery.private_message(typename)
        else:
            msg = delivery.message(typename)
        self.clock.decode += time.perf_counter_ns() - start
        if msg is None:
            self._drop(port, f"bytes that do not decode as {typename or spec.type}")
            return
        self.stats.received[port] += 1
        self.input_ns = stamp if self.input_ns is None else max(self.input_ns, stamp)
        self.merger.push(port, stamp, msg)

    def run(self) -> None:
        merger = self.merger
        op = self.op
        while not merger.finished:
            if self.abort.is_set():
                return
            try:
                port, delivery = self.inbox.get(timeout=0.0)
            except queue.Empty:
                more = self.idle()
                waiting = time.perf_counter_ns()
                try:
                    port, delivery = self.inbox.get(timeout=0.0 if more else POLL_S)
                except queue.Empty:
                    continue
                finally:
                    self.clock.idle += time.perf_counter_ns() - waiting
            if self.acks is not None and not codec.is_control(delivery.attachment):
                self.acks.took(port)
            self._accept(port, delivery)
            for port, stamp, msg in merger.pop_ready():
                if self.abort.is_set():
                    return
                self.handle(functools.partial(op.on_input, port, msg, stamp), stamp)
                self.handled_ns = stamp
            self.reached_ns = merger.safe_time()
            self.promise()
        self.handle(op.on_end, self.last_stamp())

    def promise(self) -> None:
        """Promise on every output what the operator can still send: from what it holds, when it
        says (`held_since_ns`), else `lateness_s` behind what its inputs reached."""
        held = self.op.held_since_ns()
        self.advance(self.reached_ns - self.op.lateness_s * 1e9 if held is None else min(self.reached_ns, held))

    def idle(self) -> bool:
        """Nothing to handle: an operator holding inputs may send them, or do a part of its work
        ahead (`on_idle`), and promises that moved on since their port's last message go out on
        their own. Returns whether the operator has more work to do ahead (the caller then looks
        for an input again at once, instead of waiting for one)."""
        held = self.op.held_since_ns()
        if (held is not None and held != INF) or self.op.has_idle_work():
            self.handle(self.op.on_idle, self.last_stamp())
            self.promise()
        for out in self.outputs.values():
            out.idle()
        return self.op.has_idle_work()

    def last_stamp(self) -> int:
        """The latest stamp sent on any output, for what `on_end` emits without one (0 before any)."""
        sent = [o.last_ns for o in self.outputs.values() if o.last_ns != -INF]
        return int(max(sent)) if sent else 0


def described(exc: Exception) -> str:
    """An exception in one line: our own errors by their message, others with their type."""
    return str(exc) if isinstance(exc, RoverError) else f"{type(exc).__name__}: {exc}"


def report_drops(task: Task) -> None:
    """One warning per reason the operator gave `Operator.drop`, like the per-input drops of the runtime.
    A copy of the counts: a thread cut off at the end of the run may still be counting."""
    for reason, n in sorted(dict(task.op.drops).items()):
        log.warning("operator %r: dropped %d %s", task.name, n, reason)


def _plausible_cdr(payload: bytes, typename: str, stamp: int) -> bool:
    """Cheap check for pass-through ports that never decode: a CDR encapsulation header and, for
    types with a header, a header stamp no later than the event time in the attachment (an output
    may carry an older header, as SLAM's final poses do when they leave the window)."""
    if len(payload) < 4 or payload[:2] not in (b"\x00\x00", b"\x00\x01") or typename not in _KNOWN:
        return False
    if has_header(typename):
        return len(payload) >= 16 and cdr_stamp_ns(payload) <= stamp
    return True
