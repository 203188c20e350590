"""Three hosts on one machine: network namespaces joined by a bridge, for multi-host tests.

    with Lab() as lab:
        nuc = lab.popen("nuc", "run", str(pipeline), "--host", "nuc", ...)
        lab.link_down("base"); ...; lab.link_up("base")

Layout (every name unique per test, `rvr-<pid>-<n>-...`, so leftovers of a crashed run never
collide; namespaces of runs whose process is gone are removed when the next Lab starts):

    namespace rvr-P-N-sw:      bridge br0, ports `nuc`, `base`, `laptop` (the switch side of each veth)
    namespace rvr-P-N-nuc:     eth0 10.77.0.1/24, lo
    namespace rvr-P-N-base:    eth0 10.77.0.2/24, lo
    namespace rvr-P-N-laptop:  eth0 10.77.0.3/24, lo

Nothing is created in the machine's own namespace. Needs root and the `ip` (iproute2) and `nft`
(nftables) commands; without root the tests fail loudly, or skip with ROVER_SKIP_NETNS=1.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import pytest
from helpers import wait_until

from rover.security.certs import issue

TESTS = Path(__file__).resolve().parent
SUBNET = "10.77.0"
ROOT = Path(__file__).resolve().parent.parent
"""the repository"""
ADDRESSES = {"nuc": f"{SUBNET}.1", "base": f"{SUBNET}.2", "laptop": f"{SUBNET}.3"}
"""The default hosts and their addresses (a /24)."""
IFACE = "eth0"
"""Each host's end of its veth, inside its namespace."""
BRIDGE = "br0"
PREFIX = "rvr"
LOSS_TABLE = "rvr_loss"
POLL_S = 0.05
READY_S = 10.0
"""The longest a relay may take to start listening."""

_labs = itertools.count()


def require_root() -> None:
    """Fail loudly unless the lab can be built: root, `ip` and `nft`. With ROVER_SKIP_NETNS=1 the
    test is skipped instead of failed (for machines where these tests cannot run at all)."""
    skip = os.environ.get("ROVER_SKIP_NETNS") == "1"
    problem = None
    if os.geteuid() != 0:
        problem = (
            "the multi-host tests build network namespaces and need root (run pytest as root, e.g. in "
            "the dev container); set ROVER_SKIP_NETNS=1 to skip them instead"
        )
    else:
        tools = {"ip": "iproute2", "nft": "nftables"}
        missing = {cmd: pkg for cmd, pkg in tools.items() if shutil.which(cmd) is None}
        if missing:
            problem = (
                f"the multi-host tests need {' and '.join(f'`{cmd}`' for cmd in missing)}: "
                f"apt-get install {' '.join(missing.values())} (Debian packages)"
            )
    if problem is None:
        return
    if skip:
        pytest.skip(f"ROVER_SKIP_NETNS=1: skipped although {problem}")
    pytest.fail(f"\n{'!' * 78}\n!!! CANNOT RUN THE MULTI-HOST TESTS: {problem}\n{'!' * 78}", pytrace=False)


def _run(*argv: str, stdin: str | None = None) -> str:
    """Run a command; its stdout, or a RuntimeError with its stderr."""
    done = subprocess.run(argv, input=stdin, capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.strip()}")
    return done.stdout


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _namespaces() -> list[str]:
    return [line.split()[0] for line in _run("ip", "netns", "list").splitlines() if line.strip()]


def remove_stale_namespaces() -> list[str]:
    """Delete the namespaces of labs whose test process is gone (a crashed or killed run); their names."""
    stale = []
    for name in _namespaces():
        match = re.match(rf"^{PREFIX}-(\d+)-\d+-", name)
        if match and not _alive(int(match.group(1))):
            with contextlib.suppress(RuntimeError):
                _run("ip", "netns", "del", name)
                stale.append(name)
    return stale


def rover_env() -> dict[str, str]:
    """The environment of conftest's popen_rover: the tests' operators importable."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))


class Lab:
    """Hosts in network namespaces on one bridge; every process started here is killed and every
    namespace removed on exit, whatever happened."""

    def __init__(self, addresses: dict[str, str] | None = None):
        self.addresses = dict(addresses or ADDRESSES)
        for host in self.addresses:
            assert re.fullmatch(r"[a-z][a-z0-9]{0,14}", host), f"host name {host!r}: a short interface name"
        self.tag = f"{PREFIX}-{os.getpid()}-{next(_labs)}"
        self.switch = f"{self.tag}-sw"
        self.ns = {host: f"{self.tag}-{host}" for host in self.addresses}
        self.procs: list[subprocess.Popen] = []
        self._made: list[str] = []

    # -- building and tearing down

    def __enter__(self) -> Lab:
        require_root()
        remove_stale_namespaces()
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, exc_type: object, *_exc: object) -> None:
        problems = self.close()
        assert exc_type is not None or not problems, f"could not remove the lab's namespaces: {problems}"

    def _netns_add(self, name: str) -> None:
        _run("ip", "netns", "add", name)
        self._made.append(name)
        _run("ip", "-n", name, "link", "set", "lo", "up")

    def _build(self) -> None:
        self._netns_add(self.switch)
        _run("ip", "-n", self.switch, "link", "add", BRIDGE, "type", "bridge")
        _run("ip", "-n", self.switch, "link", "set", BRIDGE, "up")
        for host, address in self.addresses.items():
            ns = self.ns[host]
            self._netns_add(ns)
            _run("ip", "-n", self.switch, "link", "add", host, "type", "veth", "peer", "name", IFACE, "netns", ns)
            _run("ip", "-n", self.switch, "link", "set", host, "master", BRIDGE)
            _run("ip", "-n", self.switch, "link", "set", host, "up")
            _run("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", IFACE)
            _run("ip", "-n", ns, "link", "set", IFACE, "up")

    def close(self) -> list[str]:
        """Kill what was started here, then delete the namespaces (the veths and bridge go with them);
        what could not be deleted."""
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
            with contextlib.suppress(Exception):
                proc.communicate(timeout=10)
        problems = []
        for name in reversed(self._made):
            # Anything still inside one of this lab's namespaces was started by this lab.
            with contextlib.suppress(RuntimeError):
                for pid in _run("ip", "netns", "pids", name).split():
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(int(pid), signal.SIGKILL)
            try:
                _run("ip", "netns", "del", name)
            except RuntimeError as exc:
                problems.append(str(exc))
        self._made.clear()
        return problems

    def namespaces(self) -> list[str]:
        """This lab's namespaces that exist now (for checking that they were removed)."""
        mine = {self.switch, *self.ns.values()}
        return [name for name in _namespaces() if name in mine]

    # -- processes

    def exec_argv(self, host: str, *argv: str) -> list[str]:
        """`argv` run inside `host`'s namespace. `ip netns exec` execs the command in place (it forks
        only with -all or -b), so the pid of a Popen of this is the command's own pid and signals
        (kill -9 included) reach it directly."""
        return ["ip", "netns", "exec", self.ns[host], *argv]

    def spawn(self, host: str, *argv: str, **kwargs) -> subprocess.Popen:
        """Start `argv` inside `host`'s namespace; killed when the lab closes. Its standard streams
        are the null device unless given: it never holds the test runner's output open."""
        for stream in ("stdin", "stdout", "stderr"):
            kwargs.setdefault(stream, subprocess.DEVNULL)
        proc = subprocess.Popen(self.exec_argv(host, *argv), **kwargs)
        self.procs.append(proc)
        return proc

    def popen(self, host: str, *rover_args: str, cwd: Path | None = None) -> subprocess.Popen:
        """`rover ROVER_ARGS` (python -m rover.cli) inside `host`'s namespace, as conftest's popen_rover:
        the tests' operators importable, stdout and stderr piped, text."""
        return self.spawn(
            host,
            sys.executable,
            "-m",
            "rover.cli",
            *rover_args,
            cwd=cwd,
            env=rover_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )

    def python(self, host: str, code: str, *args: str) -> subprocess.CompletedProcess:
        """Run a Python snippet inside `host`'s namespace and wait for it (for checks of the lab itself)."""
        argv = self.exec_argv(host, sys.executable, "-c", code, *args)
        return subprocess.run(argv, capture_output=True, text=True, timeout=60)

    # -- faults

    def link_down(self, host: str) -> None:
        """Pull `host`'s cable at the switch: the bridge-side end of its veth goes down.

        The host's own eth0 stays administratively up and only loses carrier, as a real NIC would,
        so its address and routes stay; every packet to or from the host is lost until `link_up`.
        TCP connections survive it (measured over a 4 s cut, same connection before and after):
        what the host itself sends resumes ~0.1 s after `link_up` (its sends die at its own
        carrier-less interface and are retried without backoff). The other candidate, an nftables
        rule dropping all the host's packets, also keeps connections but delays that by the host's
        retransmission backoff: 2.5 s after the rule is removed. What another host sends *to* the
        cut host resumes ~2.5 s after `link_up` either way (that sender's timer backs off
        0.2, 0.4, ... 3.2 s): a 4 s cut stalls a busy stream towards the host ~6.5 s, which is
        past Zenoh's default `congestion_control/block/wait_before_close` (5 s, after which a link
        whose blocking queue stayed full is closed). Zenoh's lease is a separate, longer limit."""
        _run("ip", "-n", self.switch, "link", "set", host, "down")

    def link_up(self, host: str) -> None:
        """Plug `host`'s cable back in (the bridge has no STP, so its port forwards at once)."""
        _run("ip", "-n", self.switch, "link", "set", host, "up")

    def loss(self, percent: int, hosts: Iterable[str] | None = None) -> None:
        """Drop `percent` % of every host's outgoing IPv4 packets on its eth0, at random (nftables
        `numgen random mod 100 < N`, with a counter); 0 removes the rule. IPv4 only: the lab's traffic
        is IPv4, and the kernel's own IPv6 chatter on a fresh link (router solicitations, MLD) would
        otherwise be dropped and counted too."""
        assert 0 <= percent <= 100 and percent == int(percent), percent
        for host in hosts if hosts is not None else self.addresses:
            script = f"table inet {LOSS_TABLE}\ndelete table inet {LOSS_TABLE}\n"
            if percent:
                script += (
                    f"table inet {LOSS_TABLE} {{\n"
                    "  chain out {\n"
                    "    type filter hook output priority 0; policy accept;\n"
                    f'    oifname "{IFACE}" meta nfproto ipv4 numgen random mod 100 < {int(percent)} counter drop\n'
                    "  }\n"
                    "}\n"
                )
            _run("ip", "netns", "exec", self.ns[host], "nft", "-f", "-", stdin=script)

    def lost_packets(self) -> dict[str, int]:
        """Per host, the packets the loss rule dropped so far (0 without a rule)."""
        counts = {}
        for host, ns in self.ns.items():
            try:
                listing = json.loads(_run("ip", "netns", "exec", ns, "nft", "-j", "list", "table", "inet", LOSS_TABLE))
            except RuntimeError:
                counts[host] = 0
                continue
            counts[host] = sum(
                expr["counter"]["packets"]
                for item in listing["nftables"]
                if "rule" in item
                for expr in item["rule"]["expr"]
                if "counter" in expr
            )
        return counts

    def rx_bytes(self, host: str) -> int:
        """Bytes `host` received on its eth0 so far (the kernel's interface counter)."""
        stats = json.loads(_run("ip", "-j", "-s", "-n", self.ns[host], "link", "show", "dev", IFACE))
        return int(stats[0]["stats64"]["rx"]["bytes"])

    def wait_received(
        self, host: str, min_bytes: int, procs: Sequence[subprocess.Popen], timeout_s: float = 120
    ) -> None:
        """Wait until `host` received `min_bytes` on the wire: how far a run is, to act mid-run
        (the recorder's partial file grows only per 1 MiB chunk, too coarse for that). Fails if any
        of `procs` ends first."""
        wait_until(
            lambda: self.rx_bytes(host) >= min_bytes,
            f"{host} received {min_bytes} bytes",
            procs=procs,
            timeout_s=timeout_s,
            poll_s=POLL_S,
        )

    def relay(self, host: str, listen_port: int, target: str, delay_s: float) -> subprocess.Popen:
        """Start tests/relay.py in `host`'s namespace: it accepts TCP on the host's address at
        `listen_port` and forwards to `target` (`HOST:PORT`), every chunk `delay_s` late in both
        directions, order kept. Returns once it listens; killed when the lab closes."""
        listen = f"{self.addresses[host]}:{listen_port}"
        proc = self.spawn(
            host,
            sys.executable,
            str(TESTS / "relay.py"),
            listen,
            target,
            repr(delay_s),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        assert proc.stdout is not None
        seen = b""
        deadline = time.monotonic() + READY_S
        while b"\n" not in seen:
            left = deadline - time.monotonic()
            assert left > 0, f"relay on {listen} not listening after {READY_S:g} s: {seen!r}"
            ready, _, _ = select.select([proc.stdout], [], [], left)
            if ready:
                chunk = os.read(proc.stdout.fileno(), 4096)
                assert chunk, f"relay on {listen} exited ({proc.wait()}) before listening: {seen!r}"
                seen += chunk
        assert seen.startswith(b"listening "), f"relay on {listen}: {seen!r}"
        return proc


def lab_certs(folder: Path) -> Path:
    """A CA and certificates for the lab's hosts (each named by its address) and the monitor."""
    issue(folder, {host: [address] for host, address in ADDRESSES.items()}, monitor=True, label="rover lab")
    return folder


def security_block(certs: Path, *, monitor: bool = True) -> str:
    """The `security:` section naming the certificates `lab_certs` wrote (the lab's hosts, and the
    monitor unless told otherwise)."""
    entries = "".join(f'    {h}: {{cert: "{certs}/{h}.pem", key: "{certs}/{h}.key"}}\n' for h in ADDRESSES)
    identity = f'  monitor: {{cert: "{certs}/monitor.pem", key: "{certs}/monitor.key"}}\n' if monitor else ""
    return f'security:\n  ca: "{certs}/ca.pem"\n  hosts:\n{entries}{identity}'


def pipeline_file(tmp_path: Path, *, certs: Path | None = None, **host_keys: object) -> Path:
    """rover/pipeline.yaml with its hosts on the lab's addresses (the NUC listens on 10.77.0.1,
    the others connect to it) and `host_keys` added to every host; with `certs` (from
    `lab_certs`), under mutual TLS: tls/ endpoints and a security: section."""
    text = (ROOT / "rover" / "pipeline.yaml").read_text()
    extra = "".join(f", {key}: {value}" for key, value in host_keys.items())
    nuc = f"{'tls' if certs else 'tcp'}/{ADDRESSES['nuc']}:${{port}}"
    hosts = (
        "hosts:\n"
        f'  nuc:    {{listen: ["{nuc}"]{extra}}}\n'
        f'  base:   {{connect: ["{nuc}"]{extra}}}\n'
        f'  laptop: {{connect: ["{nuc}"]{extra}}}\n'
    )
    if certs:
        hosts += security_block(certs)
    lab_text, count = re.subn(r"^hosts:\n(?:[ ]+.*\n)+", hosts, text, count=1, flags=re.M)
    assert count == 1, "rover/pipeline.yaml has no `hosts:` block of indented lines to replace"
    path = tmp_path / "pipeline.yaml"
    path.write_text(lab_text)
    return path
