"""Opening Zenoh sessions with explicit endpoints only, and clear errors when that fails."""

from __future__ import annotations

import json
import re
import socket
from dataclasses import dataclass, field
from typing import Any

import zenoh

from rover.errors import TransportError

RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 1.5}


@dataclass(frozen=True)
class SessionSpec:
    """Where a session listens and what it connects to. No endpoints: a private in-process session."""

    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    host_timeout_s: float = 15.0
    """a link silent this long is closed (Zenoh's transport lease): its hosts are lost"""
    label: str = "local"
    tls: TlsFiles | None = None
    """mutual TLS: this host's identity and the CA it checks the others against"""
    access_control: dict[str, Any] | None = None
    """Zenoh's `access_control` section (rover.security.acl), enforced on every link of this host"""


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one identity: the CA certificate, this side's certificate and private key."""

    ca: str
    cert: str
    key: str


def tls_config(conf: zenoh.Config, tls: TlsFiles, *, listen: bool) -> None:
    """Mutual TLS on both sides of every link: certificates checked against the CA, the server's
    names against the endpoint dialled, links closed when the other side's certificate expires."""
    settings: dict[str, Any] = {
        "root_ca_certificate": tls.ca,
        "connect_certificate": tls.cert,
        "connect_private_key": tls.key,
        "enable_mtls": True,  # on a connecting side too: without it Zenoh sends no certificate
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }
    if listen:
        settings |= {"listen_certificate": tls.cert, "listen_private_key": tls.key}
    for key, value in settings.items():
        conf.insert_json5(f"transport/link/tls/{key}", json.dumps(value))


def config(spec: SessionSpec) -> zenoh.Config:
    """Router mode when other hosts take part (no separate router binary), scouting off, nothing implicit.
    Connections are retried in the background for as long as the session lives: the runtime's own
    wait (`wait_timeout_s`) decides when to give up, and stays interruptible."""
    conf = zenoh.Config()
    distributed = bool(spec.listen or spec.connect)
    conf.insert_json5("mode", json.dumps("router" if distributed else "peer"))
    conf.insert_json5("listen/endpoints", json.dumps(spec.listen))
    conf.insert_json5("connect/endpoints", json.dumps(spec.connect))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("connect/timeout_ms", "-1")
    conf.insert_json5("connect/exit_on_failure", "false")
    conf.insert_json5("connect/retry", json.dumps(RETRY))
    conf.insert_json5("transport/link/tx/lease", str(max(1, int(spec.host_timeout_s * 1000))))
    # A publisher blocked on a link (the other side unreachable, TCP backing off) must not close
    # it before the lease does: Zenoh's default closes it after 5 s, a 4 s outage takes ~6.5 s.
    block_us = max(1, int(spec.host_timeout_s * 1e6))
    conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close", str(block_us))
    if spec.tls is not None:
        tls_config(conf, spec.tls, listen=True)
    if spec.access_control is not None:
        conf.insert_json5("access_control", json.dumps(spec.access_control))
    return conf


def _busy_listen_endpoint(endpoints: list[str]) -> str | None:
    for ep in endpoints:
        match = re.match(r"^tcp/\[?([^\]]*)\]?:(\d+)$", ep)
        if not match:
            continue
        family = socket.AF_INET6 if ":" in match.group(1) else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            try:
                probe.bind((match.group(1), int(match.group(2))))
            except OSError:
                return ep
    return None


def open_session(spec: SessionSpec) -> zenoh.Session:
    """Open a session; a busy listen port is a TransportError naming it."""
    try:
        return zenoh.open(config(spec))
    except zenoh.ZError as exc:
        text = str(exc)
        busy = _busy_listen_endpoint(spec.listen)
        if busy or "listener" in text.lower():
            raise TransportError(
                f"host {spec.label}: cannot listen on {busy or ', '.join(spec.listen)}: address in use or not available"
            ) from None
        raise TransportError(f"host {spec.label}: cannot open a Zenoh session: {text.split(' at /')[0]}") from None
