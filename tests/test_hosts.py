"""The default pipeline split over three hosts on a real network, and what the hosts do when the
network or a host fails: three network namespaces joined by a bridge (tests/netns.py), with
packet loss (nftables), latency (tests/relay.py), pulled cables, killed and interrupted hosts.

Needs root, `ip` and `nft`: without them these tests fail loudly (ROVER_SKIP_NETNS=1 skips them).
Each run of the default pipeline on the simulated dataset takes about 30 s on two cores.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import popen_rover, read_bag, run_rover, wait_until
from netns import ADDRESSES, Lab, lab_certs, pipeline_file, require_root

pytestmark = pytest.mark.netns  # builds network namespaces (tests/netns.py)

HOSTS = ("laptop", "base", "nuc")
"""Start order: the NUC, where the others connect, last (they retry until it listens)."""
PORT = 7447
"""The NUC's port; every lab has its own namespaces, so it is never busy."""
RELAY_PORT = 7448
COMPARED = ("results.mcap", "trajectory.tum", "trajectory_live.tum", "tags.csv", "metrics.json")
MID_RUN_BYTES = 1_000_000
"""What the laptop has received about a third of the way into a run (it receives ~3 MB in all)."""
PACED = ("--speed", "4")
"""The failure tests replay at 4x real time: the 90 s dataset lasts ~23 s, time to act mid-run."""
RUN_S = 180.0
"""The longest a run of the hosts may take in these tests."""
OUTAGE_S = 4.0
LONG_OUTAGE_S = 8.0
"""Longer than the host_timeout_s: 3 of that test, shorter than the default (15 s)."""
WAIT_BUDGET_S = 11.0
"""A lone host with wait_timeout_s: 4 must have given up by then (startup takes ~3 s)."""


# -- fixtures and helpers


@pytest.fixture(scope="module")
def root() -> None:
    """Fail (or skip) before the slow module fixtures when the lab cannot be built."""
    require_root()


@pytest.fixture(scope="module")
def dataset(root, tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sim") / "sim.mcap"
    run_rover("simulate", "--set", "trajectory.laps=1", "--seed", "5", "-o", str(path), check=True, timeout=300)
    return path


class Reference:
    """The one-process run of the dataset: started when first asked for, so that it runs beside
    the first multi-host run (two cores: each uses about one), and waited for when compared."""

    def __init__(self, dataset: Path, out: Path):
        self.out = out
        self.proc = popen_rover("run", "--dataset", str(dataset), "--output", str(out))
        self._files: dict[str, bytes] | None = None

    def files(self) -> dict[str, bytes]:
        if self._files is None:
            _out, err = self.proc.communicate(timeout=300)
            assert self.proc.returncode == 0, f"the one-process run exited {self.proc.returncode}:\n{err}"
            self._files = {name: (self.out / name).read_bytes() for name in COMPARED}
        return self._files


@pytest.fixture(scope="module")
def reference(dataset, tmp_path_factory):
    ref = Reference(dataset, tmp_path_factory.mktemp("one"))
    yield ref
    if ref.proc.poll() is None:
        ref.proc.kill()
    ref.proc.communicate()


@pytest.fixture
def lab(root):
    with Lab() as lab:
        yield lab


def start(
    lab: Lab,
    pipeline: Path,
    dataset: Path,
    out: Path,
    *extra: str,
    hosts: tuple[str, ...] = HOSTS,
    ports: dict[str, int] | None = None,
) -> dict[str, subprocess.Popen]:
    """`rover run PIPELINE --host H` for each host in its namespace, all writing to `out` (only
    the laptop writes there). `ports`: a host's value of ${port} when not PORT."""
    return {
        host: lab.popen(
            host,
            "run",
            str(pipeline),
            "--host",
            host,
            "--dataset",
            str(dataset),
            "--output",
            str(out),
            "--set",
            f"port={(ports or {}).get(host, PORT)}",
            *extra,
        )
        for host in hosts
    }


def finish(procs: dict[str, subprocess.Popen], timeout_s: float = RUN_S) -> dict[str, tuple[int, str]]:
    """(exit status, stderr) of each host once all have ended."""
    deadline = time.monotonic() + timeout_s
    results = {}
    for host, proc in procs.items():
        try:
            _out, err = proc.communicate(timeout=max(1.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            _out, err = proc.communicate()
            err += f"\n[test: {host} still running after {timeout_s:g} s, killed]"
        results[host] = (proc.returncode, err)
    return results


def statuses(results: dict[str, tuple[int, str]]) -> dict[str, int]:
    return {host: rc for host, (rc, _err) in results.items()}


def stderrs(results: dict[str, tuple[int, str]]) -> str:
    return "\n".join(f"--- {host} ({rc}):\n{err}" for host, (rc, err) in results.items())


def assert_same_outputs(out: Path, reference: Reference) -> None:
    expected = reference.files()
    for name in COMPARED:
        assert (out / name).read_bytes() == expected[name], f"{name} differs from the one-process run"


def names(host: str, text: str) -> bool:
    """Whether `text` names `host` as a word (not inside a name like a tmp path's `test_drop_of_base_0`)."""
    return re.search(rf"(?<![\w-]){host}(?![\w-])", text) is not None


def run_json(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def no_tracebacks(results: dict[str, tuple[int, str]]) -> None:
    for host, (_rc, err) in results.items():
        assert "Traceback" not in err, f"{host}:\n{err}"


# -- the harness itself


def test_the_lab_joins_three_namespaces_on_a_bridge_and_removes_them(root):
    """The lab makes four namespaces (three hosts and the switch), leaves the machine's own
    interfaces alone, lets every host reach every other over TCP, and removes everything on exit,
    even when the test inside failed."""

    def links() -> set[str]:
        done = subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True, check=True)
        return {line.split(":")[1].strip() for line in done.stdout.splitlines()}

    before = links()
    with Lab() as lab:
        assert len(lab.namespaces()) == 4
        assert links() == before, "the lab changed the machine's own namespace"
        server = lab.spawn("nuc", sys.executable, "-c", ECHO, ADDRESSES["nuc"], "9000", stdout=subprocess.PIPE)
        assert server.stdout is not None and server.stdout.readline() == b"ready\n"
        for host in ("base", "laptop"):
            probe = lab.python(host, ROUND_TRIP, ADDRESSES["nuc"], "9000", "1")
            assert probe.returncode == 0, probe.stderr
        ns = lab.ns["nuc"]
    assert lab.namespaces() == []
    assert lab.procs[0].poll() is not None, "the lab left a process running"
    with pytest.raises(ZeroDivisionError), Lab() as failing:
        assert len(failing.namespaces()) == 4
        _ = 1 / 0
    assert failing.namespaces() == []
    assert ns not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout


def test_without_root_or_tools_the_tests_fail_loudly_or_skip_when_asked(monkeypatch):
    """Without root (or without `ip`/`nft`) the tests fail with a message saying why, and skip
    instead only when ROVER_SKIP_NETNS=1."""
    monkeypatch.delenv("ROVER_SKIP_NETNS", raising=False)
    with monkeypatch.context() as m:
        m.setattr(os, "geteuid", lambda: 1000)
        with pytest.raises(pytest.fail.Exception, match="need root"):
            require_root()
        m.setenv("ROVER_SKIP_NETNS", "1")
        with pytest.raises(pytest.skip.Exception, match="ROVER_SKIP_NETNS=1"):
            require_root()
    monkeypatch.setattr(shutil, "which", lambda cmd: None if cmd == "nft" else "/usr/sbin/ip")
    with pytest.raises(pytest.fail.Exception, match="nftables"):
        require_root()


ECHO = r"""
import socket, sys, threading
server = socket.socket()
server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
server.bind((sys.argv[1], int(sys.argv[2])))
server.listen()
print("ready", flush=True)
def echo(conn):
    while data := conn.recv(65536):
        conn.sendall(data)
while True:
    threading.Thread(target=echo, args=(server.accept()[0],), daemon=True).start()
"""

ROUND_TRIP = r"""
import json, socket, sys, time
conn = socket.create_connection((sys.argv[1], int(sys.argv[2])), timeout=10)
conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
def receive(n):
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        assert chunk, "connection closed"
        data += chunk
    return data
t = time.monotonic()
conn.sendall(b"ping")
assert receive(4) == b"ping"
one = time.monotonic() - t
messages = [bytes([i]) * 1000 for i in range(int(sys.argv[3]))]
t = time.monotonic()
for m in messages:
    conn.sendall(m)
    time.sleep(0.01)
assert receive(len(messages) * 1000) == b"".join(messages), "reordered or corrupted"
print(json.dumps({"one": one, "burst": time.monotonic() - t}))
"""


def test_the_relay_delays_both_directions_in_order_without_limiting_throughput(lab):
    """Through the relay a round trip takes twice its delay more than directly; a stream of 40
    messages sent 10 ms apart takes one round trip more, not forty, and comes back in order."""
    delay = 0.2
    server = lab.spawn("nuc", sys.executable, "-c", ECHO, ADDRESSES["nuc"], "9000", stdout=subprocess.PIPE)
    assert server.stdout is not None and server.stdout.readline() == b"ready\n"
    lab.relay("nuc", 9001, f"{ADDRESSES['nuc']}:9000", delay)
    direct = lab.python("base", ROUND_TRIP, ADDRESSES["nuc"], "9000", "40")
    relayed = lab.python("base", ROUND_TRIP, ADDRESSES["nuc"], "9001", "40")
    assert direct.returncode == 0 and relayed.returncode == 0, direct.stderr + relayed.stderr
    d, r = json.loads(direct.stdout), json.loads(relayed.stdout)
    assert d["one"] < 0.05, d
    assert 2 * delay <= r["one"] < 2 * delay + 0.1, r
    sending = d["burst"]  # 40 x 10 ms
    assert sending + 2 * delay - 0.05 < r["burst"] < sending + 2 * delay + 0.2, (d, r)


def test_the_loss_rule_drops_a_share_of_outgoing_packets_and_counts_them(lab):
    """`lab.loss(30)` drops about 30 % of a host's outgoing packets on its link (each drop is an
    EPERM for a UDP sender, and counted by the rule); `lab.loss(0)` removes the rule."""
    send = r"""
import socket, sys
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
refused = 0
for _ in range(1000):
    try:
        s.sendto(b"x", (sys.argv[1], 9))
    except PermissionError:
        refused += 1
print(refused)
"""
    lab.loss(30, hosts=["base"])
    sent = lab.python("base", send, ADDRESSES["nuc"])
    assert sent.returncode == 0, sent.stderr
    lost = lab.lost_packets()
    assert 200 < lost["base"] < 400, lost
    assert lost["base"] == int(sent.stdout), (lost, sent.stdout)
    assert lost["nuc"] == lost["laptop"] == 0, lost
    lab.loss(0)
    assert lab.lost_packets() == {"nuc": 0, "base": 0, "laptop": 0}


# -- the pipeline on three hosts


def test_three_hosts_under_mutual_tls_give_the_same_bytes_as_one_process(lab, tmp_path, dataset, reference):
    """The default pipeline's real stages (sweep, decode, AoA holding its bursts, preintegration, SLAM
    merging several inputs) split over three namespaces that reach each other only through the
    bridge, under `security:` (mutual TLS, access control generated from the wiring: a rule too
    narrow would starve a stage), write the same results.mcap, trajectories, tags and metrics,
    byte for byte, as one process (wall-clock timings go to timing.json, not into results.mcap),
    and every host exits 0. The plain-TCP split is compared byte for byte by the loss test below."""
    out = tmp_path / "out"
    pipeline = pipeline_file(tmp_path, certs=lab_certs(tmp_path / "certs"))
    assert "tls/" in pipeline.read_text() and "tcp/" not in pipeline.read_text()
    results = finish(start(lab, pipeline, dataset, out))
    assert statuses(results) == {"laptop": 0, "base": 0, "nuc": 0}, stderrs(results)
    assert_same_outputs(out, reference)
    topics = {t for t, _s, _d in read_bag(out / "results.mcap")}
    assert topics == {
        "/rover/aoa",
        "/rover/bearings",
        "/rover/preintegration",
        "/rover/sweep",
        "/rover/pose",
        "/rover/trajectory",
        "/rover/path",
        "/rover/tags",
        "/rover/tag_status",
        "/rover/slam/diagnostics",
    }
    timing = json.loads((out / "timing.json").read_text())
    update = timing["slam.update"]
    assert update["count"] > 100 and 0 < update["median_s"] < update["max_s"]


def test_1_percent_loss_and_50_ms_delay_give_the_same_bytes(lab, tmp_path, dataset, reference):
    """With 1 % of every host's outgoing packets dropped and 50 ms added each way between the NUC
    and the others, the outputs are still byte-identical to one process's (exit 0 everywhere).

    The relay runs in the NUC's namespace on RELAY_PORT and forwards to the NUC's PORT; base and
    laptop run with ${port} set to the relay's port, so their own copy of the pipeline says the
    NUC listens there (what `rover check` verifies), while the NUC listens on the real port."""
    relay = lab.relay("nuc", RELAY_PORT, f"{ADDRESSES['nuc']}:{PORT}", 0.05)
    lab.loss(1)
    out = tmp_path / "out"
    procs = start(lab, pipeline_file(tmp_path), dataset, out, ports={"base": RELAY_PORT, "laptop": RELAY_PORT})
    results = finish(procs)
    assert statuses(results) == {"laptop": 0, "base": 0, "nuc": 0}, stderrs(results)
    assert relay.poll() is None, "the relay died during the run"
    lost = lab.lost_packets()
    assert all(n > 0 for n in lost.values()), f"the loss rule dropped nothing somewhere: {lost}"
    assert_same_outputs(out, reference)


def test_a_drop_of_base_for_4_s_mid_run_gives_the_same_bytes(lab, tmp_path, dataset, reference):
    """Base's cable pulled at the switch for 4 s, a third of the way into the run: the TCP
    connections and Zenoh sessions survive, the run resumes where it was, and the outputs are
    byte-identical to one process's, exit 0 everywhere."""
    out = tmp_path / "out"
    procs = start(lab, pipeline_file(tmp_path), dataset, out, *PACED)
    lab.wait_received("laptop", MID_RUN_BYTES, list(procs.values()))
    lab.link_down("base")
    try:
        cut = lab.rx_bytes("base")
        time.sleep(OUTAGE_S)  # the outage itself
        assert lab.rx_bytes("base") == cut, "base received packets while its link was down"
    finally:
        lab.link_up("base")
    results = finish(procs)
    assert statuses(results) == {"laptop": 0, "base": 0, "nuc": 0}, stderrs(results)
    assert_same_outputs(out, reference)


# -- lost hosts: partial results (status 3, docs/exit-codes.md)


def test_kill_9_of_the_preintegration_host_mid_run_leaves_partial_results(lab, tmp_path, dataset):
    """kill -9 of base a third of the way into the run: the laptop finishes what it has and exits
    3 with results.mcap (readable), trajectory.tum, tags.csv and a run.json saying `partial`, lost
    base; its stderr has one error line, naming base, and no traceback. The NUC lost base too: exit 3."""
    out = tmp_path / "out"
    procs = start(lab, pipeline_file(tmp_path), dataset, out, *PACED)
    lab.wait_received("laptop", MID_RUN_BYTES, list(procs.values()))
    procs["base"].send_signal(signal.SIGKILL)
    results = finish(procs)
    rc, err = results["laptop"]
    assert rc == 3, stderrs(results)
    for name in ("results.mcap", "trajectory.tum", "tags.csv", "run.json"):
        assert (out / name).is_file(), f"no {name} in {sorted(p.name for p in out.iterdir())}"
    assert read_bag(out / "results.mcap"), "the partial results.mcap holds no message"
    run = run_json(out)
    assert run["status"] == "partial", run
    assert names("base", run["reason"]), run
    assert [lost["host"] for lost in run["lost"]] == ["base"], run
    errors = [line for line in err.splitlines() if line.startswith("rover: error:")]
    assert len(errors) == 1 and names("base", errors[0]), f"not one error line naming base:\n{err}"
    no_tracebacks(results)
    assert statuses(results) == {"laptop": 3, "base": -signal.SIGKILL, "nuc": 3}, stderrs(results)


def test_ctrl_c_on_the_hub_mid_run_leaves_partial_results_on_the_others(lab, tmp_path, dataset):
    """SIGINT to the NUC a third of the way into the run: the NUC stops as interrupted (130);
    base and laptop lost the hub and exit 3; the laptop's run.json is partial, and its stderr
    says that the hub, nuc, was lost and base became unreachable with it."""
    out = tmp_path / "out"
    procs = start(lab, pipeline_file(tmp_path), dataset, out, *PACED)
    lab.wait_received("laptop", MID_RUN_BYTES, list(procs.values()))
    procs["nuc"].send_signal(signal.SIGINT)
    results = finish(procs)
    assert statuses(results) == {"laptop": 3, "base": 3, "nuc": 130}, stderrs(results)
    no_tracebacks(results)
    run = run_json(out)
    assert run["status"] == "partial", run
    lost = {entry["host"] for entry in run["lost"]}
    assert "nuc" in lost, run
    assert "base" in lost or names("base", run["reason"]), run
    err = results["laptop"][1]
    assert any("hub" in line and names("nuc", line) for line in err.splitlines()), err
    assert names("base", err), err


def test_a_drop_of_base_longer_than_host_timeout_leaves_partial_results(lab, tmp_path, dataset):
    """With host_timeout_s: 3, base's cable pulled for 8 s a third of the way in (an outage the
    default host_timeout_s, 15 s, rides out): the laptop gives base up, exits 3, and its run.json
    is partial, lost base."""
    out = tmp_path / "out"
    procs = start(lab, pipeline_file(tmp_path, host_timeout_s=3), dataset, out, *PACED)
    lab.wait_received("laptop", MID_RUN_BYTES, list(procs.values()))
    lab.link_down("base")
    try:
        with contextlib.suppress(subprocess.TimeoutExpired):
            procs["laptop"].wait(timeout=LONG_OUTAGE_S)  # the outage, cut short once the laptop gave up
    finally:
        lab.link_up("base")
    results = finish({"laptop": procs["laptop"]})
    rc, err = results["laptop"]
    assert rc == 3, err
    no_tracebacks(results)
    run = run_json(out)
    assert run["status"] == "partial", run
    assert names("base", run["reason"]), run
    assert "base" in {entry["host"] for entry in run["lost"]}, run


def test_a_lone_host_gives_up_waiting_after_wait_timeout(lab, tmp_path, dataset):
    """Only the laptop started, with wait_timeout_s: 4: it says (at the default log level) that
    it is waiting for nuc and base, then gives up: exit 2 within ~10 s, one error line naming both."""
    pipeline = pipeline_file(tmp_path, wait_timeout_s=4)
    began = time.monotonic()
    laptop = start(lab, pipeline, dataset, tmp_path / "out", hosts=("laptop",))["laptop"]
    with contextlib.suppress(subprocess.TimeoutExpired):
        laptop.wait(timeout=60)
    took = time.monotonic() - began
    results = finish({"laptop": laptop})
    rc, err = results["laptop"]
    assert rc == 2, err
    assert took < WAIT_BUDGET_S, f"exited after {took:.1f} s"
    no_tracebacks(results)
    lines = err.splitlines()
    errors = [i for i, line in enumerate(lines) if line.startswith("rover: error:")]
    assert len(errors) == 1, err
    assert names("nuc", lines[errors[0]]) and names("base", lines[errors[0]]), err
    assert any("waiting for" in line and names("nuc", line) and names("base", line) for line in lines[: errors[0]]), (
        f"no 'waiting for' line naming nuc and base before the error:\n{err}"
    )


def test_wait_until_fails_when_a_process_ends_first(lab):
    """The mid-run trigger never waits for a run that already ended: it fails, with its stderr."""
    done = lab.spawn("base", sys.executable, "-c", "import sys; sys.exit('bye')", stderr=subprocess.PIPE, text=True)
    with pytest.raises(AssertionError, match=r"(?s)ended \(1\).*bye"):
        wait_until(lambda: False, "never", procs=[done], timeout_s=30)
