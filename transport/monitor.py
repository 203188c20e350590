"""Asking the hosts of a running pipeline for their status, as a Zenoh client of any one of them.

The client connects to one reachable endpoint (explicit endpoints only, no scouting); that host's
router forwards the query to every host of the pipeline, so one connection sees them all.

Each query also measures every answering host's clock against this machine's (`StatusClient.poll`,
`rover.runtime.status.clock_offset`): reported, not corrected.
"""

from __future__ import annotations

import json
import logging
import re
import time
from dataclasses import dataclass
from types import TracebackType

import zenoh

from rover.errors import TransportError
from rover.runtime.status import Clocks, HostStatus, clock_offset, read_reply, status_selector
from rover.transport.session import TlsFiles, tls_config

log = logging.getLogger("rover.status")

RETRY_S = 0.1
"""pause between two rounds of connection attempts while the timeout lasts"""
WILDCARDS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}


def local_endpoint(endpoint: str) -> str:
    """A listen endpoint as a client reaches it: a wildcard address (0.0.0.0, [::]) becomes loopback."""
    match = re.match(r"^([a-z-]+/)(0\.0\.0\.0|\[::\])(:.*)$", endpoint)
    return f"{match[1]}{WILDCARDS[match[2]]}{match[3]}" if match else endpoint


@dataclass(frozen=True)
class Reply:
    """One host's answer to a status query and when it travelled, on this machine's wall clock."""

    payload: bytes
    sent_ns: int
    """just before the query went out"""
    received_ns: int
    """when this reply arrived"""


def _client_config(endpoints: list[str], open_timeout_s: float, tls: TlsFiles | None = None) -> zenoh.Config:
    """Client mode, scouting off. One attempt per endpoint (`timeout_ms` 0): with a longer timeout a
    client keeps retrying the first endpoint alone and never tries the others; we retry ourselves."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/timeout_ms", "0")
    conf.insert_json5("connect/exit_on_failure", "true")
    conf.insert_json5("transport/unicast/open_timeout", str(max(1, int(open_timeout_s * 1000))))
    if tls is not None:
        tls_config(conf, tls, listen=False)
    return conf


class StatusClient:
    """One Zenoh session to a running pipeline, opened once and queried at every refresh.

    Opening retries every endpoint until `timeout_s`; when none is reachable it raises the same
    TransportError as a query nobody answers (`no_answer`). The same `timeout_s`, counted from the
    start, bounds `first_poll`'s wait for a first answer."""

    def __init__(self, pipeline: str, endpoints: list[str], timeout_s: float = 5.0, tls: TlsFiles | None = None):
        self.pipeline = pipeline
        self.tls = tls
        """the monitor's identity, for a pipeline under security:"""
        self.endpoints = list(endpoints)
        self.timeout_s = timeout_s
        self.errors = 0
        """error replies to the last query"""
        self.clocks = Clocks()
        """each host's clock offset from this machine's, measured by `poll`"""
        self._deadline = time.monotonic() + timeout_s
        self._session = self._open()

    def _open(self) -> zenoh.Session:
        while True:
            try:
                timeout_s = max(self._deadline - time.monotonic(), RETRY_S)
                return zenoh.open(_client_config(self.endpoints, timeout_s, self.tls))
            except zenoh.ZError as exc:
                log.debug("cannot connect to %s: %s", ", ".join(self.endpoints), exc)
            self.wait_to_retry()

    def wait_to_retry(self) -> None:
        """Wait a retry's pause, or raise `no_answer` when the timeout would pass during it."""
        if time.monotonic() + RETRY_S >= self._deadline:
            raise self.no_answer()
        time.sleep(RETRY_S)

    def no_answer(self) -> TransportError:
        """The error for a pipeline none of whose hosts answered."""
        return TransportError(
            f"no host of pipeline {self.pipeline} answered at {', '.join(self.endpoints)} (is it running?)"
        )

    def query(self) -> list[bytes]:
        """Every host's status payload (possibly none); error replies are left out and counted in `errors`."""
        return [reply.payload for reply in self.query_timed()]

    def query_timed(self) -> list[Reply]:
        """`query`, each payload with this machine's wall clock as the query left and as it arrived.

        The replies are taken from the channel one by one as they come, each stamped then (not when
        the whole query ends); the time between the two stamps comes from the monotonic clock, so a
        step of the wall clock during the query cannot make it negative."""
        out: list[Reply] = []
        errors = 0
        try:
            sent_ns, start = time.time_ns(), time.monotonic_ns()
            replies = self._session.get(
                status_selector(self.pipeline),
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
                timeout=self.timeout_s,
            )
            for reply in replies:
                received_ns = sent_ns + time.monotonic_ns() - start
                if reply.ok is not None:
                    out.append(Reply(reply.ok.payload.to_bytes(), sent_ns, received_ns))
                else:
                    errors += 1
        except zenoh.ZError as exc:
            raise TransportError(f"querying {', '.join(self.endpoints)}: {str(exc).split(' at /')[0]}") from None
        self.errors = errors
        return out

    def poll(self) -> tuple[dict[str, HostStatus], list[str]]:
        """Every answering host's status by host, and a note for each reply that could not be used
        (as `collect`); each host's clock offset from this machine's goes into `clocks`."""
        statuses: dict[str, HostStatus] = {}
        notes: list[str] = []
        for reply in self.query_timed():
            status = read_reply(reply.payload, self.pipeline)
            if isinstance(status, str):
                notes.append(status)
                continue
            statuses[status.host] = status
            if status.clock_ns is None:
                notes.append(f"host {status.host} does not send its clock (an older rover): its offset is unknown")
            else:
                self.clocks.add(status.host, clock_offset(status.clock_ns, reply.sent_ns, reply.received_ns))
        return statuses, notes

    def first_poll(self) -> tuple[dict[str, HostStatus], list[str]]:
        """`poll` until some host answers; `no_answer` once the timeout has passed without one.

        A host's router accepts connections a moment before the host declares its status (it is
        still building its operators then): a query in between is answered by nobody at once,
        which is not yet "nobody is running"."""
        while True:
            statuses, notes = self.poll()
            if statuses:
                return statuses, notes
            self.wait_to_retry()

    def close(self) -> None:
        self._session.close()

    def __enter__(self) -> StatusClient:
        return self

    def __exit__(
        self, _type: type[BaseException] | None, _value: BaseException | None, _tb: TracebackType | None
    ) -> None:
        self.close()


def query_status(pipeline: str, endpoints: list[str], timeout_s: float) -> list[bytes]:
    """The status payloads of a pipeline's hosts, asked until one answers; TransportError when
    none has within `timeout_s`."""
    with StatusClient(pipeline, endpoints, timeout_s) as client:
        while True:
            payloads = client.query()
            if payloads:
                return payloads
            client.wait_to_retry()
