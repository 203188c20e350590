"""Shared test helpers: datasets written on the fly, free loopback ports, and the real CLI in a subprocess."""

from __future__ import annotations

import contextlib
import math
import os
import resource
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

# as the `rover` command does (cli/__init__.py): one OpenBLAS thread for the small matrices the
# operators work on, in this process and the CLI subprocesses it starts; before numpy loads
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from rover.formats.bag import BagReader, BagWriter, iter_messages  # noqa: E402
from rover.messages import deserialize, header, make  # noqa: E402

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
T0_NS = 1_700_000_000_000_000_000


def reference_data() -> Path:
    """The real captures in ../shared/data (or ROVER_TEST_DATA); tests that need them skip without them."""
    path = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data"))
    if not path.is_dir():
        pytest.skip(
            f"reference data not found at {path}: it is the shared/data folder beside this repository "
            "(set ROVER_TEST_DATA to point at it)"
        )
    return path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_imu_dataset(path: Path, n_imu: int, *, imu_hz: float = 200.0, odom_every: int = 10, seed: int = 7) -> Path:
    """A dataset with `n_imu` IMU samples and odometry every `odom_every` samples, from a seeded RNG."""
    rng = np.random.default_rng(seed)
    gyro_z = rng.normal(0.0, 0.3, n_imu)
    with BagWriter(path) as bag:
        for i in range(n_imu):
            stamp = T0_NS + int(i * 1e9 / imu_hz)
            imu = make(
                "sensor_msgs/msg/Imu",
                header=header(stamp, "imu_link"),
                angular_velocity=make("geometry_msgs/msg/Vector3", z=float(gyro_z[i])),
                linear_acceleration=make("geometry_msgs/msg/Vector3", z=9.81),
            )
            bag.write("/imu/data", imu, stamp)
            if odom_every and i % odom_every == 0:
                odom = make("nav_msgs/msg/Odometry", header=header(stamp, "odom"))
                odom.pose.pose.position.x = math.sin(i / 100.0)
                bag.write("/odom", odom, stamp)
    return path


def run_rover(
    *args: str,
    cwd: Path | None = None,
    timeout: float = 120,
    check: bool = False,
) -> subprocess.CompletedProcess:
    """The real `rover` command in a subprocess, with the tests' operators importable."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.run(
        [sys.executable, "-m", "rover.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"rover {' '.join(args)} exited {proc.returncode}:\n{proc.stderr}")
    return proc


def popen_rover(*args: str, cwd: Path | None = None, max_file_bytes: int | None = None) -> subprocess.Popen:
    """`rover ARGS` started in a subprocess; with `max_file_bytes`, writes past that size fail
    (EFBIG, as on a full disk)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))

    def limit() -> None:
        if max_file_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    return subprocess.Popen(
        [sys.executable, "-m", "rover.cli", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=limit,
    )


def wait_for_file(path: Path, proc: subprocess.Popen, min_bytes: int = 0, timeout_s: float = 300.0) -> None:
    """Poll until `path` exists with more than `min_bytes`; fail if the process ends first or time runs out."""
    deadline = time.monotonic() + timeout_s
    while True:
        with contextlib.suppress(FileNotFoundError):
            if path.stat().st_size >= min_bytes:
                return
        assert proc.poll() is None, f"rover ended ({proc.returncode}) before writing {path}: {proc.communicate()[1]}"
        assert time.monotonic() < deadline, f"no {path} of {min_bytes} bytes after {timeout_s} s"
        time.sleep(0.002)


def stop_while_writing(proc: subprocess.Popen, partial: Path, signum: int) -> tuple[int, str]:
    """Send `signum` once the command's `partial` output file exists; (status, stderr) once it ended."""
    wait_for_file(partial, proc)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert "Traceback" not in stderr, stderr
    return proc.returncode, stderr


def read_bag(path: Path) -> list[tuple[str, int, bytes]]:
    """(topic, log time, payload) of every message of an MCAP file, in file order."""
    return [(m.topic, m.log_time_ns, m.data) for m in iter_messages(path, log_time_order=False)]


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """Simulated datasets, made once per (scenario, seed, overrides) for the whole test session."""
    cache: dict[tuple, Path] = {}
    root = tmp_path_factory.mktemp("datasets")

    def get(scenario: str = "paper", seed: int = 1, *overrides: str) -> Path:
        key = (scenario, seed, overrides)
        if key not in cache:
            path = root / f"{scenario}-{seed}-{len(cache)}.mcap"
            sets = [a for o in overrides for a in ("--set", o)]
            run_rover(
                "-q",
                "simulate",
                "--scenario",
                scenario,
                "--seed",
                str(seed),
                *sets,
                "-o",
                str(path),
                check=True,
                timeout=300,
            )
            cache[key] = path
        return cache[key]

    return get


def strip_truth(source: Path, target: Path) -> None:
    """The same dataset without /groundtruth/* and without the truth metadata."""
    with BagReader(source) as reader:
        meta = {k: v for k, v in reader.metadata().items() if k not in ("rover.truth", "rover.simulation")}
        with BagWriter(target, metadata=meta) as bag:
            for message in reader.messages(log_time_order=True):
                if not message.topic.startswith("/groundtruth/"):
                    bag.write(message.topic, deserialize(message.data, message.schema), message.log_time_ns)


LAP = ("paper", 2, "trajectory.laps=1")
"""one lap of the paper's scenario, seed 2: the dataset of `lap_runs`"""


@dataclass
class LapRun:
    dataset: Path
    output: Path
    args: list[str]
    """what the command line added to `rover run --dataset D --output O`"""
    status: int
    stderr: str


@pytest.fixture(scope="session")
def lap_runs(tmp_path_factory, simulated) -> dict[str, LapRun]:
    """`rover run` of the default pipeline on one lap of `paper` (seed 2), side by side (one core each):
    "with" on the dataset, "without" on a copy without its ground truth and with the timings recorded.
    Shared by the end-to-end test on ground truth and the window model's test (its SLAM inputs)."""
    dataset = simulated(*LAP)
    root = tmp_path_factory.mktemp("lap-runs")
    blind = root / "blind.mcap"
    strip_truth(dataset, blind)
    inputs = {"with": dataset, "without": blind}
    window = ["--set", "slam.window=30"]  # the default, given on the command line: run.json records it
    args = {"with": window, "without": [*window, "--timing-topic", "/rover/timing"]}
    procs = {
        name: popen_rover("run", "--dataset", str(path), "--output", str(root / name), *args[name])
        for name, path in inputs.items()
    }
    runs = {}
    for name, proc in procs.items():
        _stdout, stderr = proc.communicate(timeout=600)
        runs[name] = LapRun(inputs[name], root / name, args[name], proc.returncode, stderr)
    return runs
