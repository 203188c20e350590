"""One host's part in a distributed run, beside the others: it starts once every host has declared
its subscribers and leaves once every host is done or lost, ends the streams of a lost host, says
why it leaves after a signal, keeps flow control on the links between hosts, and answers
`rover status`. Who is there, and who was lost, is the HostWatch's (rover/runtime/hosts.py).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

import zenoh

from rover.pipeline.validation import Pipeline
from rover.runtime import host_report
from rover.runtime.credit import Acks, Credits
from rover.runtime.host_report import HostReport, ReportError
from rover.runtime.hosts import HostWatch
from rover.runtime.status import HostStatus, OperatorStatus, status_key
from rover.runtime.tasks import OperatorTask, Task, described

log = logging.getLogger("rover")
TLS_HINT = " Does it have the same ca.pem? `rover check PIPELINE --host H` on each machine checks its certificate)"
"""A TLS handshake refused (another CA, a certificate not naming the address) looks like a host that never comes."""
REPORT_WAIT_S = 2.0
"""How long a host, everybody done, waits for the reports of the others (put before their `done`)."""
HUB_LINGER_S = 5.0
"""How long a hub, done, waits for the hosts behind it to leave first (their `done` tokens pass through it)."""


class HostProtocol:
    """What one host of a run says to and hears from the others, owned by its Runner. `tasks`: the
    runner's tasks (the list it fills as it builds them); `stop_reason`: why a signal stopped this
    host, None while none did."""

    def __init__(
        self,
        pipeline: Pipeline,
        host: str | None,
        tasks: Sequence[Task],
        stop: threading.Event,
        abort: threading.Event,
        stop_reason: Callable[[], str | None],
    ):
        self.pipeline = pipeline
        self.host = host
        self.tasks = tasks
        self.stop = stop
        self.abort = abort
        self.stop_reason = stop_reason
        self.watch: HostWatch | None = None
        self.state = "waiting"
        self.started = time.monotonic()
        self.on_running: Callable[[], None] = lambda: None
        """called once every host has subscribed, as this one starts its tasks"""
        self.reports: dict[str, HostReport] = {}
        """what the other hosts' operators did, by host (those that ended well and reported)"""

    def flow_control(self, session: zenoh.Session, live: Callable[[str], bool]) -> None:
        """Credits on every output (not live) with consumers on other hosts; acks on every input fed
        from another host."""
        nodes, name = self.pipeline.nodes, self.pipeline.name
        for task in self.tasks:
            if isinstance(task, OperatorTask):
                remote = [p for p, w in task.node.spec.inputs.items() if nodes[w.source].spec.host != self.host]
                if remote:
                    task.acks = Acks(session, name, task.name, remote, max(1, task.inbox.capacity // 4))
            if live(task.name):
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
                    described(task.error) if isinstance(task.error, Exception) else "",
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

    def run(self, session: zenoh.Session, start_and_wait: Callable[[], None]) -> None:
        """Start once every host has subscribed; leave once every host is done or lost. A lost host's
        streams are ended here (`OperatorTask.cut`), so the operators finish on what they have.
        `start_and_wait` starts this host's tasks and returns when they have ended (or were cut)."""
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
            self.on_running()
            start_and_wait()
            stopped = self.stop.is_set()
            # A host stopped before its input ended is not done: the others report it lost. One whose
            # streams all ended (live sources stopped: the end of a live session) is done.
            clean = not stopped or self._ended_cleanly()
            log.debug("host %s: tasks ended (stopped: %s, every stream ended: %s)", self.host, stopped, clean)
            if clean:
                self.state = "finishing"
                watch.say_report(host_report.encode(self._report()))
                watch.declare("done")
                if not stopped:
                    watch.wait_done(wanted, self.stop)
                    self._read_reports(watch.wait_reports(watch.done, REPORT_WAIT_S), watch.done)
                behind = self.pipeline.hubs().get(self.host)
                if behind and (stopped or not self.stop.is_set()):
                    watch.wait_gone(behind, HUB_LINGER_S)  # their last messages pass through this one
            self.state = "done"
        finally:
            self.say_bye()
            if status is not None:
                status.undeclare()
            watch.close()

    def _report(self) -> HostReport:
        """What this host's operators received, sent and dropped, and where their time went."""
        counts = {}
        for task in self.tasks:
            c = task.stats.counts(task.op.drops)
            if isinstance(task, OperatorTask):
                c = replace(c, dropped={**c.dropped, **task.inbox_drops()})
            counts[task.name] = c
        return HostReport(counts, {task.name: task.clock.profile() for task in self.tasks})

    def _read_reports(self, payloads: dict[str, bytes], done: set[str]) -> None:
        """The other hosts' reports, each only for operators placed on it; one that cannot be read is left out."""
        placed = {name: node.spec.host for name, node in self.pipeline.nodes.items()}
        for host, payload in sorted(payloads.items()):
            try:
                report = host_report.decode(payload)
            except ReportError as exc:
                log.warning("host %s: the report of host %s is left out of run.json: %s", self.host, host, exc)
                continue
            if any(placed.get(name) != host for name in report.counts):
                log.warning(
                    "host %s: the report of host %s names operators not placed there: left out", self.host, host
                )
                continue
            self.reports[host] = report
        for host in sorted(done - set(self.reports)):
            log.info("host %s: no report from host %s: its operators are not in run.json", self.host, host)

    def _ended_cleanly(self) -> bool:
        """Every task of this host ended its outputs at the end of its input (none cut, nothing aborted)."""
        return not self.abort.is_set() and not any(task.ended_cut for task in self.tasks)

    def say_bye(self) -> None:
        """After a signal, tell the other hosts why this one leaves (once, as early as possible)."""
        reason = self.stop_reason()
        if reason is not None and self.watch is not None and not self.watch.said_bye:
            with contextlib.suppress(zenoh.ZError):
                self.watch.say_bye(reason)

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
