"""Hosts under `security:` on a real network, attacked the way an intruder would: three network
namespaces (tests/netns.py), mutual TLS, the access control generated from the wiring, and
Zenoh clients with no certificate, another CA's, or a real host's or the monitor's certificate
(tests/tls_probe.py). The byte-identical run under TLS is in tests/test_hosts.py.

Needs root, `ip` and `nft`: without them these tests fail loudly (ROVER_SKIP_NETNS=1 skips them).
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import write_imu_dataset
from netns import ADDRESSES, TESTS, Lab, lab_certs, require_root, rover_env, security_block

from rover.cli.registry import BUILTINS
from rover.pipeline.validation import load_and_check
from rover.security.certs import issue

pytestmark = pytest.mark.netns  # builds network namespaces (tests/netns.py)

PORT = 7447
NUC = f"tls/{ADDRESSES['nuc']}:{PORT}"
WAIT_TIMEOUT_S = 8
"""How long the hosts of the forgery test wait for base before they give up."""
RUN_S = 120.0


def toy_pipeline(folder: Path, certs: Path, wait_timeout_s: float = 120) -> Path:
    """The NUC's `csi` stands for raw CSI (a live source only the laptop reads), base replays IMU
    and odometry for the laptop; base's operators read nothing."""
    text = f"""\
name: secure
vars: {{dataset: "", output: out}}
hosts:
  nuc:    {{listen: ["{NUC}"], wait_timeout_s: {wait_timeout_s}}}
  base:   {{connect: ["{NUC}"], wait_timeout_s: {wait_timeout_s}}}
  laptop: {{connect: ["{NUC}"], wait_timeout_s: {wait_timeout_s}}}
{security_block(certs)}operators:
  csi:     {{uses: toyops.Ticker, host: nuc, params: {{rate_hz: 50}}}}
  replay:  {{uses: dataset_replay, host: base, params: {{path: "${{dataset}}", speed: 1}}}}
  heading: {{uses: toyops.Heading, host: laptop, inputs: {{imu: replay/imu, odom: replay/odom}}}}
  record:
    {{uses: recorder, host: laptop, inputs: {{pose: heading/pose, csi: csi/imu}}, params: {{out: "${{output}}"}}}}
"""
    path = folder / "secure.yaml"
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def root() -> None:
    require_root()


@pytest.fixture(scope="module")
def certs(root, tmp_path_factory) -> Path:
    return lab_certs(tmp_path_factory.mktemp("certs"))


@pytest.fixture(scope="module")
def dataset(root, tmp_path_factory) -> Path:
    """60 s of IMU at 200 Hz: long enough for every probe at speed 1."""
    return write_imu_dataset(tmp_path_factory.mktemp("data") / "toy.mcap", 12000)


@pytest.fixture
def lab(root):
    with Lab() as lab:
        yield lab


def start(lab: Lab, pipeline: Path, dataset: Path, out: Path, hosts: tuple[str, ...]) -> dict[str, subprocess.Popen]:
    return {
        h: lab.popen(h, "run", str(pipeline), "--host", h, "--dataset", str(dataset), "--output", str(out))
        for h in hosts
    }


def probe(lab: Lab, host: str, *args: str) -> dict:
    argv = lab.exec_argv(host, sys.executable, str(TESTS / "tls_probe.py"), *args)
    done = subprocess.run(argv, capture_output=True, text=True, timeout=RUN_S, env=rover_env())
    assert done.returncode == 0, f"tls_probe {' '.join(args)} exited {done.returncode}:\n{done.stderr}"
    return json.loads(done.stdout.strip().splitlines()[-1])


def stop(procs: dict[str, subprocess.Popen]) -> dict[str, tuple[int, str]]:
    """Ctrl-C every host still running; (status, stderr) of each."""
    for proc in procs.values():
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    results = {}
    for host, proc in procs.items():
        _out, err = proc.communicate(timeout=RUN_S)
        results[host] = (proc.returncode, err)
    return results


def test_intruders_read_and_write_only_what_the_wiring_gives_their_certificate(lab, tmp_path, certs, dataset):
    """Mid-run, from the laptop's namespace: a client with base's certificate receives none of the
    NUC's raw-CSI stand-in (which the laptop's witness receives at 50 Hz) and its message on that
    NUC-owned key reaches nobody, while its message on base's own key does (the rules are not
    simply closed); the monitor identity receives no data, cannot write, and gets every host's
    status. The run itself is unharmed (no tracebacks, stopped by Ctrl-C)."""
    procs = start(lab, toy_pipeline(tmp_path, certs), dataset, tmp_path / "out", ("laptop", "base", "nuc"))
    seen = probe(lab, "laptop", "data", "secure", NUC, str(certs))
    results = stop(procs)
    assert seen["witness_csi"] >= 100, seen
    assert seen["base_csi"] == 0, f"base's certificate read the NUC's raw data: {seen}"
    assert seen["witness_csi_forged"] == 0, f"base's certificate wrote on a NUC key: {seen}"
    assert seen["witness_replay_forged"] == 1, f"only base's forgery on its own key gets through: {seen}"
    assert seen["monitor_data"] == 0, f"the monitor read data: {seen}"
    assert seen["monitor_status_replies"] == 3, seen
    for host, (_rc, err) in results.items():
        assert "Traceback" not in err, f"{host}:\n{err}"


def test_without_a_certificate_of_the_ca_nobody_connects(lab, tmp_path, certs, dataset):
    """While the NUC listens (waiting for the others): no certificate, a certificate of another CA
    that names itself `base`, and plain TCP to the TLS port are all refused; base's real
    certificate connects (the refusals are not a dead port)."""
    rogue = issue(tmp_path / "rogue", {"base": [ADDRESSES["base"]]}, label="rogue")
    nuc = start(lab, toy_pipeline(tmp_path, certs), dataset, tmp_path / "out", ("nuc",))
    ca = str(certs / "ca.pem")
    good = probe(lab, "base", "reach", NUC, str(certs), "base")
    bare = probe(lab, "base", "connect", NUC, ca)
    other = probe(lab, "base", "connect", NUC, ca, str(rogue.identities["base"][0]), str(rogue.identities["base"][1]))
    plain = probe(lab, "base", "connect", NUC.replace("tls/", "tcp/"), ca)
    stop(nuc)
    assert good == {"connected": True}, good
    assert not bare["connected"] and not other["connected"] and not plain["connected"], (bare, other, plain)


def test_a_forged_presence_token_starts_nothing_and_the_monitor_sees_the_wait(lab, tmp_path, certs, dataset):
    """Base is down. Clients with the monitor's and the laptop's certificates declare base's
    `ready` token (right digest, a session id): the NUC and the laptop keep waiting for base and
    give up after wait_timeout_s (exit 2 naming base), as without the forgeries. Meanwhile the
    monitor identity runs `rover status --once`, which shows both hosts waiting for base."""
    pipeline = toy_pipeline(tmp_path, certs, WAIT_TIMEOUT_S)
    digest = load_and_check(pipeline, BUILTINS).digest()
    token = f"rover/secure/_hosts/base/{digest}/0123456789abcdef/ready"
    forgers = [
        lab.spawn(
            "base",
            sys.executable,
            str(TESTS / "tls_probe.py"),
            "forge",
            "secure",
            NUC,
            str(certs),
            name,
            token,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env=rover_env(),
        )
        for name in ("monitor", "laptop")
    ]
    procs = start(lab, pipeline, dataset, tmp_path / "out", ("nuc", "laptop"))
    for forger in forgers:
        assert forger.stdout is not None
        assert json.loads(forger.stdout.readline())["declared"] == token
    status = lab.popen("base", "status", str(pipeline), "--once", "--timeout", "5")
    status_out, status_err = status.communicate(timeout=RUN_S)
    results = {h: (p.wait(timeout=RUN_S), p.stderr.read()) for h, p in procs.items() if p.stderr}
    for forger in forgers:
        forger.communicate("", timeout=30)
    assert status.returncode == 0, status_err
    assert "nuc" in status_out and "laptop" in status_out, status_out
    assert "waiting for base" in status_out, status_out
    for host, (rc, err) in results.items():
        assert rc == 2, f"{host} exited {rc} (a forged token started the run?):\n{err}"
        error = [line for line in err.splitlines() if line.startswith("rover: error:")]
        assert len(error) == 1 and "base" in error[0], err
