"""`rover status`: the status snapshot and its JSON, rates, the table, the Zenoh query and the command."""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import zenoh
from helpers import free_port, run_rover
from rich.console import Console

from rover.errors import TransportError
from rover.runtime.status import (
    CLOCK_WARN_S,
    ClockOffset,
    Clocks,
    ClockSpread,
    HostStatus,
    OperatorStatus,
    StatusError,
    clock_offset,
    clock_spread,
    collect,
    rates,
    render,
    report,
    status_key,
    status_selector,
)
from rover.transport.monitor import StatusClient, local_endpoint, query_status
from rover.transport.session import SessionSpec, open_session


def snapshot(k: int = 0, host: str = "a", error: str = "") -> HostStatus:
    """Host `host` of pipeline toy after 10 + k seconds: 100 imu and 10 odom messages a second in, 10 poses out."""
    return HostStatus(
        pipeline="toy",
        host=host,
        state="running",
        waiting_for=[],
        lost=["c"] if error else [],
        uptime_s=10.0 + k,
        sent_at=1_700_000_000.0 + k,
        operators=[
            OperatorStatus(
                name="heading",
                uses="toyops.Heading",
                received={"imu": 1000 + 100 * k, "odom": 100 + 10 * k},
                sent={"pose": 100 + 10 * k},
                dropped={"imu": 2, "odom": 0},
                queue=3,
                queue_high=17,
                event_time_ns=1_000_000_000,
                input_time_ns=1_250_000_000,
                last_error=error,
            ),
            OperatorStatus("replay", "dataset_replay", {}, {"imu": 1000 + 100 * k}, {}, 0, 0, None, None, ""),
        ],
    )


def test_keys():
    assert status_key("toy", "a") == "rover/toy/_status/a"
    assert status_selector("toy") == "rover/toy/_status/*"


def test_json_round_trip():
    status = snapshot(error="boom")
    assert HostStatus.from_json(status.to_json()) == status
    assert json.loads(status.to_json())["version"] == 1
    clocked = replace(status, clock_ns=1_700_000_000_123_456_789)
    assert HostStatus.from_json(clocked.to_json()) == clocked
    assert json.loads(clocked.to_json())["clock_ns"] == 1_700_000_000_123_456_789
    assert status.operators[0].lag_s == pytest.approx(0.25)
    assert status.operators[1].lag_s is None


def _doc() -> dict:
    return json.loads(snapshot().to_json())


def _set(path: str, value: object) -> bytes:
    """The snapshot's JSON with one field (a dotted path, list indexes as numbers) replaced or, for ..., removed."""
    doc = _doc()
    *parents, last = path.split(".")
    target = doc
    for part in parents:
        target = target[int(part)] if part.isdigit() else target[part]
    key = int(last) if last.isdigit() else last
    if value is ...:
        del target[key]
    else:
        target[key] = value
    return json.dumps(doc).encode()


@pytest.mark.parametrize(
    ("payload", "field"),
    [
        (b"not json", ""),
        (b"\xff\xfe{}", ""),
        (json.dumps(_doc()).replace('"uptime_s": 10.0', '"uptime_s": NaN').encode(), ""),
        (b"[" * 100_000 + b"]" * 100_000, ""),
        (b"[]", "status"),
        (_set("host", ...), "host"),
        (_set("version", 2), "version"),
        (_set("version", True), "version"),
        (_set("state", "exploded"), "state"),
        (_set("waiting_for", "b"), "waiting_for"),
        (_set("lost", [1]), "lost[0]"),
        (_set("uptime_s", "3"), "uptime_s"),
        (_set("sent_at", True), "sent_at"),
        (_set("operators", {}), "operators"),
        (_set("operators.0.queue", -1), "operators[0].queue"),
        (_set("operators.0.queue_high", 1.5), "operators[0].queue_high"),
        (_set("operators.0.received", {"imu": "7"}), "operators[0].received.imu"),
        (_set("operators.0.sent", []), "operators[0].sent"),
        (_set("operators.0.event_time_ns", "x"), "operators[0].event_time_ns"),
        (_set("operators.1.last_error", None), "operators[1].last_error"),
        (_set("operators.1.dropped", ...), "operators[1].dropped"),
        (_set("operators.1", "replay"), "operators[1]"),
        (_set("clock_ns", "1700000000000000000"), "clock_ns"),
        (_set("clock_ns", -1), "clock_ns"),
        (_set("clock_ns", True), "clock_ns"),
        (_set("clock_ns", 1.7e18), "clock_ns"),
        (_set("clock_ns", 2**63), "clock_ns"),
    ],
)
def test_from_json_names_the_bad_field(payload, field):
    with pytest.raises(StatusError) as raised:
        HostStatus.from_json(payload)
    assert raised.value.field == field
    assert str(raised.value).startswith(f"{field}: " if field else "not a UTF-8 JSON status")


def test_a_reply_without_clock_is_from_an_older_host():
    assert HostStatus.from_json(_set("clock_ns", ...)).clock_ns is None
    assert HostStatus.from_json(_set("clock_ns", 0)).clock_ns == 0


def test_collect_keeps_good_replies_and_notes_the_others():
    statuses, notes = collect([snapshot().to_json(), b"{}", snapshot(host="b").to_json()], "toy")
    assert sorted(statuses) == ["a", "b"]
    assert notes == ["a status reply was not understood: version: missing"]
    assert collect([snapshot().to_json()], "other")[0] == {}


def test_rates_from_two_snapshots():
    per_op = rates(snapshot(0), snapshot(2))
    assert per_op["heading"] == ({"imu": 100.0, "odom": 10.0}, {"pose": 10.0})
    assert per_op["replay"] == ({}, {"imu": 100.0})
    assert rates(None, snapshot(2)) == {}
    assert rates(snapshot(2), snapshot(0)) == {}  # restarted: uptime went back
    assert rates(snapshot(0, host="b"), snapshot(2)) == {}
    counted_down = replace(snapshot(2), operators=[replace(snapshot(2).operators[0], received={"imu": 5, "odom": 120})])
    assert rates(snapshot(0), counted_down) == {"heading": ({"odom": 10.0}, {"pose": 10.0})}


def _text(renderable: object) -> str:
    console = Console(record=True, width=200)
    console.print(renderable)
    return console.export_text()


def test_render_shows_operators_and_hosts_not_answering():
    text = _text(render({"a": snapshot(1, error="[bold]boom[/bold]")}, {"a": snapshot(0)}, ["a", "b"], ["a note"]))
    rows = [line.split() for line in text.splitlines()]
    assert "pipeline toy: 1 of 2 hosts answering" in text
    assert ["b", "not", "answering", "-", "-"] in rows
    assert ["a", "running", "11", "s", "-", "lost", "c"] in rows  # no clock measured: "-"
    assert "clocks:" not in text
    heading = next(row for row in rows if row[1:2] == ["heading"])
    assert heading == [
        "a",
        "heading",
        "imu",
        "100.0",
        "pose",
        "10.0",
        "3/17",
        "0.250",
        "s",
        "imu",
        "2",
        "[bold]boom[/bold]",
    ]
    assert ["odom", "10.0"] in rows  # the operator's second input, on its own line
    assert next(row for row in rows if row[1:2] == ["replay"]) == ["a", "replay", "imu", "100.0", "0/0", "-", "-"]
    assert "note: a note" in text


def test_a_table_written_to_a_pipe_is_never_cut_to_the_terminals_width():
    """`rover status --once | less`: every column whole (rich would cut a pipe's table to 80 columns)."""
    from io import StringIO

    from rover.cli.status import show

    long_name = "preintegration_of_the_second_imu_on_the_left_wheel"
    a = replace(
        snapshot(0, "a_host_with_a_long_name"),
        operators=[OperatorStatus(long_name, "preintegration", {}, {}, {}, 0, 0, None, None, "")],
    )
    piped = StringIO()
    show(render({"a_host_with_a_long_name": a}, {}, ["a_host_with_a_long_name", "nuc"]), file=piped)
    text = piped.getvalue()
    assert long_name in text and "a_host_with_a_long_name" in text and "…" not in text, text
    assert max(len(line) for line in text.splitlines()) > 80


def test_render_without_previous_snapshot_shows_no_rate():
    rows = [line.split() for line in _text(render({"a": snapshot(0)}, {}, ["a"])).splitlines()]
    assert ["a", "heading", "imu", "-", "pose", "-", "3/17", "0.250", "s", "imu", "2"] in rows
    assert ["odom", "-"] in rows


def test_clock_offset_is_the_midpoint_of_the_round_trip():
    # sent at 1 s, received 400 ns later: the host read 250.1 us past the midpoint
    assert clock_offset(1_000_250_300, 1_000_000_000, 1_000_000_400) == ClockOffset(250_100, 200)
    assert clock_offset(1_000_000_000, 1_000_250_000, 1_000_250_400) == ClockOffset(-250_200, 200)
    assert clock_offset(5, 5, 5) == ClockOffset(0, 0)
    # an odd round trip: the bound is rounded up, so it still covers [clock - received, clock - sent]
    odd = clock_offset(10, 0, 3)
    assert odd == ClockOffset(9, 2)
    assert odd.offset_ns - odd.uncertainty_ns <= 10 - 3 and odd.offset_ns + odd.uncertainty_ns >= 10 - 0
    with pytest.raises(ValueError, match="before its query was sent"):
        clock_offset(10, 5, 4)


def test_clocks_keep_the_shortest_round_trip_of_the_last_replies():
    clocks = Clocks(keep=3)
    assert clocks.best() == {}
    for offset_ms, half_rtt_us in ((10, 500), (12, 100), (11, 300)):
        clocks.add("a", ClockOffset(offset_ms * MS, half_rtt_us * 1000))
    clocks.add("b", ClockOffset(-3 * MS, 900))
    assert clocks.best() == {"a": ClockOffset(12 * MS, 100_000), "b": ClockOffset(-3 * MS, 900)}
    for offset_ms, half_rtt_us in ((20, 400), (21, 200), (22, 600)):  # the 100 us one is now too old
        clocks.add("a", ClockOffset(offset_ms * MS, half_rtt_us * 1000))
    assert clocks.best()["a"] == ClockOffset(21 * MS, 200_000)
    clocks.add("a", ClockOffset(23 * MS, 200_000))  # as tight as the best: the later one wins
    assert clocks.best()["a"] == ClockOffset(23 * MS, 200_000)


def test_clock_spread_is_the_largest_difference_between_two_hosts():
    offsets = {
        "a": ClockOffset(10 * MS, 1 * MS),
        "b": ClockOffset(-5 * MS, 2 * MS),
        "c": ClockOffset(1 * MS, MS // 2),
    }
    spread = clock_spread(offsets)
    assert spread == ClockSpread("a", "b", 15 * MS, 3 * MS)
    assert spread.too_far
    close = clock_spread({"a": ClockOffset(2 * MS, 0), "b": ClockOffset(-2 * MS, 0)})
    assert close == ClockSpread("a", "b", 4 * MS, 0) and not close.too_far
    assert CLOCK_WARN_S == 0.005
    assert ClockSpread("a", "b", 5 * MS + 1, 0).too_far and not ClockSpread("a", "b", 5 * MS, 9 * MS).too_far
    assert clock_spread({"a": ClockOffset(7, 0), "b": ClockOffset(7, 0)}) == ClockSpread("b", "a", 0, 0)
    assert clock_spread({"a": ClockOffset(7, 0)}) is None
    assert clock_spread({}) is None


def test_render_shows_each_hosts_clock_and_the_largest_difference():
    offsets = {"a": ClockOffset(12_300_000, 400_000), "b": ClockOffset(-2_000_000, 300_000), "gone": ClockOffset(0, 0)}
    statuses = {"a": snapshot(1), "b": snapshot(1, host="b")}
    text = _text(render(statuses, {}, ["a", "b", "gone"], (), offsets))
    rows = [line.split() for line in text.splitlines()]
    assert ["host", "state", "uptime", "clock", "detail"] in rows
    assert ["a", "running", "11", "s", "+12.3", "ms", "±0.4"] in rows
    assert ["b", "running", "11", "s", "-2.0", "ms", "±0.3"] in rows
    assert ["gone", "not", "answering", "-", "-"] in rows  # a stale estimate is not shown
    assert "! clocks: a is 14.3 ms ±0.7 ahead of b: more than 5 ms" in text
    near = _text(render(statuses, {}, ["a", "b"], (), {"a": ClockOffset(1_000_000, 50_000), "b": ClockOffset(0, 0)}))
    assert "clocks: a is 1.0 ms ±0.1 ahead of b (the largest difference between two hosts" in near
    assert "!" not in near
    far = _text(render({"a": snapshot(1)}, {}, ["a"], (), {"a": ClockOffset(-3_600_000_000_000, 250_000)}))
    assert ["a", "running", "11", "s", "-3600.0", "s", "±0.2", "ms"] in [line.split() for line in far.splitlines()]
    assert "clocks:" not in far  # one host: no difference to show


def test_report_has_each_hosts_clock_offset_and_bound():
    offsets = {"a": ClockOffset(250 * MS, 400_000), "b": ClockOffset(-2 * MS, 300_000)}
    doc = report({"a": snapshot(1), "b": snapshot(1, host="b")}, {"a": snapshot(0)}, ["a", "b", "c"], ["n"], offsets)
    doc = json.loads(json.dumps(doc, allow_nan=False))
    hosts = {h["host"]: h for h in doc["hosts"]}
    assert (hosts["a"]["clock_offset_ns"], hosts["a"]["clock_uncertainty_ns"]) == (250 * MS, 400_000)
    assert (hosts["b"]["clock_offset_ns"], hosts["b"]["clock_uncertainty_ns"]) == (-2 * MS, 300_000)
    assert hosts["c"] == {
        "host": "c",
        "answering": False,
        "clock_offset_ns": None,
        "clock_uncertainty_ns": None,
        "rates": {},
        "status": None,
    }
    assert hosts["a"]["rates"]["heading"] == {"in": {"imu": 100.0, "odom": 10.0}, "out": {"pose": 10.0}}
    assert hosts["b"]["status"]["uptime_s"] == 11.0
    assert doc["clock_spread"] == {
        "ahead": "a",
        "behind": "b",
        "offset_ns": 252 * MS,
        "uncertainty_ns": 700_000,
        "warn_above_ns": 5 * MS,
        "warn": True,
    }
    assert doc["pipeline"] == "toy" and doc["notes"] == ["n"]


def test_runner_status_carries_the_hosts_clock(tmp_path: Path):
    from rover.cli.registry import BUILTINS
    from rover.pipeline.validation import load_and_check
    from rover.runtime.runner import Runner

    (tmp_path / "toy.yaml").write_text(PIPELINE)
    runner = Runner(load_and_check(tmp_path / "toy.yaml", BUILTINS), "a")
    before = time.time_ns()
    status = runner.status()
    after = time.time_ns()
    assert status.clock_ns is not None and before <= status.clock_ns <= after
    assert status.sent_at == status.clock_ns / 1e9
    assert HostStatus.from_json(status.to_json()).clock_ns == status.clock_ns


def test_local_endpoint():
    assert local_endpoint("tcp/0.0.0.0:7447") == "tcp/127.0.0.1:7447"
    assert local_endpoint("tcp/[::]:7447") == "tcp/[::1]:7447"
    assert local_endpoint("tcp/192.168.1.2:7447") == "tcp/192.168.1.2:7447"


MS = 1_000_000
"""nanoseconds"""


def shifted(offset_ns: int) -> Callable[[], int]:
    """A wall clock `offset_ns` ahead of this machine's."""
    return lambda: time.time_ns() + offset_ns


@contextlib.contextmanager
def serve_status(port: int, clocks: dict[str, Callable[[], int]]) -> Iterator[None]:
    """A router listening on `port`, answering the status of each host in `clocks` (a second later at
    each query), read at the moment it answers from that host's clock, as `Runner.status` does."""
    session = open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="status"))
    queryables: list[zenoh.Queryable[None]] = []
    for host, clock in clocks.items():
        queries = itertools.count()

        def answer(query: zenoh.Query, host: str = host, clock: Callable[[], int] = clock, n=queries) -> None:
            query.reply(status_key("toy", host), replace(snapshot(next(n), host=host), clock_ns=clock()).to_json())

        queryables.append(session.declare_queryable(status_key("toy", host), answer))
    try:
        yield
    finally:
        for queryable in queryables:
            queryable.undeclare()
        session.close()


@pytest.fixture
def host_a() -> Iterator[int]:
    """Host a's status on a free loopback port, its clock 250 ms ahead of this machine's."""
    port = free_port()
    with serve_status(port, {"a": shifted(250 * MS)}):
        yield port


def test_query_status_returns_the_hosts_answer(host_a):
    payloads = query_status("toy", [f"tcp/127.0.0.1:{host_a}"], 5)
    assert [replace(HostStatus.from_json(p), clock_ns=None) for p in payloads] == [snapshot(0)]


def test_client_tries_every_endpoint_and_stays_open(host_a):
    closed = f"tcp/127.0.0.1:{free_port()}"
    with StatusClient("toy", [closed, f"tcp/127.0.0.1:{host_a}"], 5) as client:
        assert [HostStatus.from_json(p).uptime_s for p in client.query()] == [10.0]
        assert [HostStatus.from_json(p).uptime_s for p in client.query()] == [11.0]
        assert client.errors == 0


def test_client_measures_each_hosts_clock_offset():
    """Hosts whose clocks run 250 ms ahead and 100 ms behind this machine's, over real Zenoh: each
    offset is measured within the bound the client states, and so is their difference."""
    port = free_port()
    with (
        serve_status(port, {"a": shifted(250 * MS), "b": shifted(-100 * MS)}),
        StatusClient("toy", [f"tcp/127.0.0.1:{port}"], 5) as client,
    ):
        for _ in range(3):
            statuses, notes = client.poll()
            assert sorted(statuses) == ["a", "b"] and notes == []
        offsets = client.clocks.best()
    for host, true_ns in (("a", 250 * MS), ("b", -100 * MS)):
        got = offsets[host]
        assert abs(got.offset_ns - true_ns) <= got.uncertainty_ns + 1 * MS, (host, got)
        assert got.uncertainty_ns < 100 * MS, (host, got)  # tight enough to tell the clocks apart
    spread = clock_spread(offsets)
    assert spread is not None and (spread.ahead, spread.behind) == ("a", "b") and spread.too_far
    assert abs(spread.offset_ns - 350 * MS) <= spread.uncertainty_ns + 1 * MS
    text = _text(render(statuses, {}, ["a", "b"], (), offsets))
    for host in ("a", "b"):  # the table shows each measured offset and its bound (checked above)
        shown = f"{offsets[host].offset_ns / MS:+.1f} ms ±{offsets[host].uncertainty_ns / MS:.1f}"
        assert re.search(rf"^\s*{host}\s+running\s+12 s\s+{re.escape(shown)}\s*$", text, re.M), text
    ahead = f"a is {spread.offset_ns / MS:.1f} ms ±{spread.uncertainty_ns / MS:.1f} ahead of b: more than 5 ms"
    assert re.search(rf"^! clocks: {re.escape(ahead)}", text, re.M), text


def test_a_host_without_clock_is_noted():
    port = free_port()
    session = open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="old"))
    queryable = session.declare_queryable(
        status_key("toy", "old"), lambda q: q.reply(status_key("toy", "old"), snapshot(host="old").to_json())
    )
    try:
        with StatusClient("toy", [f"tcp/127.0.0.1:{port}"], 5) as client:
            statuses, notes = client.poll()
            assert list(statuses) == ["old"] and client.clocks.best() == {}
    finally:
        queryable.undeclare()
        session.close()
    assert notes == ["host old does not send its clock (an older rover): its offset is unknown"]


def test_a_host_that_is_up_but_not_yet_answering_is_waited_for():
    """The host's router accepts the client before the host declares its status: the first query
    is answered by nobody, and `first_poll` asks again instead of reporting nobody running."""
    port = free_port()
    session = open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="late"))
    queryables: list[zenoh.Queryable[None]] = []
    try:
        with StatusClient("toy", [f"tcp/127.0.0.1:{port}"], 5) as client:
            answers = []
            poll = client.poll

            def poll_then_declare() -> tuple[dict[str, HostStatus], list[str]]:
                answers.append(poll())
                if not queryables:  # the host declares its status after the first query
                    reply = snapshot(host="late").to_json()
                    key = status_key("toy", "late")
                    queryables.append(session.declare_queryable(key, lambda q: q.reply(key, reply)))
                return answers[-1]

            client.poll = poll_then_declare  # type: ignore[method-assign]
            statuses, _ = client.first_poll()
        assert answers[0] == ({}, []) and list(statuses) == ["late"]
    finally:
        for queryable in queryables:
            queryable.undeclare()
        session.close()


def test_a_host_that_never_answers_is_reported_after_the_timeout():
    port = free_port()
    session = open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="silent"))
    try:
        with (
            StatusClient("toy", [f"tcp/127.0.0.1:{port}"], 0.5) as client,
            pytest.raises(TransportError, match="no host of pipeline toy answered"),
        ):
            client.first_poll()
    finally:
        session.close()


def test_nothing_listening_is_a_transport_error_naming_the_endpoints():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started = time.monotonic()
    with pytest.raises(TransportError, match=f"no host of pipeline toy answered at {endpoint} \\(is it running\\?\\)"):
        query_status("toy", [endpoint], 0.5)
    assert time.monotonic() - started < 5


PIPELINE = """\
version: 1
name: toy
vars: {port: 7447}
hosts:
  a: {listen: ["tcp/0.0.0.0:${port}"]}
  b: {connect: ["tcp/127.0.0.1:${port}"]}
operators:
  replay:  {uses: dataset_replay, host: a, params: {path: data.mcap}}
  record:  {uses: recorder, host: b, inputs: {imu: replay/imu}, params: {out: out}}
"""


def test_cli_once_prints_hosts_and_operators(host_a, tmp_path: Path):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(PIPELINE)
    proc = run_rover("status", str(pipeline), "--set", f"port={host_a}", "--once", "--interval", "0.05", timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    assert "1 of 2 hosts answering" in proc.stdout
    assert "not answering" in proc.stdout
    assert "heading" in proc.stdout and "replay" in proc.stdout
    assert "100.0" in proc.stdout  # the rate between the two snapshots
    assert re.search(r"^\s*host\s+state\s+uptime\s+clock\s+detail\s*$", proc.stdout, re.M), proc.stdout
    assert re.search(r"^\s*a\s+running\s+11 s\s+\+2[45]\d\.\d ms ±\d+\.\d\s*$", proc.stdout, re.M), proc.stdout


def test_cli_json_has_each_hosts_clock_offset(host_a, tmp_path: Path):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(PIPELINE)
    proc = run_rover(
        "status", str(pipeline), "--set", f"port={host_a}", "--once", "--interval", "0.05", "--json", timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    hosts = {h["host"]: h for h in doc["hosts"]}
    a = hosts["a"]
    assert abs(a["clock_offset_ns"] - 250 * MS) <= a["clock_uncertainty_ns"] + 1 * MS, a
    assert a["status"]["host"] == "a" and a["rates"]["heading"]["in"] == {"imu": 100.0, "odom": 10.0}
    assert hosts["b"]["answering"] is False and hosts["b"]["clock_offset_ns"] is None
    assert doc["clock_spread"] is None  # one host answering


def test_cli_with_nothing_listening_is_one_line_and_status_2(tmp_path: Path):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(PIPELINE)
    port = free_port()
    started = time.monotonic()
    proc = run_rover("status", str(pipeline), "--set", f"port={port}", "--timeout", "1", timeout=60)
    assert time.monotonic() - started < 15
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr == (f"rover: error: no host of pipeline toy answered at tcp/127.0.0.1:{port} (is it running?)\n")


def test_cli_bad_options_are_one_line(tmp_path: Path):
    pipeline = tmp_path / "toy.yaml"
    pipeline.write_text(PIPELINE)
    proc = run_rover("status", str(pipeline), "--connect", "localhost", timeout=60)
    assert proc.returncode == 2 and proc.stderr.startswith("rover: error: --connect: bad endpoint 'localhost'")
    proc = run_rover("status", str(pipeline), "--interval", "0", timeout=60)
    assert proc.returncode == 2 and proc.stderr == "rover: error: --interval: a number of seconds above 0, got 0\n"
    (tmp_path / "alone.yaml").write_text("name: alone\noperators:\n  replay: {uses: dataset_replay}\n")
    proc = run_rover("status", str(tmp_path / "alone.yaml"), timeout=60)
    assert proc.returncode == 2 and "no host of pipeline alone listens on an endpoint" in proc.stderr


@pytest.mark.parametrize(
    ("state", "detail"),
    [("waiting", "waiting for b, c"), ("running", "running with b, c"), ("finishing", "waiting for b, c to finish")],
)
def test_the_other_hosts_are_named_for_what_this_one_waits_on(state, detail):
    """Before the run the others are not ready; while it runs they are not done, which is no wait."""
    status = dataclasses.replace(snapshot(0), state=state, waiting_for=["b", "c"])
    assert detail in _text(render({"a": status}, {}, ["a", "b", "c"]))


def test_a_table_written_to_a_pipe_is_whole():
    import io

    from rover.cli.status import show

    hosts = [f"host_with_a_long_name_{i}" for i in range(6)]
    status = dataclasses.replace(snapshot(0), state="waiting", waiting_for=hosts)
    out = io.StringIO()
    show(render({"a": status}, {}, ["a", *hosts]), file=out)
    assert "…" not in out.getvalue() and f"waiting for {', '.join(hosts)}" in out.getvalue()
