"""What a running host reports about itself (`rover status`): the snapshot, its JSON form, rates and the table.

Each host of a distributed run answers Zenoh queries on `rover/<pipeline>/_status/<host>` with
`HostStatus.to_json()`. The payload comes from the network, so `from_json` trusts nothing: plain
`json.loads`, then every field's type and range checked, a `StatusError` naming the bad field.

Each reply carries the host's wall clock (`clock_ns`); the monitor brackets it between its own clock
just before the query went out and when the reply arrived, which bounds the host's clock offset
(`clock_offset`). Offsets are reported (the table's clock column and the line under it), never
corrected: live sources stamp messages on their own host's clock, and only the user can fix that.
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from rover.transport.keys import PREFIX

if TYPE_CHECKING:
    from rich.console import RenderableType

STATUS_KEY = "_status"
SCHEMA_VERSION = 1
STATES = ("waiting", "running", "finishing", "done")
CLOCK_WARN_S = 0.005
"""Two hosts whose clocks differ by more than this (seconds) get a warning under the table: a tenth
of the sweep's 50 ms channel dwell. Live sources stamp messages on their own host's clock, and
each CSI frame is matched to the channel dwell its stamp falls in (the hops may be stamped on
another host), so an offset of a tenth of a dwell already mislabels the frames at its edges."""
CLOCK_KEEP = 5
"""replies per host among which the monitor keeps the clock estimate with the shortest round trip"""
MAX_CLOCK_NS = 2**63 - 1
"""the largest `clock_ns` accepted (a signed 64-bit count of nanoseconds: the year 2262)"""


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
    clock_ns: int | None = None
    """this host's wall clock (time.time_ns()) as it answered, what the monitor measures the offset
    of its clock from; None from a host that predates it (the field is optional in the JSON)"""

    def to_json(self) -> bytes:
        """UTF-8 JSON: {"version": 1, the fields above, "operators": [{the OperatorStatus fields}]}
        (`clock_ns` is null when unknown)."""
        return json.dumps({"version": SCHEMA_VERSION, **asdict(self)}, allow_nan=False).encode()

    @classmethod
    def from_json(cls, data: bytes) -> HostStatus:
        """Parse and check a status payload; StatusError (naming the field) on anything unexpected.

        Unknown keys are ignored, so a newer host can add fields; a different "version" is refused.
        `clock_ns` was added within version 1: missing or null, it is None."""
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
            clock_ns=_clock(top.get("clock_ns"), "clock_ns"),
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


def _clock(value: Any, where: str) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_CLOCK_NS:
        raise StatusError(where, f"expected a whole number of nanoseconds from 0 to 2**63-1, got {value!r:.40}")
    return value


def _counts(value: Any, where: str) -> dict[str, int]:
    return {_str(port, f"{where} key"): _count(n, f"{where}.{port}") for port, n in _mapping(value, where).items()}


def _seconds(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise StatusError(where, f"expected a number of seconds >= 0, got {value!r:.40}")
    return float(value)


def read_reply(payload: bytes, pipeline: str) -> HostStatus | str:
    """A reply's status, or the note saying why it cannot be used (not understood, another pipeline)."""
    try:
        status = HostStatus.from_json(payload)
    except StatusError as exc:
        return f"a status reply was not understood: {exc}"
    if status.pipeline != pipeline:
        return f"host {status.host} answered for pipeline {status.pipeline!r}, not {pipeline!r}"
    return status


def collect(payloads: Sequence[bytes], pipeline: str) -> tuple[dict[str, HostStatus], list[str]]:
    """The statuses of a query's replies by host, and a note for each reply that could not be used."""
    statuses: dict[str, HostStatus] = {}
    notes: list[str] = []
    for payload in payloads:
        status = read_reply(payload, pipeline)
        if isinstance(status, str):
            notes.append(status)
        else:
            statuses[status.host] = status
    return statuses, notes


@dataclass(frozen=True)
class ClockOffset:
    """A host's wall clock minus the monitor's, in nanoseconds: positive when the host is ahead."""

    offset_ns: int
    uncertainty_ns: int
    """the true offset lies within offset_ns ± uncertainty_ns (half the query's round trip)"""


def clock_offset(host_clock_ns: int, sent_ns: int, received_ns: int) -> ClockOffset:
    """Cristian's (and NTP's) estimate from one reply: the host read its clock (`host_clock_ns`)
    at some instant between `sent_ns` (the monitor's clock just before the query went out) and
    `received_ns` (when the reply arrived), so its offset is within [clock - received, clock - sent]:
    clock - (sent + received) / 2, ± (received - sent) / 2. Whole nanoseconds, the bound rounded up."""
    if received_ns < sent_ns:
        raise ValueError(f"a reply received ({received_ns}) before its query was sent ({sent_ns})")
    round_trip = received_ns - sent_ns
    return ClockOffset(host_clock_ns - sent_ns - round_trip // 2, (round_trip + 1) // 2)


class Clocks:
    """Each host's clock offset over the monitor's last few queries (`keep` replies per host): the
    estimate with the shortest round trip, whose bound is the tightest (the latest among equals)."""

    def __init__(self, keep: int = CLOCK_KEEP):
        self._recent: dict[str, deque[ClockOffset]] = {}
        self.keep = keep

    def add(self, host: str, estimate: ClockOffset) -> None:
        self._recent.setdefault(host, deque(maxlen=self.keep)).append(estimate)

    def best(self) -> dict[str, ClockOffset]:
        return {host: min(reversed(recent), key=lambda e: e.uncertainty_ns) for host, recent in self._recent.items()}


@dataclass(frozen=True)
class ClockSpread:
    """The largest difference between two hosts' clocks: `ahead`'s clock minus `behind`'s."""

    ahead: str
    behind: str
    offset_ns: int
    uncertainty_ns: int
    """the sum of both hosts' uncertainties"""

    @property
    def too_far(self) -> bool:
        """Whether the estimate exceeds CLOCK_WARN_S."""
        return self.offset_ns > CLOCK_WARN_S * 1e9


def clock_spread(offsets: Mapping[str, ClockOffset]) -> ClockSpread | None:
    """The two hosts whose clocks are furthest apart (None with fewer than two hosts)."""
    if len(offsets) < 2:
        return None
    order = sorted(offsets, key=lambda h: (offsets[h].offset_ns, h))
    behind, ahead = order[0], order[-1]
    a, b = offsets[ahead], offsets[behind]
    return ClockSpread(ahead, behind, a.offset_ns - b.offset_ns, a.uncertainty_ns + b.uncertainty_ns)


def report(
    statuses: Mapping[str, HostStatus],
    previous: Mapping[str, HostStatus],
    expected_hosts: Sequence[str],
    notes: Sequence[str] = (),
    offsets: Mapping[str, ClockOffset] | None = None,
) -> dict[str, Any]:
    """What `render` shows, as JSON-ready data (`rover status --json`): per host its status (null
    when not answering), its clock offset from the monitor and that offset's bound (null when
    unknown), its operators' rates; the largest clock difference between two hosts; the notes."""
    offsets = {h: o for h, o in (offsets or {}).items() if h in statuses}
    hosts = []
    for host in dict.fromkeys([*expected_hosts, *sorted(statuses)]):
        status, clock = statuses.get(host), offsets.get(host)
        hosts.append(
            {
                "host": host,
                "answering": status is not None,
                "clock_offset_ns": None if clock is None else clock.offset_ns,
                "clock_uncertainty_ns": None if clock is None else clock.uncertainty_ns,
                "rates": {
                    name: {"in": rate_in, "out": rate_out}
                    for name, (rate_in, rate_out) in (rates(previous.get(host), status) if status else {}).items()
                },
                "status": None if status is None else asdict(status),
            }
        )
    spread = clock_spread(offsets)
    return {
        "pipeline": next((s.pipeline for s in statuses.values()), ""),
        "hosts": hosts,
        "clock_spread": None
        if spread is None
        else {**asdict(spread), "warn_above_ns": round(CLOCK_WARN_S * 1e9), "warn": spread.too_far},
        "notes": list(notes),
    }


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
    offsets: Mapping[str, ClockOffset] | None = None,
) -> RenderableType:
    """The hosts (expected ones that did not answer as "not answering") with each one's clock offset
    from this machine's (`offsets`, "-" when unknown), a line with the largest clock difference
    between two hosts, then one row per operator.

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
    offsets = {h: o for h, o in (offsets or {}).items() if h in statuses}
    for column in ("host", "state", "uptime", "clock", "detail"):
        hosts.add_column(column)
    ops = Table(box=box.SIMPLE_HEAD)
    for column in ("host", "operator", "in msg/s", "out msg/s", "queue", "lag", "dropped"):
        ops.add_column(column, no_wrap=True)
    ops.add_column("last error", overflow="fold")  # the one column that wraps
    for host in names:
        status = statuses.get(host)
        if status is None:
            hosts.add_row(Text(host), Text("not answering", style="red"), Text("-"), Text("-"), Text(""))
            continue
        # before the run the others are not ready yet; during and after it they are not done yet
        pending = ", ".join(status.waiting_for)
        if status.state == "waiting":
            detail = [f"waiting for {pending}"] if pending else []
        elif status.state == "running":
            detail = [f"running with {pending}"] if pending else []
        else:
            detail = [f"waiting for {pending} to finish"] if pending else []
        detail += [f"lost {', '.join(status.lost)}"] if status.lost else []
        clock = offsets.get(host)
        hosts.add_row(
            Text(host),
            Text(status.state),
            Text(f"{status.uptime_s:.0f} s"),
            Text("-" if clock is None else _offset(clock.offset_ns, clock.uncertainty_ns)),
            Text("; ".join(detail)),
        )
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
    spread = clock_spread(offsets)
    lines = [] if spread is None else [_spread_line(spread)]
    return Group(hosts, *lines, ops, *(Text(f"note: {n}", style="yellow") for n in notes))


def _offset(offset_ns: int, uncertainty_ns: int, sign: str = "+") -> str:
    """`+12.3 ms ±0.4` (seconds from 10 s on: `+3600.0 s ±0.4 ms`)."""
    if abs(offset_ns) < 10_000_000_000:
        return f"{offset_ns / 1e6:{sign}.1f} ms ±{uncertainty_ns / 1e6:.1f}"
    return f"{offset_ns / 1e9:{sign}.1f} s ±{uncertainty_ns / 1e6:.1f} ms"


def _spread_line(spread: ClockSpread) -> RenderableType:
    from rich.text import Text

    what = f"clocks: {spread.ahead} is {_offset(spread.offset_ns, spread.uncertainty_ns, '')} ahead of {spread.behind}"
    if not spread.too_far:
        return Text(f"{what} (the largest difference between two hosts; reported, not corrected)")
    warn = f"more than {CLOCK_WARN_S * 1e3:g} ms, not corrected: synchronize the hosts' clocks (chrony, PTP)"
    return Text(f"! {what}: {warn}", style="bold red")


def _ports(counts: Mapping[str, int], per_s: Mapping[str, float]) -> str:
    """One line per port with its rate ("-" without two snapshots)."""
    return "\n".join(f"{port} {f'{per_s[port]:.1f}' if port in per_s else '-'}" for port in counts)
