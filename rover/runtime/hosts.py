"""The hosts of a distributed run as one host sees them: waiting for them, and noticing the ones lost.

Every host declares a liveliness token when it is ready (its subscribers declared) and another when
it is done, and watches everybody's. Zenoh withdraws a process's tokens when it exits, crashes, or
stays unreachable past the transport lease (`host_timeout_s`), so a `ready` token withdrawn before
its `done` is a lost host. When the host that the others reach each other through (the hub) goes,
everybody behind it goes with it; `describe_loss` says so from the link graph of the pipeline file.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Collection, Mapping
from datetime import UTC, datetime

import zenoh

from rover.errors import TransportError
from rover.operator import LostHost
from rover.pipeline.validation import unreachable_without
from rover.transport import keys

log = logging.getLogger("rover")

POLL_S = 0.05
WAIT_LOG_FIRST_S = 2.0
"""A host that waits says so after this long (a normal start takes less), then every WAIT_LOG_S."""
WAIT_LOG_S = 5.0


Links = Mapping[str, Collection[str]]
"""host -> the hosts it talks to directly"""
SAME_LOSS_S = 2.0
"""Hosts lost this soon before a hub (or after it) went with it; earlier ones were lost on their own."""


def behind_hub(links: Links, me: str, hub: str, lost_at: Mapping[str, float]) -> list[str]:
    """The hosts `me` no longer reaches since `hub` went, leaving out those lost well before it."""
    cut = unreachable_without(links, me, hub)
    return sorted(h for h in cut if lost_at.get(h, math.inf) >= lost_at[hub] - SAME_LOSS_S)


def attribute_to_hubs(
    links: Links, me: str, lost: Mapping[str, LostHost], lost_at: Mapping[str, float]
) -> dict[str, LostHost]:
    """The lost hosts; those that went with a hub get that as their reason (they may well be running)."""
    out = dict(lost)
    for hub in sorted(lost, key=lambda h: (lost_at[h], h)):
        for name in behind_hub(links, me, hub, lost_at):
            if name in lost and out[name] is lost[name]:
                out[name] = LostHost(name, f"unreachable once hub {hub} was lost", lost[name].time)
    return out


def describe_loss(links: Links, me: str, lost: Mapping[str, LostHost], lost_at: Mapping[str, float]) -> str:
    """One sentence for the lost hosts: a hub with the hosts that became unreachable with it (lost
    with it, or done before it went), then the hosts lost on their own."""
    explained: set[str] = set()
    parts = []
    for name in sorted(lost, key=lambda h: (lost_at[h], h)):
        if name in explained:
            continue
        behind = behind_hub(links, me, name, lost_at)
        if behind:
            explained |= {name, *behind}
            parts.append(
                f"hub {name} was lost ({lost[name].reason}); host{'s' if len(behind) > 1 else ''} "
                f"{', '.join(behind)} became unreachable with it"
            )
    alone = sorted(set(lost) - explained, key=lambda h: (lost_at[h], h))
    parts += [f"host {name} was lost ({lost[name].reason})" for name in alone]
    return "; ".join(parts)


class HostWatch:
    """Presence of every host of one run, from this host's session. `host_timeouts`: each host's
    `host_timeout_s`, the lease it announces (how long the others wait for it), for messages."""

    def __init__(
        self,
        session: zenoh.Session,
        pipeline: str,
        me: str,
        host_timeouts: Mapping[str, float],
        digest: str,
    ):
        self.session = session
        self.pipeline = pipeline
        self.me = me
        self.hosts = set(host_timeouts)
        self.host_timeouts = dict(host_timeouts)
        self.digest = digest
        self.zid = str(session.zid())
        self.ready: dict[str, str] = {}
        """host -> the zid of the process that is that host"""
        self.claims: dict[str, list[str]] = {}
        """host -> every process (zid) with a `ready` token for it, in order: the first is the host"""
        self.done: set[str] = set()
        self.gone: set[str] = set()
        """hosts that were done and have left"""
        self.lost: dict[str, LostHost] = {}
        self.lost_at: dict[str, float] = {}
        """`time.monotonic()` when each lost host was noticed"""
        self.byes: dict[str, str] = {}
        self.reports: dict[str, bytes] = {}
        """host -> what it put on its `report` key (rover/runtime/host_report.py)"""
        self.running = False
        self.said_bye = False
        self.on_lost: Callable[[str], None] = lambda _host: None
        self._wanted: set[str] = set(self.hosts)
        self._warned: set[str] = set()
        self._cond = threading.Condition()
        self._tokens: list[zenoh.LivelinessToken] = []
        # Both in Zenoh's own thread (not indirect), so a `bye` is handled before the withdrawal behind it.
        on_token = zenoh.handlers.Callback(self._on_token, indirect=False)
        on_put = zenoh.handlers.Callback(self._on_put, indirect=False)
        self._subscribers = [
            session.liveliness().declare_subscriber(keys.host_tokens(pipeline), on_token, history=True),
            session.declare_subscriber(keys.host_tokens(pipeline), on_put),
        ]

    def lost_hosts(self) -> list[str]:
        with self._cond:
            return sorted(self.lost)

    def _key(self, state: str) -> str:
        return keys.host_token(self.pipeline, keys.HostKey(self.me, self.digest, self.zid, state))

    def declare(self, state: str) -> None:
        log.debug("host %s: declares %s", self.me, state)
        self._tokens.append(self.session.liveliness().declare_token(self._key(state)))

    def say_bye(self, reason: str) -> None:
        """Tell the others why this host leaves (they then report it, not a crash): sent ahead of
        the data still queued, so it is there before the tokens are withdrawn."""
        self.said_bye = True
        self.session.put(
            self._key("bye"),
            reason.encode(),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.REAL_TIME,
            express=True,
        )

    def say_report(self, report: bytes) -> None:
        """Tell the others what this host's operators did (before its `done`)."""
        self.session.put(self._key("report"), report, congestion_control=zenoh.CongestionControl.BLOCK)

    def wait_reports(self, hosts: Collection[str], timeout_s: float) -> dict[str, bytes]:
        """The reports of `hosts` (this one left out), waiting at most `timeout_s` for the missing ones."""
        deadline = time.monotonic() + timeout_s
        others = set(hosts) - {self.me}
        with self._cond:
            while not others <= set(self.reports) and time.monotonic() < deadline:
                self._cond.wait(timeout=POLL_S)
            return {h: r for h, r in self.reports.items() if h in others}

    def close(self) -> None:
        for token in self._tokens:
            token.undeclare()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._tokens, self._subscribers = [], []

    def _parse(self, key: str) -> keys.HostKey | None:
        """The key's parts when it comes from a host of this run; others are reported once and ignored."""
        parsed = keys.parse_host_token(self.pipeline, key)
        if parsed is not None and parsed.host in self.hosts and parsed.digest == self.digest:
            return parsed
        if key not in self._warned:
            self._warned.add(key)
            log.warning(
                "host %s: ignored the presence token %s: not from a host of this run (another pipeline, "
                "another version of this one, or a process that is not Rover)",
                self.me,
                key,
            )
        return None

    def _on_put(self, sample: zenoh.Sample) -> None:
        parsed = self._parse(str(sample.key_expr))
        if parsed is None or parsed.state not in ("bye", "report"):
            return
        with self._cond:
            if self.ready.get(parsed.host) != parsed.zid:
                return
            if parsed.state == "report":
                self.reports[parsed.host] = sample.payload.to_bytes()
                self._cond.notify_all()
                return
            reason = " ".join(sample.payload.to_bytes().decode("utf-8", "replace").split())[:200]
            self.byes[parsed.host] = reason or "stopped"

    def _on_token(self, sample: zenoh.Sample) -> None:
        parsed = self._parse(str(sample.key_expr))
        if parsed is None or parsed.zid == self.zid:
            return
        if parsed.host == self.me:
            if parsed.state == "ready" and sample.kind == zenoh.SampleKind.PUT:
                log.warning("host %s: another process (zid %s) also runs as this host: ignored", self.me, parsed.zid)
            return
        with self._cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self._put(parsed)
                lost_now = None
            else:
                lost_now = self._withdrawn(parsed)
            self._cond.notify_all()
        if lost_now is not None:
            log.warning("host %s: host %s was lost (%s)", self.me, lost_now, self.lost[lost_now].reason)
            self.on_lost(lost_now)

    def _put(self, parsed: keys.HostKey) -> None:
        host, zid = parsed.host, parsed.zid
        log.debug("host %s: sees host %s %s (zid %s)", self.me, host, parsed.state, zid)
        if parsed.state == "done":
            if self.ready.get(host) == zid:
                self.done.add(host)
            return
        if parsed.state != "ready":
            return
        claims = self.claims.setdefault(host, [])
        if zid not in claims:
            claims.append(zid)
        if host in self.lost:
            log.warning("host %s: host %s is back, but its streams were cut: it stays out of this run", self.me, host)
        elif host not in self.ready:
            self.ready[host] = zid
        elif self.ready[host] != zid:
            log.warning(
                "host %s: a second process (zid %s) claims host %s: ignored while the first one is there",
                self.me,
                zid,
                host,
            )

    def _withdrawn(self, parsed: keys.HostKey) -> str | None:
        """A `ready` token withdrawn: a host gone after done, lost during the run, or (before the run)
        replaced by the next process that claims it; returns the host when it is lost."""
        host, zid = parsed.host, parsed.zid
        log.debug("host %s: sees host %s withdraw %s (zid %s)", self.me, host, parsed.state, zid)
        if parsed.state != "ready":
            return None
        claims = self.claims.get(host, [])
        if zid in claims:
            claims.remove(zid)
        if self.ready.get(host) != zid:
            return None
        if host in self.done:
            self.gone.add(host)
            return None
        if self.running:
            reason = self.byes.get(host) or (
                "gone without a word: it crashed, or was unreachable for more than "
                f"{self.host_timeouts.get(host, 0):g} s (its host_timeout_s)"
            )
            self.lost[host] = LostHost(host, reason, datetime.now(UTC).isoformat(timespec="seconds"))
            self.lost_at[host] = time.monotonic()
            return host
        del self.ready[host]
        if claims:
            self.ready[host] = claims[0]
            log.warning("host %s: process %s takes over as host %s", self.me, claims[0], host)
        else:
            log.warning("host %s: host %s left before the run began; waiting for it again", self.me, host)
        return None

    def waiting_for(self) -> set[str]:
        """The hosts not ready yet (before the run) or not done yet (after this host's part ended)."""
        with self._cond:
            wanted = self._wanted
            pending = wanted - set(self.ready) if not self.running else wanted - self.done - set(self.lost)
            return pending - {self.me}

    def wait_ready(self, wanted: Collection[str], stop: threading.Event, timeout_s: float, hint: str) -> bool:
        """Wait until every wanted host is ready, saying whom it waits for; False when stopped first.
        Raises TransportError naming the missing hosts after `timeout_s`."""
        self._wanted = set(wanted)
        started = time.monotonic()
        next_log = started + WAIT_LOG_FIRST_S
        with self._cond:
            while not set(wanted) - {self.me} <= set(self.ready):
                if stop.is_set():
                    return False
                missing = ", ".join(sorted(set(wanted) - set(self.ready) - {self.me}))
                waited = time.monotonic() - started
                if waited > timeout_s:
                    raise TransportError(
                        f"host {self.me}: gave up after {timeout_s:g} s (wait_timeout_s) waiting for host(s) "
                        f"{missing}{hint}"
                    )
                if time.monotonic() > next_log:
                    log.warning("host %s: waiting for host(s) %s (%.0f s of %g s)", self.me, missing, waited, timeout_s)
                    next_log += WAIT_LOG_S
                self._cond.wait(timeout=POLL_S)
            self.running = True
        return True

    def wait_done(self, wanted: Collection[str], stop: threading.Event) -> None:
        """Wait until every wanted host that was not lost is done (or this host is stopped)."""
        with self._cond:
            while not set(wanted) - {self.me} - set(self.lost) <= self.done and not stop.is_set():
                self._cond.wait(timeout=POLL_S)

    def wait_gone(self, hosts: Collection[str], timeout_s: float) -> None:
        """Wait (at most `timeout_s`) until these hosts have left: a hub stays until the hosts behind
        it have seen everybody done, since their `done` tokens travel through it."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not set(hosts) - {self.me} <= self.gone | set(self.lost) and time.monotonic() < deadline:
                self._cond.wait(timeout=POLL_S)
