"""`rover status`: the status snapshot and its JSON, rates, the table, the Zenoh query and the command."""

from __future__ import annotations

import itertools
import json
import time
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest
import zenoh
from conftest import free_port, run_rover
from rich.console import Console

from rover.errors import TransportError
from rover.runtime.status import (
    HostStatus,
    OperatorStatus,
    StatusError,
    collect,
    rates,
    render,
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
    ],
)
def test_from_json_names_the_bad_field(payload, field):
    with pytest.raises(StatusError) as raised:
        HostStatus.from_json(payload)
    assert raised.value.field == field
    assert str(raised.value).startswith(f"{field}: " if field else "not a UTF-8 JSON status")


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
    assert ["b", "not", "answering", "-"] in rows
    assert ["a", "running", "11", "s", "lost", "c"] in rows
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


def test_render_without_previous_snapshot_shows_no_rate():
    rows = [line.split() for line in _text(render({"a": snapshot(0)}, {}, ["a"])).splitlines()]
    assert ["a", "heading", "imu", "-", "pose", "-", "3/17", "0.250", "s", "imu", "2"] in rows
    assert ["odom", "-"] in rows


def test_local_endpoint():
    assert local_endpoint("tcp/0.0.0.0:7447") == "tcp/127.0.0.1:7447"
    assert local_endpoint("tcp/[::]:7447") == "tcp/[::1]:7447"
    assert local_endpoint("tcp/192.168.1.2:7447") == "tcp/192.168.1.2:7447"


@pytest.fixture
def host_a() -> Iterator[int]:
    """A router listening on a free loopback port, answering host a's status, a second later at each query."""
    port = free_port()
    queries = itertools.count()
    session = open_session(SessionSpec(listen=[f"tcp/127.0.0.1:{port}"], label="a"))

    def answer(query: zenoh.Query) -> None:
        query.reply(status_key("toy", "a"), snapshot(next(queries)).to_json())

    queryable = session.declare_queryable(status_key("toy", "a"), answer)
    try:
        yield port
    finally:
        queryable.undeclare()
        session.close()


def test_query_status_returns_the_hosts_answer(host_a):
    payloads = query_status("toy", [f"tcp/127.0.0.1:{host_a}"], 5)
    assert [HostStatus.from_json(p) for p in payloads] == [snapshot(0)]


def test_client_tries_every_endpoint_and_stays_open(host_a):
    closed = f"tcp/127.0.0.1:{free_port()}"
    with StatusClient("toy", [closed, f"tcp/127.0.0.1:{host_a}"], 5) as client:
        assert [HostStatus.from_json(p).uptime_s for p in client.query()] == [10.0]
        assert [HostStatus.from_json(p).uptime_s for p in client.query()] == [11.0]
        assert client.errors == 0


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
