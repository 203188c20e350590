"""Flow control between hosts: an output sends at most a window of messages ahead of what each
consumer on another host has taken from its inbox.

Within one process a full inbox makes the publisher's own thread wait. Across hosts the sample
arrives in Zenoh's receive thread, which must never wait: it also carries the link's watermarks,
ends, presence tokens and keep-alives, and a link it froze would be closed. So each consumer on
another host acknowledges what it took (`Acks`), and the producer waits for credit (`Credits`) in
its own thread instead. The window is the consumer's inbox size: its inbox never overflows.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping

import zenoh

from rover.transport import keys

POLL_S = 0.05


class Credits:
    """The acknowledgements one output waits on, per remote consumer input `(operator, port)`."""

    def __init__(
        self,
        session: zenoh.Session,
        pipeline: str,
        windows: Mapping[tuple[str, str], int],
        hosts: Mapping[tuple[str, str], str],
        abort: threading.Event,
    ):
        self._windows = dict(windows)
        self._hosts = dict(hosts)
        self._acked = dict.fromkeys(windows, 0)
        self._abort = abort
        self._cond = threading.Condition()
        self._subscribers = [
            session.declare_subscriber(
                keys.ack_key(pipeline, *consumer), zenoh.handlers.Callback(self._on_ack(consumer), indirect=False)
            )
            for consumer in windows
        ]

    def _on_ack(self, consumer: tuple[str, str]) -> Callable[[zenoh.Sample], None]:
        def on_ack(sample: zenoh.Sample) -> None:
            try:
                taken = int(sample.payload.to_bytes())
            except ValueError:
                return
            with self._cond:
                if consumer in self._acked and taken > self._acked[consumer]:
                    self._acked[consumer] = taken
                    self._cond.notify_all()

        return on_ack

    def wait(self, number: int) -> None:
        """Return once message `number` (1-based) may be sent: within every consumer's window."""
        with self._cond:
            while not self._abort.is_set() and any(number - self._acked[c] > self._windows[c] for c in self._acked):
                self._cond.wait(POLL_S)

    def host_lost(self, host: str) -> None:
        """Stop waiting for the consumers on a lost host."""
        with self._cond:
            for consumer in [c for c, h in self._hosts.items() if h == host]:
                self._acked.pop(consumer, None)
            self._cond.notify_all()

    def close(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers = []


class Acks:
    """What one operator took from its inbox per input port fed from another host, published every
    `every` messages (and at the end) for the producers' `Credits`."""

    def __init__(self, session: zenoh.Session, pipeline: str, operator: str, ports: list[str], every: int):
        self._every = every
        self._taken = dict.fromkeys(ports, 0)
        self._publishers = {port: session.declare_publisher(keys.ack_key(pipeline, operator, port)) for port in ports}

    def took(self, port: str) -> None:
        if port in self._taken:
            self._taken[port] += 1
            if self._taken[port] % self._every == 0:
                self._publishers[port].put(str(self._taken[port]).encode())

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers = {}
