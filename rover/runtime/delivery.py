"""Delivering each received message to every operator of the process that takes it, decoded once.

One Zenoh subscriber per key for the whole process (not one per consuming port): each sample
becomes one `Delivery`, put in the inbox of every consuming operator. The first of them to need
the message decodes it; the others get the same object. It is read-only (`rover.frozen`), so no
operator's edit reaches another's input; a port declared `In(..., writable=True)` decodes its own
mutable copy instead, and a raw port takes the bytes.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from rover.frozen import freeze
from rover.messages import deserialize


class Delivery:
    """One sample received on a key: its encoding, payload and attachment, and the message decoded
    from it once, on first use."""

    __slots__ = ("encoding", "payload", "attachment", "_lock", "_decoded")

    def __init__(self, encoding: str, payload: bytes, attachment: bytes | None):
        self.encoding = encoding
        self.payload = payload
        self.attachment = attachment
        self._lock = threading.Lock()
        self._decoded: tuple[str, Any] | None = None

    def message(self, typename: str) -> Any | None:
        """The payload decoded as `typename`, read-only and shared; None when it does not decode."""
        with self._lock:
            if self._decoded is None or self._decoded[0] != typename:
                self._decoded = (typename, decode(self.payload, typename))
            return self._decoded[1]

    def private_message(self, typename: str) -> Any | None:
        """A mutable message of this consumer's own (a writable port); None when it does not decode."""
        return decode(self.payload, typename, frozen=False)


def decode(payload: bytes, typename: str, frozen: bool = True) -> Any | None:
    """CDR bytes as a message, read-only unless told otherwise; None when they do not decode."""
    try:
        msg = deserialize(payload, typename)
    except Exception:  # noqa: BLE001 - any decoding failure of foreign bytes is a drop, never a crash
        return None
    return freeze(msg) if frozen else msg


class Fanout:
    """The process's subscribers: one per key, handing each sample to every consumer added for it."""

    def __init__(self, session: zenoh.Session):
        self.session = session
        self.consumers: dict[str, list[Callable[[Delivery], None]]] = {}
        self.subscribers: list[zenoh.Subscriber[None]] = []

    def add(self, key: str, consumer: Callable[[Delivery], None]) -> None:
        """Hand every sample on `key` to `consumer` (called in the thread that delivers the sample)."""
        self.consumers.setdefault(key, []).append(consumer)

    def declare(self) -> None:
        for key, consumers in self.consumers.items():
            handler = zenoh.handlers.Callback(_deliver_to(tuple(consumers)), indirect=False)
            self.subscribers.append(self.session.declare_subscriber(key, handler))

    def undeclare(self) -> None:
        for subscriber in self.subscribers:
            with contextlib.suppress(zenoh.ZError):
                subscriber.undeclare()
        self.subscribers.clear()


def _deliver_to(consumers: tuple[Callable[[Delivery], None], ...]) -> Callable[[zenoh.Sample], None]:
    def deliver(sample: zenoh.Sample) -> None:
        att = sample.attachment
        delivery = Delivery(str(sample.encoding), sample.payload.to_bytes(), att.to_bytes() if att else None)
        for consumer in consumers:
            consumer(delivery)

    return deliver
