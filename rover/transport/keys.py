"""Zenoh key expressions of a pipeline: `rover/<pipeline>/<operator>/<port>` plus host presence tokens."""

from __future__ import annotations

PREFIX = "rover"


def port_key(pipeline: str, operator: str, port: str) -> str:
    return f"{PREFIX}/{pipeline}/{operator}/{port}"


def host_token(pipeline: str, host: str, state: str) -> str:
    """Liveliness token a host declares when it is `ready` (subscribed) and when it is `done`."""
    return f"{PREFIX}/{pipeline}/_hosts/{host}/{state}"


def host_tokens(pipeline: str) -> str:
    return f"{PREFIX}/{pipeline}/_hosts/*/*"


def parse_host_token(key: str) -> tuple[str, str]:
    parts = key.split("/")
    return parts[-2], parts[-1]
