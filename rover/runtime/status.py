"""What a running host reports about itself (`rover status`): the snapshot, its JSON form, rates and the table.

Each host of a distributed run answers Zenoh queries on `rover/<pipeline>/_status/<host>` with
`HostStatus.to_json()`. The payload comes from the network, so `from_json` trusts nothing: plain
`json.loads`, then every field's type and range checked, a `StatusError` naming the bad field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from rover.transport.keys import PREFIX

if TYPE_CHECKING:
    from rich.console import RenderableType

STATUS_KEY = "_status"
SCHEMA_VERSION = 1
STATES = ("waiting", "running", "finishing", "done")


class StatusError(ValueError):
    """A status payload that is not the JSON `HostStatus.to_json` writes; the message names the field."""

    def __init__(self, field: str, problem: str):
        self.field = field
        super().__init__(f"{field}: {problem}" if field else problem)


def status_key(pipeline: str, host: str) -> str:
    """The key a host's status queryable answers on (operator names start with a letter: no clash)."""
    return f"{PREFIX}/{pipeline}/{STATUS_KEY}/{host}"


def status_selector(pipeline: str) -> str:
    """The keys of every host's status in a pipeline."""
    return f"{PREFIX}/{pipeline}/{STATUS_KEY}/*"


@dataclass(frozen=True)
class OperatorStatus:
    """One operator's counters: cumulative messages per port since the host started, its queue, its time."""

    name: str
    uses: str
    received: dict[str, int]
    sent: dict[str, int]
    dropped: dict[str, int]
    queue: int
    queue_high: int
    event_time_ns: int | None
    """stamp of the last message handled (None before any)"""
    input_time_ns: int | None
    """latest stamp received on any input (None before any)"""
    last_error: str
    """empty when none"""

    @property
    def lag_s(self) -> float | None:
        """How far the operator's event time trails its inputs, in seconds (None until both are known)."""
        if self.input_time_ns is None or self.event_time_ns is None:
            return None
        return (self.input_time_ns - self.event_time_ns) / 1e9


@dataclass(frozen=True)
class HostStatus:
    """A snapshot of one host of a running pipeline."""

    pipeline: str
    host: str
    state: str
    """one of STATES"""
    waiting_for: list[str]
    """hosts this one waits for (to be ready, or done)"""
    lost: list[str]
    """hosts that left before the end of the stream"""
    uptime_s: float
    """seconds since the host started, from a monotonic clock (what rates divide by)"""
    sent_at: float
    """wall clock (time.time()) when the snapshot was taken"""
    operators: list[OperatorStatus]

    def to_json(self) -> bytes:
        """UTF-8 JSON: {"version": 1, the fields above, "operators": [{the OperatorStatus fields}]}."""
        return json.dumps({"version": SCHEMA_VERSION, **asdict(self)}, allow_nan=False).encode()

    @classmethod
    def from_json(cls, data: bytes) -> HostStatus:
        """Parse and check a status payload; StatusError (naming the field) on anything unexpected.

        Unknown keys are ignored, so a newer host can add fields; a different "version" is refused."""
        try:
            doc = json.loads(data.decode("utf-8"), parse_constant=_no_constant)
        except (UnicodeDecodeError, ValueError, RecursionError) as exc:
            raise StatusError("", f"not a UTF-8 JSON status: {exc}") from None
        top = _mapping(doc, "status")
        version = _field(top, "version", "")
        if isinstance(version, bool) or version != SCHEMA_VERSION:
            raise StatusError("version", f"expected {SCHEMA_VERSION}, got {version!r:.40}")
        state = _str(_field(top, "state", ""), "state")
        if state not in STATES:
            raise StatusError("state", f"expected one of {', '.join(STATES)}, got {state!r:.40}")
        operators = _field(top, "operators", "")
        if not isinstance(operators, list):
            raise StatusError("operators", f"expected a list, got {_kind(operators)}")
        return cls(
            pipeline=_str(_field(top, "pipeline", ""), "pipeline"),
            host=_str(_field(top, "host", ""), "host"),
            state=state,
            waiting_for=_strs(_field(top, "waiting_for", ""), "waiting_for"),
            lost=_strs(_field(top, "lost", ""), "lost"),
            uptime_s=_seconds(_field(top, "uptime_s", ""), "uptime_s"),
            sent_at=_seconds(_field(top, "sent_at", ""), "sent_at"),
            operators=[_operator(op, f"operators[{i}]") for i, op in enumerate(operators)],
        )


def _operator(value: Any, where: str) -> OperatorStatus:
    op = _mapping(value, where)

    def get(key: str) -> Any:
        return _field(op, key, where)

    return OperatorStatus(
        name=_str(get("name"), f"{where}.name"),
        uses=_str(get("uses"), f"{where}.uses"),
        received=_counts(get("received"), f"{where}.received"),
        sent=_counts(get("sent"), f"{where}.sent"),
        dropped=_counts(get("dropped"), f"{where}.dropped"),
        queue=_count(get("queue"), f"{where}.queue"),
        queue_high=_count(get("queue_high"), f"{where}.queue_high"),
        event_time_ns=None if get("event_time_ns") is None else _count(op["event_time_ns"], f"{where}.event_time_ns"),
        input_time_ns=None if get("input_time_ns") is None else _count(op["input_time_ns"], f"{where}.input_time_ns"),
        last_error=_str(get("last_error"), f"{where}.last_error", empty=True),
    )


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _kind(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}.get(
        type(value), "a number"
    )


def _field(obj: dict[str, Any], key: str, where: str) -> Any:
    if key not in obj:
        raise StatusError(f"{where}.{key}" if where else key, "missing")
    return obj[key]


def _mapping(value: Any, where: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise StatusError(where, f"expected an object, got {_kind(value)}")
    return value


def _str(value: Any, where: str, *, empty: bool = False) -> str:
    if not isinstance(value, str) or (not value and not empty):
        raise StatusError(where, f"expected a {'' if empty else 'non-empty '}string, got {_kind(value)}")
    return value


def _strs(value: Any, where: str) -> list[str]:
    if not isinstance(value, list):
        raise StatusError(where, f"expected a list of strings, got {_kind(value)}")
    return [_str(v, f"{where}[{i}]") for i, v in enumerate(value)]


def _count(value: Any, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise StatusError(where, f"expected a whole number >= 0, got {value!r:.40}")
    return value


def _counts(value: Any, where: str) -> dict[str, int]:
    return {_str(port, f"{where} key"): _count(n, f"{where}.{port}") for port, n in _mapping(value, where).items()}


def _seconds(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise StatusError(where, f"expected a number of seconds >= 0, got {value!r:.40}")
    return float(value)


def collect(payloads: Sequence[bytes], pipeline: str) -> tuple[dict[str, HostStatus], list[str]]:
    """The statuses of a query's replies by host, and a note for each reply that could not be used."""
    statuses: dict[str, HostStatus] = {}
    notes: list[str] = []
    for payload in payloads:
        try:
            status = HostStatus.from_json(payload)
        except StatusError as exc:
            notes.append(f"a status reply was not understood: {exc}")
            continue
        if status.pipeline != pipeline:
            notes.append(f"host {status.host} answered for pipeline {status.pipeline!r}, not {pipeline!r}")
            continue
        statuses[status.host] = status
    return statuses, notes


Rates = dict[str, tuple[dict[str, float], dict[str, float]]]


def rates(previous: HostStatus | None, current: HostStatus) -> Rates:
    """Per operator, (input, output) messages/s per port between two snapshots of one host.

    Divides by the hosts' own uptime difference (monotonic, immune to clock skew). Empty without a
    usable earlier snapshot (none, another host, a restarted host); an operator new since then, or a
    port whose count went down, is left out: "-" in the table."""
    if previous is None or (previous.pipeline, previous.host) != (current.pipeline, current.host):
        return {}
    dt = current.uptime_s - previous.uptime_s
    if dt <= 0:
        return {}
    before = {op.name: op for op in previous.operators}
    out: Rates = {}
    for op in current.operators:
        old = before.get(op.name)
        if old is not None:
            out[op.name] = (_per_s(old.received, op.received, dt), _per_s(old.sent, op.sent, dt))
    return out


def _per_s(old: Mapping[str, int], new: Mapping[str, int], dt: float) -> dict[str, float]:
    return {port: (n - old.get(port, 0)) / dt for port, n in new.items() if n >= old.get(port, 0)}


def render(
    statuses: Mapping[str, HostStatus],
    previous: Mapping[str, HostStatus],
    expected_hosts: Sequence[str],
    notes: Sequence[str] = (),
) -> RenderableType:
    """The hosts (expected ones that did not answer as "not answering"), then one row per operator.

    Every string from the network goes in as `Text`, never as rich markup."""
    from rich import box
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    names = list(dict.fromkeys([*expected_hosts, *sorted(statuses)]))
    pipeline = next((s.pipeline for s in statuses.values()), "")
    answering = sum(h in statuses for h in names)
    title = Text(f"pipeline {pipeline}: {answering} of {len(names)} hosts answering")
    hosts = Table(title=title, title_justify="left", box=box.SIMPLE_HEAD)
    for column in ("host", "state", "uptime", "detail"):
        hosts.add_column(column)
    ops = Table(box=box.SIMPLE_HEAD)
    for column in ("host", "operator", "in msg/s", "out msg/s", "queue", "lag", "dropped"):
        ops.add_column(column, no_wrap=True)
    ops.add_column("last error", overflow="fold")  # the one column that wraps
    for host in names:
        status = statuses.get(host)
        if status is None:
            hosts.add_row(Text(host), Text("not answering", style="red"), Text("-"), Text(""))
            continue
        detail = [f"waiting for {', '.join(status.waiting_for)}"] if status.waiting_for else []
        detail += [f"lost {', '.join(status.lost)}"] if status.lost else []
        hosts.add_row(Text(host), Text(status.state), Text(f"{status.uptime_s:.0f} s"), Text("; ".join(detail)))
        per_op = rates(previous.get(host), status)
        for op in status.operators:
            rate_in, rate_out = per_op.get(op.name, ({}, {}))
            lag = op.lag_s
            ops.add_row(
                Text(host),
                Text(op.name),
                Text(_ports(op.received, rate_in)),
                Text(_ports(op.sent, rate_out)),
                Text(f"{op.queue}/{op.queue_high}"),
                Text("-" if lag is None else f"{lag:.3f} s"),
                Text("\n".join(f"{p} {n}" for p, n in op.dropped.items() if n) or "-"),
                Text(" ".join(op.last_error.split()), style="red"),
            )
    return Group(hosts, ops, *(Text(f"note: {n}", style="yellow") for n in notes))


def _ports(counts: Mapping[str, int], per_s: Mapping[str, float]) -> str:
    """One line per port with its rate ("-" without two snapshots)."""
    return "\n".join(f"{port} {f'{per_s[port]:.1f}' if port in per_s else '-'}" for port in counts)
