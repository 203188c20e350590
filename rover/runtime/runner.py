"""Running a checked pipeline: operators on real Zenoh sessions, in event-time order.

One process runs every operator (or, with a host name, that host's share) on one Zenoh
session. Each operator has a thread and an inbox; the process's subscribers, one per key, only
enqueue, and the message is decoded once for all its consumers (rover/runtime/delivery.py). Sources start
once every host has declared its subscribers, so nothing is published into the void, and a
host leaves only when every host is done, so nothing in flight is cut off.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import queue
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from types import FrameType
from typing import Any

import zenoh

from rover.errors import BadInput, OperatorFailed, OutputFailed, PeerLost, RoverError, SpecError, TransportError
from rover.messages import Raw, cdr_stamp_ns, has_header, serialize, stamp_ns, typestore
from rover.operator import Emit, Operator, OperatorCounts, OperatorProfile, RunOutcome, Source, Watermark
from rover.pipeline.validation import Node, Pipeline, host_links
from rover.runtime.credit import Acks, Credits
from rover.runtime.delivery import Delivery, Fanout
from rover.runtime.hosts import HostWatch, attribute_to_hubs, describe_loss
from rover.runtime.inbox import Inbox, Policy
from rover.runtime.scheduler import INF, EventTimeMerger
from rover.runtime.status import HostStatus, OperatorStatus, status_key
from rover.security.acl import access_control
from rover.security.check import check_security
from rover.transport import codec, keys
from rover.transport.session import SessionSpec, TlsFiles, open_session

log = logging.getLogger("rover")
TLS_HINT = " Does it have the same ca.pem? `rover check PIPELINE --host H` on each machine checks its certificate)"
"""A TLS handshake refused (another CA, a certificate not naming the address) looks like a host that never comes."""

WATERMARK_INTERVAL_NS = 100_000_000
"""Event time between watermarks on an output that has nothing else to say."""
STOP_BUDGET_S = 1.6
"""After an interrupt, the time until the process has finished its outputs (the promise is 2 s)."""
DRAIN_S = 0.8
"""After an interrupt, how long operators may drain what is queued before the run is cut; the
rest of the budget is for finishing the outputs."""
JOIN_S = 0.3
"""After an interrupt cut the run, how long all threads together may take to leave their handlers;
an operator still in its handler then is not closed (its outputs are not finished)."""
LEAVE_S = 10.0
"""The same after a failure, where no time was promised."""
POLL_S = 0.05
_KNOWN = typestore.fielddefs
HUB_LINGER_S = 5.0
"""How long a hub, done, waits for the hosts behind it to leave first (their `done` tokens pass through it)."""
INBOX_DROP = "inbox full (a live source's oldest) or after the operator ended"

_SignalHandler = Callable[[int, FrameType | None], Any] | int | None
"""What signal.signal returns and takes back."""


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
        self.count = 0
        self.credits: Credits | None = None
        """flow control toward consumers on other hosts (None: none, or a live stream that must not wait)"""

    def send(self, payload: bytes, stamp: int) -> None:
        self.count += 1
        if self.credits is not None:
            self.credits.wait(self.count)
        self.publisher.put(payload, attachment=codec.attachment(codec.Kind.DATA, stamp, self.mark_ns))
        self.last_ns = max(self.last_ns, stamp)

    def promise(self, mark: int) -> None:
        """Nothing sent from now on is stamped before `mark`; rides on the next sample."""
        self.mark_ns = max(self.mark_ns, mark)

    def heartbeat(self) -> None:
        """Send the promise on its own when this port has been silent for a while of event time."""
        if self.mark_ns - self.last_ns >= WATERMARK_INTERVAL_NS:
            self.publisher.put(
                b"",
                encoding=codec.control_encoding(),
                attachment=codec.attachment(codec.Kind.WATERMARK, self.mark_ns, self.mark_ns),
            )
            self.last_ns = self.mark_ns

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
            waiting = time.perf_counter_ns()
            try:
                port, delivery = self.inbox.get(timeout=POLL_S)
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
            self.advance(merger.safe_time() - op.lateness_s * 1e9)
        self.handle(op.on_end, self.last_stamp())

    def last_stamp(self) -> int:
        """The latest stamp sent on any output, for what `on_end` emits without one (0 before any)."""
        sent = [o.last_ns for o in self.outputs.values() if o.last_ns != -INF]
        return int(max(sent)) if sent else 0


def _described(exc: Exception) -> str:
    """An exception in one line: our own errors by their message, others with their type."""
    return str(exc) if isinstance(exc, RoverError) else f"{type(exc).__name__}: {exc}"


def _report_drops(task: Task) -> None:
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


class _ProgressBar:
    """A progress bar on stderr for sources that know their length, only when stderr is a terminal."""

    def __init__(self, sources: list[Source]):
        self.sources = [s for s in sources if s.progress() is not None]
        self.progress = None
        if self.sources and sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

            self.progress = Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                transient=True,
            )
            self.ids = [self.progress.add_task("replay", total=(s.progress() or (0, 0))[1]) for s in self.sources]

    def update(self) -> None:
        if self.progress is not None:
            for task_id, source in zip(self.ids, self.sources, strict=True):
                self.progress.update(task_id, completed=(source.progress() or (0, 0))[0])

    def __enter__(self) -> _ProgressBar:
        if self.progress is not None:
            self.progress.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        if self.progress is not None:
            self.progress.stop()


class Runner:
    """Runs the operators of one host (or all of them) until end of stream or an interrupt."""

    def __init__(self, pipeline: Pipeline, host: str | None = None):
        self.pipeline = pipeline
        self.host = host
        self.distributed = host is not None and bool(pipeline.spec.hosts)
        self.nodes = [n for n in pipeline.nodes.values() if not self.distributed or n.spec.host == host]
        self.stop = threading.Event()
        self.abort = threading.Event()
        self.interrupted: int | None = None
        self.stopped_at: float | None = None
        """`time.monotonic()` of the first interrupt"""
        self.tasks: list[Task] = []
        self.watch: HostWatch | None = None
        self.state = "waiting"
        self.started = time.monotonic()

    def session_spec(self) -> SessionSpec:
        if not self.distributed or self.host is None:
            return SessionSpec()
        spec = self.pipeline.spec
        h = spec.hosts[self.host]
        if spec.security is None:
            return SessionSpec(h.listen, h.connect, h.host_timeout_s, self.host)
        ident = spec.security.hosts[self.host]
        tls = TlsFiles(spec.security.ca, ident.cert, ident.key)
        return SessionSpec(h.listen, h.connect, h.host_timeout_s, self.host, tls, access_control(spec, self.host))

    def request_stop(self, signum: int) -> None:
        """The first signal stops the run; later ones change nothing (the outputs are being finished).
        A later one must not touch the stop event either: it may interrupt the first one's `set`,
        which holds the event's lock (a second `set` would then wait for it forever)."""
        if self.stopped_at is not None:
            return
        self.stopped_at = time.monotonic()
        self.interrupted = signum
        self.stop.set()

    def run(self) -> int:
        """Run to the end; return the exit status (0, or 128 + signal after an interrupt).

        Every operator built is closed and, once the run began, told the outcome (`Operator.report`),
        whatever happened: a failed run raises its error afterwards, and an operator that cannot
        finish its outputs fails the run (`OutputFailed`). A run that never began (bad input found
        while building the operators) leaves the output folder as it was."""
        handlers = self._install_signals()
        try:
            return self._run_and_close()
        finally:
            for sig, old in handlers.items():
                signal.signal(sig, old)

    def _run_and_close(self) -> int:
        ops: dict[str, Operator] = {}
        error: RoverError | None = None
        began = False
        try:
            for node in self.nodes:
                ops[node.name] = self._build(node)
            with open_session(self.session_spec()) as session:
                if self.stop.is_set():  # stopped while starting: the earlier run's files stay as they were
                    return self._close(ops, RunOutcome("interrupted", self._stop_reason()), began)
                began = True
                self._start(ops)
                self._run(session, ops)
        except TransportError as exc:
            if not self.interrupted:
                error = exc
        except RoverError as exc:
            error = exc
        return self._close(ops, self._outcome(error), began, error)

    def _close(
        self, ops: dict[str, Operator], outcome: RunOutcome, began: bool, error: RoverError | None = None
    ) -> int:
        """Close every operator whose thread has left its handler, then (once the run began) tell each
        the final outcome; raise the run's error, or return its exit status."""
        alive = {t.name for t in self.tasks if t.thread.is_alive()}
        for name in sorted(alive):
            log.warning("operator %r is still in its handler: its outputs are not finished", name)
        closing = {name: op for name, op in ops.items() if name not in alive}
        # A run that never began writes nothing: its operators close as after a failure.
        closed_s: dict[str, float] = {}
        failures = self._each(closing, "close", outcome if began else replace(outcome, status="failed"), closed_s)
        for name, problem in failures if error is not None else ():
            log.error("operator %r failed to close: %s", name, problem)
        if failures and error is None:
            error = OutputFailed("; ".join(f"operator {name!r}: {problem}" for name, problem in failures))
            outcome = self._outcome(error)
        profile = {name: replace(p, close_s=closed_s.get(name, 0.0)) for name, p in outcome.profile.items()}
        outcome = replace(outcome, profile=profile)
        reported = self._each(closing, "report", outcome) if began else []
        if reported and error is None:
            error = OutputFailed("; ".join(f"operator {name!r}: {problem}" for name, problem in reported))
        elif reported:
            for name, problem in reported:
                log.error("operator %r could not report the run: %s", name, problem)
        if error is not None:
            raise error
        if outcome.status == "partial":
            raise PeerLost(f"host {self.host}: {outcome.reason}")
        return 128 + self.interrupted if outcome.status == "interrupted" and self.interrupted else 0

    @staticmethod
    def _build(node: Node) -> Operator:
        """The node's operator; a constructor that fails other than on bad input fails the run, in one line."""
        try:
            return node.build()
        except RoverError:
            raise
        except Exception as exc:  # noqa: BLE001 - a user's operator: reported like a failing handler
            raise OperatorFailed(
                f"operator {node.name!r} ({node.spec.uses}) failed to start: {_described(exc)}"
            ) from exc

    @staticmethod
    def _start(ops: dict[str, Operator]) -> None:
        """`start` every operator, even after one failed: each removes what an earlier run left, so
        a run that fails here leaves no stale result beside its run.json either."""
        failed: RoverError | None = None
        for name, op in ops.items():
            try:
                op.start()
            except RoverError as exc:
                failed = failed or exc
            except Exception as exc:  # noqa: BLE001 - a user's operator: reported like a failing handler
                failed = failed or OperatorFailed(f"operator {name!r} failed to start: {_described(exc)}")
        if failed is not None:
            raise failed

    def _outcome(self, error: RoverError | None) -> RunOutcome:
        return replace(self._ending(error), profile={t.name: t.clock.profile() for t in self.tasks})

    def _ending(self, error: RoverError | None) -> RunOutcome:
        counts = {t.name: t.stats.counts(t.op.drops) for t in self.tasks}
        if error is not None:
            return RunOutcome("failed", str(error), counts)
        if self.interrupted:
            deadline = (self.stopped_at or time.monotonic()) + STOP_BUDGET_S
            return RunOutcome("interrupted", self._stop_reason(), counts, deadline)
        links, me = host_links(self.pipeline.spec), self.host or ""
        lost, lost_at = (dict(self.watch.lost), dict(self.watch.lost_at)) if self.watch is not None else ({}, {})
        nodes = self.pipeline.nodes
        cut = {nodes[t.node.spec.inputs[port].source].spec.host or "" for t in self.tasks for port in t.cut_inputs}
        feeding = {nodes[w.source].spec.host for t in self.tasks for w in t.node.spec.inputs.values()}
        ended = {h for h in lost if h in feeding and h not in cut and lost[h].reason.startswith("stopped")}
        if ended == set(lost):  # every one stopped on purpose after the streams it sends here had ended
            lost = {}
        if lost or cut:
            if lost:
                reason = describe_loss(links, me, lost, lost_at)
            else:
                reason = f"the streams from {', '.join(sorted(cut))} ended early: a host upstream was stopped or lost"
            blamed = attribute_to_hubs(links, me, lost, lost_at)
            ordered = tuple(blamed[h] for h in sorted(lost, key=lambda h: (lost_at[h], h)))
            return RunOutcome("partial", f"results are partial: {reason}", counts, lost=ordered)
        return RunOutcome("complete", "", counts)

    def _stop_reason(self) -> str:
        return f"stopped by {signal.Signals(self.interrupted).name}" if self.interrupted else "stopped"

    @staticmethod
    def _each(
        ops: dict[str, Operator], hook: str, outcome: RunOutcome, took_s: dict[str, float] | None = None
    ) -> list[tuple[str, str]]:
        """Call `close` or `report` on every operator (each one's wall-clock seconds into `took_s`);
        the ones that raised, with their errors."""
        failed = []
        for name, op in ops.items():
            start = time.perf_counter()
            try:
                getattr(op, hook)(outcome)
            except Exception as exc:  # noqa: BLE001 - collected; the other operators still close
                failed.append((name, _described(exc)))
            if took_s is not None:
                took_s[name] = time.perf_counter() - start
        return failed

    def _install_signals(self) -> dict[signal.Signals, _SignalHandler]:
        if threading.current_thread() is not threading.main_thread():
            return {}
        old: dict[signal.Signals, _SignalHandler] = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, lambda signum, _frame: self.request_stop(signum))
        return old

    def _run(self, session: zenoh.Session, ops: dict[str, Operator]) -> None:
        name = self.pipeline.name
        args = (name, session, self.stop, self.abort)
        fanout = Fanout(session)
        try:
            # one at a time: what was built is undeclared and released in `finally` if a later one fails
            for n in self.nodes:
                if not issubclass(n.cls, Source):
                    self.tasks.append(OperatorTask(n, ops[n.name], *args, self._wire_types(n), self._policies(n)))
            for n in self.nodes:
                if issubclass(n.cls, Source):
                    self.tasks.append(SourceTask(n, ops[n.name], *args))
            threads = frozenset(t.thread for t in self.tasks)
            for task in self.tasks:
                if isinstance(task, OperatorTask):
                    task.local_threads = threads
                    task.subscribe(fanout, name)
            fanout.declare()
            if self.distributed:
                self._flow_control(session)
                self._run_with_hosts(session)
            else:
                self._start_and_wait()
        finally:
            self.abort.set()
            for task in self.tasks:  # a producer may wait on a consumer that never started or has stopped
                task.release()
            joined_by = time.monotonic() + (JOIN_S if self.interrupted else LEAVE_S)
            for task in self.tasks:
                if task.thread.ident is not None:
                    task.thread.join(timeout=max(0.0, joined_by - time.monotonic()))
            fanout.undeclare()
            for task in self.tasks:
                if not task.thread.is_alive():
                    task.undeclare()
            for task in self.tasks:
                queue_line = ""
                if isinstance(task, OperatorTask):
                    task.stats.dropped.update(task.inbox_drops())
                    queue_line = f"; queue high-water {task.inbox.high_water} of {task.inbox.capacity}"
                    if over := sum(task.inbox.overflowed.values()):
                        queue_line += f" ({over} from other hosts over the bound)"
                line = task.stats.line(task.name) + queue_line
                log.log(logging.WARNING if task.stats.dropped else logging.INFO, "%s", line)
                _report_drops(task)
        failed = next((t for t in self.tasks if t.error is not None), None)
        if failed is not None:
            exc = failed.error
            if isinstance(exc, (OperatorFailed, OutputFailed, BadInput)):
                raise exc
            raise OperatorFailed(
                f"operator {failed.name!r} ({failed.node.spec.uses}) failed: {type(exc).__name__}: {exc}"
            ) from exc

    def _wire_types(self, node: Node) -> dict[str, str]:
        """The declared type of the output each input port of `node` is wired to."""
        nodes = self.pipeline.nodes
        return {port: nodes[w.source].output_type(w.source_port) for port, w in node.spec.inputs.items()}

    def _live(self, name: str) -> bool:
        """Whether a live source feeds this operator's outputs (they must never wait)."""
        n = self.pipeline.nodes[name]
        if issubclass(n.cls, Source):
            return n.cls.is_live(n.params)
        return any(self._live(w.source) for w in n.spec.inputs.values())

    def _policies(self, node: Node) -> dict[str, Policy]:
        """Per input port: a stream that a live source feeds drops its oldest when the inbox is full;
        any other (a replay) makes its producer wait, so nothing is lost."""
        return {port: "drop_oldest" if self._live(w.source) else "block" for port, w in node.spec.inputs.items()}

    def _flow_control(self, session: zenoh.Session) -> None:
        """Credits on every output (not live) with consumers on other hosts; acks on every input fed
        from another host."""
        nodes, name = self.pipeline.nodes, self.pipeline.name
        for task in self.tasks:
            if isinstance(task, OperatorTask):
                remote = [p for p, w in task.node.spec.inputs.items() if nodes[w.source].spec.host != self.host]
                if remote:
                    task.acks = Acks(session, name, task.name, remote, max(1, task.inbox.capacity // 4))
            if self._live(task.name):
                continue
            for port, out in task.outputs.items():
                consumers = [(n, w) for n, w in self.pipeline.consumers(task.name, port) if n.spec.host != self.host]
                if consumers:
                    windows = {(n.name, w.port): n.spec.inbox for n, w in consumers}
                    hosts = {(n.name, w.port): n.spec.host or "" for n, w in consumers}
                    out.credits = Credits(session, name, windows, hosts, self.abort)

    def status(self) -> HostStatus:
        """This host's snapshot for `rover status`."""
        watch = self.watch
        operators = []
        for task in self.tasks:
            dropped = dict(task.stats.dropped)
            queue, high = 0, 0
            if isinstance(task, OperatorTask):
                queue, high = task.inbox.depth, task.inbox.high_water
                dropped.update(task.inbox_drops())
            operators.append(
                OperatorStatus(
                    task.name,
                    task.node.spec.uses,
                    dict(task.stats.received),
                    dict(task.stats.sent),
                    dropped,
                    queue,
                    high,
                    task.handled_ns,
                    task.input_ns,
                    _described(task.error) if isinstance(task.error, Exception) else "",
                )
            )
        now_ns = time.time_ns()  # this host's clock as it answers: `rover status` measures its offset
        return HostStatus(
            self.pipeline.name,
            self.host or "",
            self.state,
            sorted(watch.waiting_for()) if watch else [],
            watch.lost_hosts() if watch else [],
            time.monotonic() - self.started,
            now_ns / 1e9,
            operators,
            now_ns,
        )

    def _answer_status(self, query: zenoh.Query) -> None:
        with contextlib.suppress(zenoh.ZError):
            query.reply(status_key(self.pipeline.name, self.host or ""), self.status().to_json())

    def _run_with_hosts(self, session: zenoh.Session) -> None:
        """Start once every host has subscribed; leave once every host is done or lost. A lost host's
        streams are ended here (`OperatorTask.cut`), so the operators finish on what they have."""
        assert self.host is not None, "a distributed run has a host"
        spec = self.pipeline.spec.hosts[self.host]
        wanted = self.pipeline.hosts_in_use()
        timeouts = {name: h.host_timeout_s for name, h in self.pipeline.spec.hosts.items()}
        self.watch = watch = HostWatch(session, self.pipeline.name, self.host, timeouts, self.pipeline.digest())
        watch.on_lost = self._cut_streams_of
        status: zenoh.Queryable[None] | None = None
        try:
            status = session.declare_queryable(status_key(self.pipeline.name, self.host), self._answer_status)
            watch.declare("ready")
            hint = f" ({self.host} connects to {', '.join(spec.connect)}: is the host listening there running?"
            hint = hint + ")" if self.pipeline.spec.security is None else hint + TLS_HINT
            if not watch.wait_ready(wanted, self.stop, spec.wait_timeout_s, hint if spec.connect else ""):
                return
            self.state = "running"
            self._start_and_wait()
            stopped = self.stop.is_set()
            # A host stopped before its input ended is not done: the others report it lost. One whose
            # streams all ended (live sources stopped: the end of a live session) is done.
            clean = not stopped or self._ended_cleanly()
            log.debug("host %s: tasks ended (stopped: %s, every stream ended: %s)", self.host, stopped, clean)
            if clean:
                self.state = "finishing"
                watch.declare("done")
                if not stopped:
                    watch.wait_done(wanted, self.stop)
                behind = self.pipeline.hubs().get(self.host)
                if behind and (stopped or not self.stop.is_set()):
                    watch.wait_gone(behind, HUB_LINGER_S)  # their last messages pass through this one
            self.state = "done"
        finally:
            self._say_bye()
            if status is not None:
                status.undeclare()
            watch.close()

    def _ended_cleanly(self) -> bool:
        """Every task of this host ended its outputs at the end of its input (none cut, nothing aborted)."""
        return not self.abort.is_set() and not any(task.ended_cut for task in self.tasks)

    def _say_bye(self) -> None:
        """After a signal, tell the other hosts why this one leaves (once, as early as possible)."""
        if self.interrupted and self.watch is not None and not self.watch.said_bye:
            with contextlib.suppress(zenoh.ZError):
                self.watch.say_bye(self._stop_reason())

    def _cut_streams_of(self, host: str) -> None:
        """End every input stream that comes from an operator on `host`, and stop waiting for credit
        from the consumers there."""
        nodes = self.pipeline.nodes
        for task in self.tasks:
            for out in task.outputs.values():
                if out.credits is not None:
                    out.credits.host_lost(host)
            if isinstance(task, OperatorTask):
                for port, wire in task.node.spec.inputs.items():
                    if nodes[wire.source].spec.host == host:
                        task.cut(port)

    def _start_and_wait(self) -> None:
        for task in self.tasks:
            task.thread.start()
        self._wait_tasks()

    def _wait_tasks(self) -> None:
        deadline = None
        with _ProgressBar([t.op for t in self.tasks if isinstance(t, SourceTask)]) as bar:
            while not all(t.done.is_set() for t in self.tasks):
                if self.stop.is_set() and deadline is None:
                    deadline = (self.stopped_at or time.monotonic()) + DRAIN_S
                    self._say_bye()
                if deadline is not None and time.monotonic() > deadline:
                    self.abort.set()
                    break
                bar.update()
                time.sleep(POLL_S)


def run(pipeline: Pipeline, host: str | None = None) -> int:
    """Run a checked pipeline (all of it, or one host's share); return the exit status."""
    if host is not None and pipeline.spec.hosts and host not in pipeline.spec.hosts:
        raise BadInput(
            f"{pipeline.spec.file}: --host {host!r} is not declared under hosts: ({', '.join(pipeline.spec.hosts)})"
        )
    if host is not None and pipeline.spec.security is not None:
        problems, warnings = check_security(pipeline.spec, [host])
        for line in warnings:
            log.warning("%s", line)
        if problems:
            raise SpecError(problems)
    return Runner(pipeline, host).run()
