"""The live robot end to end without hardware: `pipelines/live.yaml` on three hosts (network
namespaces) for 30 s of real time, the NUC reading an emulated 3DM-GX4-45 on a pty and a CSI Tool
log that grows as `channel_hop` tunes the emulated NIC, the base an emulated Create 2 on a pty, the
laptop running the method; the NUC records the session with `rover record`, and the recording
replayed in one process gives the live run's trajectory and tags. The sensors play the first 30 s
of a simulated `paper` run (tests/live_feed.py) with tag 2 moved off channel 153, where tag 4's
third harmonic lands: a live sweep refuses that plan (`channel_sweep`), and 104 is the channel its
planner proposes instead."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import yaml
from conftest import ROOT, run_rover
from create2_device import Create2Device
from live_feed import CsiLogFeeder, Recorded, tune_command
from mip_device import MipDevice
from netns import ADDRESSES, Lab, require_root, wait_until

from rover.formats.bag import BagReader

LIVE_S = 30.0
"""real time the session runs once every sensor streams"""
IMU_DECIMATION = 5
"""500 Hz / 5: the 100 Hz of pipelines/live.yaml's `rate_hz`"""


def live_pipeline(tmp_path: Path, log: Path, tuned: Path) -> Path:
    """pipelines/live.yaml with the lab's addresses, the CSI log followed in place of the netlink
    socket, and the NIC 'retuned' through `tuned`; every operator and parameter of the method as shipped."""
    text = (ROOT / "pipelines" / "live.yaml").read_text()
    command = yaml.safe_dump(tune_command(tuned), default_style='"').strip()
    edits = {
        "nuc_address: 127.0.0.1": f"nuc_address: {ADDRESSES['nuc']}",
        "    uses: csi_netlink\n    host: nuc\n": (
            f'    uses: csi_file\n    host: nuc\n    params: {{path: "{log}", follow: true, poll_s: 0.005}}\n'
        ),
        "dwell_s: 0.05}\n  csi:": f"dwell_s: 0.05, command: {command}}}\n  csi:",
    }
    for old, new in edits.items():
        assert text.count(old) == 1, f"pipelines/live.yaml: {old!r} not found once"
        text = text.replace(old, new)
    path = tmp_path / "live.yaml"
    path.write_text(text)
    return path


def live_scenario(tmp_path: Path) -> Path:
    """The paper's scenario, one lap, tag 2 on the channel the sweep's planner proposes."""
    text = (ROOT / "datasets" / "scenarios" / "paper.yaml").read_text()
    old = "{id: 2, channel: 153,"
    assert text.count(old) == 1 and text.count("laps: 2") == 1, "datasets/scenarios/paper.yaml changed"
    path = tmp_path / "live-scenario.yaml"
    path.write_text(text.replace(old, "{id: 2, channel: 104,").replace("laps: 2", "laps: 1"))
    return path


def _finish(proc: subprocess.Popen, timeout_s: float = 60) -> tuple[int, str]:
    _out, err = proc.communicate(timeout=timeout_s)
    assert "Traceback" not in err, err
    return proc.returncode, err


def test_a_live_session_on_three_hosts_is_recorded_and_replays_to_the_same_trajectory(tmp_path, simulated):
    require_root()
    recorded = Recorded.read(simulated(str(live_scenario(tmp_path)), 1))
    setup = tmp_path / "setup.yaml"
    setup.write_text(recorded.setup_yaml)
    log, tuned, session = tmp_path / "csi.dat", tmp_path / "tuned", tmp_path / "session.mcap"
    pipeline = live_pipeline(tmp_path, log, tuned)
    t0 = time.time()

    def since_start() -> float:
        return time.time() - t0

    with (
        Lab() as lab,
        MipDevice(lambda _t: recorded.imu_device(since_start()), decimation=IMU_DECIMATION) as imu,
        Create2Device(lambda _t: recorded.wheel_angles(since_start())) as base,
        CsiLogFeeder(recorded, log, tuned, t0) as nic,
    ):
        sets = ["--set", f"setup={setup}", "--set", f"imu_port={imu.port}", "--set", f"base_port={base.path}"]
        hosts = {
            "nuc": lab.popen("nuc", "record", str(pipeline), "--host", "nuc", "-o", str(session), *sets),
            "base": lab.popen("base", "run", str(pipeline), "--host", "base", *sets),
            "laptop": lab.popen(
                "laptop", "run", str(pipeline), "--host", "laptop", "--output", str(tmp_path / "live"), *sets
            ),
        }
        procs = list(hosts.values())
        wait_until(lambda: bool(nic.records and imu.sent and base.sent), procs, "every sensor streams", timeout_s=60)
        streaming = time.monotonic()
        wait_until(lambda: time.monotonic() - streaming >= LIVE_S, procs, f"{LIVE_S:g} s of live data", LIVE_S + 30)
        for host in ("nuc", "base"):  # the sources' hosts: Ctrl-C on each, as the operator of the robot does
            hosts[host].send_signal(signal.SIGINT)
        ended = {host: _finish(proc) for host, proc in hosts.items()}
        sent = {"imu": len(imu.sent), "odom": len(base.good_frames()), "csi": nic.records}

    assert ended["nuc"][0] == 130 and ended["base"][0] == 130, ended
    assert ended["laptop"][0] == 0, ended["laptop"][1]
    live = tmp_path / "live"
    trajectory = (live / "trajectory.tum").read_text().splitlines()
    stamps = [float(line.split()[0]) for line in trajectory if not line.startswith("#")]
    assert stamps[-1] - stamps[0] > 0.8 * LIVE_S, (stamps[0], stamps[-1])
    assert len((live / "tags.csv").read_text().splitlines()) == 1 + 4  # a header and the paper's four tags

    with BagReader(session) as bag:
        summary = bag.summary()
        record = yaml.safe_load(bag.metadata()["rover.record"]["yaml"])
    assert summary is not None
    counts = {c.topic: c.count for c in summary.channels}
    assert record["late"] == {}, record
    assert record["messages"] == counts
    # every sample the devices sent while the NUC was running, less what they sent before it started reading
    assert 0.9 * sent["imu"] <= counts["/imu/data"] <= sent["imu"], (counts, sent)
    assert 0.9 * sent["odom"] <= counts["/odom"] <= sent["odom"], (counts, sent)
    assert 0.9 * sent["csi"] <= counts["/csi"] <= sent["csi"], (counts, sent)

    replay = tmp_path / "replay"
    run_rover("-q", "run", "--dataset", str(session), "--output", str(replay), check=True, timeout=300)
    assert (replay / "trajectory.tum").read_text().splitlines() == trajectory
    assert (replay / "tags.csv").read_text() == (live / "tags.csv").read_text()
