"""Zenoh key expressions of a pipeline: `rover/<pipeline>/<operator>/<port>` plus host presence.

A host's presence is a liveliness token `rover/<pipeline>/_hosts/<host>/<digest>/<zid>/<state>`:
`digest` identifies the pipeline's structure (hosts, placement, wiring), so a process of another
pipeline or version is not taken for a host of this run; `zid` is the Zenoh session of the process,
so a second process claiming the same host is told apart. A host that stops on a signal also puts
its reason on `.../bye` before it leaves; one whose part ended puts its operators' counts and
profiles on `.../report` (rover/runtime/host_report.py) before its `done`.
"""

from __future__ import annotations

from typing import NamedTuple

PREFIX = "rover"
HOSTS = "_hosts"
STATES = ("ready", "done", "bye", "report")


class HostKey(NamedTuple):
    host: str
    digest: str
    zid: str
    state: str


def port_key(pipeline: str, operator: str, port: str) -> str:
    return f"{PREFIX}/{pipeline}/{operator}/{port}"


def ack_key(pipeline: str, operator: str, port: str) -> str:
    """What `operator` took from its inbox on input `port`, for flow control across hosts."""
    return f"{PREFIX}/{pipeline}/_ack/{operator}/{port}"


def host_token(pipeline: str, key: HostKey) -> str:
    """The key a host declares when it is `ready` (subscribed) and `done`, or puts its `bye` on."""
    return f"{PREFIX}/{pipeline}/{HOSTS}/{key.host}/{key.digest}/{key.zid}/{key.state}"


def host_tokens(pipeline: str) -> str:
    """Every presence key of the pipeline (also malformed ones, which the watcher reports and ignores)."""
    return f"{PREFIX}/{pipeline}/{HOSTS}/**"


def parse_host_token(pipeline: str, key: str) -> HostKey | None:
    """The parts of a presence key; None when it is not one of the form above."""
    head = f"{PREFIX}/{pipeline}/{HOSTS}/"
    if not key.startswith(head):
        return None
    parts = key[len(head) :].split("/")
    if len(parts) != 4 or parts[3] not in STATES or not all(parts):
        return None
    return HostKey(*parts)
