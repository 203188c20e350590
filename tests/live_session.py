"""A live session of `pipelines/live.yaml` without hardware, for tests/test_live.py and
bench/bench_live.py: three hosts in network namespaces (tests/netns.py), the NUC reading an emulated
3DM-GX4-45 on a pty and a CSI Tool log that grows as `channel_hop` tunes the emulated NIC, the base
an emulated Create 2 on a pty, the laptop running the method, for `seconds` of real time once every
sensor streams; the NUC records it with `rover record`. The sensors play a simulated run
(tests/live_feed.py). Ended as an operator ends one: Ctrl-C on the NUC and the base.

The scenario is the paper's, one lap, with tag 2 moved off channel 153, where tag 4's third
harmonic lands: a live sweep refuses that plan (`channel_sweep`), and 104 is the channel its
planner proposes instead.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import yaml
from create2_device import Create2Device
from helpers import wait_until
from live_feed import CsiLogFeeder, Recorded, tune_command
from mip_device import MipDevice
from netns import ADDRESSES, POLL_S, Lab, rover_env

ROOT = Path(__file__).resolve().parent.parent
IMU_DECIMATION = 5
"""500 Hz / 5: the 100 Hz of pipelines/live.yaml's `rate_hz`"""
START_TIMEOUT_S = 60.0
END_TIMEOUT_S = 60.0
LIVE_PORT = 7450
"""the NUC's port in pipelines/live.yaml"""
OBSERVED_KEYS = ("rover/live/aoa/aoa", "rover/live/slam/pose")
"""what `observe` watches: the AoAs computed on the NUC, the poses solved on the laptop"""
OBSERVER = """
import sys, time, zenoh
from rover.transport import codec
endpoint, out, *keys = sys.argv[1:]
config = zenoh.Config()
config.insert_json5("mode", '"client"')
config.insert_json5("connect/endpoints", '["' + endpoint + '"]')
config.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(config)
sink = open(out, "a", buffering=1)
def seen(sample):
    now = time.time_ns()
    raw = sample.attachment.to_bytes() if sample.attachment else None
    kind, stamp, _mark = codec.read_attachment(raw)
    if kind == codec.Kind.DATA:
        sink.write(f"{sample.key_expr} {now} {stamp}\\n")
subscribers = [session.declare_subscriber(key, seen) for key in keys]
print("ready", flush=True)
while True:
    time.sleep(1)
"""


def live_scenario(folder: Path) -> Path:
    """The paper's scenario, one lap, tag 2 on the channel the sweep's planner proposes."""
    text = (ROOT / "datasets" / "scenarios" / "paper.yaml").read_text()
    old = "{id: 2, channel: 153,"
    assert text.count(old) == 1 and text.count("laps: 2") == 1, "datasets/scenarios/paper.yaml changed"
    path = folder / "live-scenario.yaml"
    path.write_text(text.replace(old, "{id: 2, channel: 104,").replace("laps: 2", "laps: 1"))
    return path


def live_pipeline(folder: Path, log: Path, tuned: Path) -> Path:
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
    path = folder / "live.yaml"
    path.write_text(text)
    return path


@dataclass
class LiveSession:
    """What a session left: each host's exit status and stderr, what the emulated devices sent, the
    laptop's output folder and the NUC's recording."""

    ended: dict[str, tuple[int, str]]
    sent: dict[str, int]
    output: Path
    recording: Path
    pipeline: Path


def run_session(
    folder: Path, dataset: Path, seconds: float, during: Callable[[Lab, Path], None] | None = None
) -> LiveSession:
    """Play `dataset` live for `seconds` across three hosts; `during(lab, pipeline)`, if given, is
    called once every sensor streams (to start an observer)."""
    recorded = Recorded.read(dataset)
    setup = folder / "setup.yaml"
    setup.write_text(recorded.setup_yaml)
    log, tuned, recording, output = folder / "csi.dat", folder / "tuned", folder / "session.mcap", folder / "live"
    pipeline = live_pipeline(folder, log, tuned)
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
            "nuc": lab.popen("nuc", "record", str(pipeline), "--host", "nuc", "-o", str(recording), *sets),
            "base": lab.popen("base", "run", str(pipeline), "--host", "base", *sets),
            "laptop": lab.popen("laptop", "run", str(pipeline), "--host", "laptop", "--output", str(output), *sets),
        }
        procs = list(hosts.values())
        streaming = lambda: bool(nic.records and imu.sent and base.sent)  # noqa: E731
        wait_until(streaming, "every sensor streams", procs=procs, timeout_s=START_TIMEOUT_S, poll_s=POLL_S)
        if during is not None:
            during(lab, pipeline)
        started = time.monotonic()
        wait_until(
            lambda: time.monotonic() - started >= seconds,
            f"{seconds:g} s of live data",
            procs=procs,
            timeout_s=seconds + 30,
            poll_s=POLL_S,
        )
        for host in ("nuc", "base"):  # the sources' hosts: Ctrl-C on each, as the operator of the robot does
            hosts[host].send_signal(signal.SIGINT)
        ended = {host: _finish(proc) for host, proc in hosts.items()}
        sent = {"imu": len(imu.sent), "odom": len(base.good_frames()), "csi": nic.records}
    return LiveSession(ended, sent, output, recording, pipeline)


def _finish(proc: subprocess.Popen) -> tuple[int, str]:
    _out, err = proc.communicate(timeout=END_TIMEOUT_S)
    return proc.returncode, err


def observe(lab: Lab, arrivals: Path, keys: tuple[str, ...] = OBSERVED_KEYS) -> None:
    """An observer on the laptop's machine writing each data sample of `keys` to `arrivals` as it
    arrives: "KEY ARRIVAL_NS STAMP_NS" (one kernel clock for all namespaces); returns once it listens."""
    endpoint = f"tcp/{ADDRESSES['nuc']}:{LIVE_PORT}"
    proc = lab.spawn(
        "laptop",
        sys.executable,
        "-c",
        OBSERVER,
        endpoint,
        str(arrivals),
        *keys,
        env=rover_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"


def read_arrivals(arrivals: Path) -> list[tuple[str, int, int]]:
    """What `observe` wrote: (key, arrival ns, stamp ns) in arrival order."""
    rows = (line.split() for line in arrivals.read_text().splitlines())
    return [(key, int(arrived), int(stamp)) for key, arrived, stamp in rows]
