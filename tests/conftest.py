"""Fixtures only: datasets simulated once per session and the one-lap runs several tests share.
Helpers are in tests/helpers (`from helpers import ...`)."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

# as the `rover` command does (cli/__init__.py): one OpenBLAS thread for the small matrices the
# operators work on, in this process and the CLI subprocesses it starts; before numpy loads
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# runs in one process unless a test asks for workers (tests/test_workers.py): what the tests patch
# in this process, and the signals they send, then reach every operator
os.environ.setdefault("ROVER_WORKERS", "1")

import pytest  # noqa: E402
from helpers import LAP, popen_rover, run_rover, strip_truth  # noqa: E402
from helpers.processes import children  # noqa: E402
from helpers.shared import once  # noqa: E402

LEFTOVER_GRACE_S = 5.0
"""how long a child may still take to exit once the last test is done"""


@pytest.fixture(scope="session", autouse=True)
def no_child_outlives_the_suite():
    """Every process a test started is stopped by that test: one still running after the last test
    is killed and fails the session, naming its command line."""
    yield
    deadline = time.monotonic() + LEFTOVER_GRACE_S
    while (left := children()) and time.monotonic() < deadline:
        time.sleep(0.05)
    for pid in left:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    if left:
        pytest.fail("processes left running by the tests (killed): " + "; ".join(f"{p}: {c}" for p, c in left.items()))


@pytest.fixture(scope="session")
def simulated(tmp_path_factory):
    """Simulated datasets, made once per (scenario, seed, overrides) for the whole test run, shared
    by the xdist workers."""

    def get(scenario: str = "paper", seed: int = 1, *overrides: str) -> Path:
        name = "-".join([scenario, str(seed), *overrides]).replace("/", "_")

        def make(folder: Path) -> dict:
            sets = [a for o in overrides for a in ("--set", o)]
            path = folder / "dataset.mcap"
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
            return {}

        folder, _ = once(tmp_path_factory, f"simulated-{name}", make)
        return folder / "dataset.mcap"

    return get


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
    window = ["--set", "slam.window=30"]  # the default, given on the command line: run.json records it
    args = {"with": window, "without": [*window, "--timing-topic", "/rover/timing"]}

    def make(root: Path) -> dict:
        blind = root / "blind.mcap"
        strip_truth(dataset, blind)
        inputs = {"with": dataset, "without": blind}
        procs = {
            name: popen_rover("run", "--dataset", str(path), "--output", str(root / name), *args[name])
            for name, path in inputs.items()
        }
        finished = {}
        for name, proc in procs.items():
            _stdout, stderr = proc.communicate(timeout=600)
            finished[name] = {"dataset": str(inputs[name]), "status": proc.returncode, "stderr": stderr}
        return finished

    root, finished = once(tmp_path_factory, "lap-runs", make)
    runs = {
        name: LapRun(Path(run["dataset"]), root / name, args[name], run["status"], run["stderr"])
        for name, run in finished.items()
    }
    return runs
