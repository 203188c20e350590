"""Running a checked pipeline: operators on real Zenoh sessions, in event-time order.

One process runs every operator (or, with a host name, that host's share) on one Zenoh
session. Each operator has a thread and an inbox; the process's subscribers, one per key, only
enqueue, and the message is decoded once for all its consumers (rover/runtime/delivery.py). Sources start
once every host has declared its subscribers, so nothing is published into the void, and a
host leaves only when every host is done, so nothing in flight is cut off.

What runs in each operator's thread is in rover/runtime/tasks.py; what one host says to and hears
from the others, in rover/runtime/host_protocol.py.
"""

from __future__ import annotations

import gc
import logging
import math
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from types import FrameType
from typing import Any

import zenoh

from rover.errors import BadInput, OperatorFailed, OutputFailed, PeerLost, RoverError, SpecError, TransportError
from rover.operator import Operator, RunOutcome, Source
from rover.pipeline.validation import Node, Pipeline, host_links
from rover.runtime.delivery import Fanout
from rover.runtime.host_protocol import HostProtocol
from rover.runtime.hosts import attribute_to_hubs, describe_loss
from rover.runtime.inbox import Policy
from rover.runtime.progress import RunProgress
from rover.runtime.status import HostStatus
from rover.runtime.tasks import POLL_S, OperatorTask, SourceTask, Task, described, report_drops
from rover.security.acl import access_control
from rover.security.check import check_security
from rover.transport.session import SessionSpec, TlsFiles, open_session

log = logging.getLogger("rover")

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

_SignalHandler = Callable[[int, FrameType | None], Any] | int | None
"""What signal.signal returns and takes back."""


class Runner:
    """Runs the operators of one host (or all of them) until end of stream or an interrupt."""

    def __init__(self, pipeline: Pipeline, host: str | None = None, progress: bool = True):
        self.pipeline = pipeline
        self.host = host
        self.progress = progress
        """whether to show the run's progress on stderr (`rover -q` does not)"""
        self.distributed = host is not None and bool(pipeline.spec.hosts)
        self.nodes = [n for n in pipeline.nodes.values() if not self.distributed or n.spec.host == host]
        self.stop = threading.Event()
        self.abort = threading.Event()
        self.interrupted: int | None = None
        self.stopped_at: float | None = None
        """`time.monotonic()` of the first interrupt"""
        self.tasks: list[Task] = []
        self.hosts = HostProtocol(pipeline, host, self.tasks, self.stop, self.abort, self._signal_reason)
        """this host's part beside the others (a distributed run), and its `rover status`"""

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
                f"operator {node.name!r} ({node.spec.uses}) failed to start: {described(exc)}"
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
                failed = failed or OperatorFailed(f"operator {name!r} failed to start: {described(exc)}")
        if failed is not None:
            raise failed

    def _outcome(self, error: RoverError | None) -> RunOutcome:
        """How the run ended, with the counts and profiles of this host's operators and of the other
        hosts' that reported them."""
        ending = self._ending(error)
        counts, profile = dict(ending.counts), {t.name: t.clock.profile() for t in self.tasks}
        hosts = {t.name: self.host for t in self.tasks} if self.distributed and self.host else {}
        for host, report in self.hosts.reports.items():
            counts |= report.counts
            profile |= report.profile
            hosts |= dict.fromkeys(report.counts, host)
        return replace(ending, counts=counts, profile=profile, hosts=hosts)

    def _ending(self, error: RoverError | None) -> RunOutcome:
        counts = {t.name: t.stats.counts(t.op.drops) for t in self.tasks}
        if error is not None:
            return RunOutcome("failed", str(error), counts)
        if self.interrupted:
            deadline = (self.stopped_at or time.monotonic()) + STOP_BUDGET_S
            return RunOutcome("interrupted", self._stop_reason(), counts, deadline)
        links, me = host_links(self.pipeline.spec), self.host or ""
        watch = self.hosts.watch
        lost, lost_at = (dict(watch.lost), dict(watch.lost_at)) if watch is not None else ({}, {})
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

    def _signal_reason(self) -> str | None:
        """Why a signal stopped this host (what it tells the others), None while none did."""
        return self._stop_reason() if self.interrupted else None

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
                failed.append((name, described(exc)))
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
                self.hosts.flow_control(session, self._live)
                self.hosts.run(session, self._start_and_wait)
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
            # after an interrupt what was still queued is dropped by design: one line says so, -v each
            stopped = bool(self.interrupted)
            dropped_at_stop = 0
            for task in self.tasks:
                queue_line = ""
                if isinstance(task, OperatorTask):
                    task.stats.dropped.update(task.inbox_drops())
                    queue_line = f"; queue high-water {task.inbox.high_water} of {task.inbox.capacity}"
                    if over := sum(task.inbox.overflowed.values()):
                        queue_line += f" ({over} from other hosts over the bound)"
                line = task.stats.line(task.name) + queue_line
                loud = task.stats.dropped and not stopped
                dropped_at_stop += sum(task.stats.dropped.values()) if stopped else 0
                log.log(logging.WARNING if loud else logging.INFO, "%s", line)
                report_drops(task)
            if dropped_at_stop:
                log.warning(
                    "stopped: %d message(s) still queued or in flight were dropped (-v lists them per operator)",
                    dropped_at_stop,
                )
        failed = next((t for t in self.tasks if t.error is not None), None)
        if failed is not None:
            exc = failed.error
            if isinstance(exc, (OperatorFailed, OutputFailed, BadInput)):
                raise exc
            log.info("operator %r failed:", failed.name, exc_info=exc)  # its traceback, shown with -v
            hint = "" if log.isEnabledFor(logging.INFO) else " (-v prints its traceback)"
            raise OperatorFailed(
                f"operator {failed.name!r} ({failed.node.spec.uses}) failed: {type(exc).__name__}: {exc}{hint}"
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

    def status(self) -> HostStatus:
        """This host's snapshot for `rover status`."""
        return self.hosts.status()

    def _reached(self) -> float:
        """Event time this host's last stages (those no task here feeds) have finished with."""
        fed = {w.source for t in self.tasks for w in t.node.spec.inputs.values()}
        last = [t for t in self.tasks if t.name not in fed]
        return min((math.inf if t.done.is_set() else t.reached_ns) for t in last) if last else math.inf

    def _start_and_wait(self) -> None:
        # What was built to run (modules, operators, the session) lives until the end: kept out of
        # the collector's full passes, which otherwise walk all of it mid-run (74-167 ms a pass on
        # a live host, measured: longer than a dwell). Garbage first, so none is kept for good.
        gc.collect()
        gc.freeze()
        for task in self.tasks:
            task.thread.start()
        self._wait_tasks()

    def _wait_tasks(self) -> None:
        deadline = None
        sources = [t.op for t in self.tasks if isinstance(t, SourceTask)] if self.progress else []
        with RunProgress(sources, self._reached) as bar:
            while not all(t.done.is_set() for t in self.tasks):
                if self.stop.is_set() and deadline is None:
                    deadline = (self.stopped_at or time.monotonic()) + DRAIN_S
                    self.hosts.say_bye()
                if deadline is not None and time.monotonic() > deadline:
                    self.abort.set()
                    break
                bar.update()
                time.sleep(POLL_S)


def run(
    pipeline: Pipeline, host: str | None = None, progress: bool = True, on_running: Callable[[], None] | None = None
) -> int:
    """Run a checked pipeline (all of it, or one host's share); return the exit status. `progress`:
    show how far it has got on stderr; `on_running`: called once every host has subscribed (a
    distributed run), as this one starts its operators."""
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
    runner = Runner(pipeline, host, progress)
    if on_running is not None:
        runner.hosts.on_running = on_running
    return runner.run()
