"""The whole pipeline as users run it: the demo, outputs without ground truth, the sample recording."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import popen_rover, read_bag, reference_data, run_rover, strip_truth, wait_for_file

from rover.cli.demo import simulator_version
from rover.drivers.run_outputs import TAG_COLUMNS
from rover.formats.bag import BagWriter, read_metadata
from rover.formats.output_folder import STAGING_PREFIX
from rover.geometry import wrap_angle
from rover.messages import deserialize

pytestmark = pytest.mark.slow  # every test here runs the whole pipeline


def test_the_demo_beats_the_papers_figures(tmp_path, simulated):
    dataset = simulated("paper", 1)
    cache = tmp_path / "cache"
    cache.mkdir()
    os.link(dataset, cache / f"paper-seed1-{simulator_version()}.mcap")
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "rover.cli.demo", "--output", str(out)],
        capture_output=True,
        text=True,
        env=dict(os.environ, ROVER_CACHE=str(cache)),
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert "paper (Zhang et al.)" in proc.stdout and "trajectory.tum" in proc.stdout
    for name in (
        "results.mcap",
        "trajectory.tum",
        "trajectory_live.tum",
        "tags.csv",
        "metrics.json",
        "trajectory.png",
        "robot_error.png",
        "tag_error.png",
        "aoa_cdf.png",
    ):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"] <= 0.393
    assert metrics["los_tags_mean_m"] <= 0.746
    assert metrics["aoa"]["los"]["median_deg"] <= 9.3
    topics = {t for t, _s, _d in read_bag(out / "results.mcap")}
    assert {"/rover/pose", "/rover/path", "/rover/tags", "/rover/aoa", "/rover/slam/diagnostics"} <= topics


PAPER_ROBOT_M, PAPER_LOS_TAGS_M = 0.393, 0.746
"""the paper's figures with these very sensors (AoA + IMU)"""


def test_aoa_and_imu_alone_beat_the_papers_figures(simulated, tmp_path):
    """The paper's own sensors: no wheel odometry and no wheeled-robot assumption, on one lap of
    seeds 1 and 2 through the real pipeline, side by side (the full table: bench/bench_slam.py)."""
    flags = ["--set", "slam.wheel=false", "--set", "slam.nonholonomic=false"]
    procs = {
        seed: popen_rover(
            "run",
            "--dataset",
            str(simulated("paper", seed, "trajectory.laps=1")),
            "--output",
            str(tmp_path / str(seed)),
            *flags,
        )
        for seed in (1, 2)
    }
    for seed, proc in procs.items():
        _out, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err
        assert "no wheel odometry arrived" not in err, "wheel=false says nothing of a missing wheel"
        metrics = json.loads((tmp_path / str(seed) / "metrics.json").read_text())
        robot = metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"]
        assert robot <= PAPER_ROBOT_M and metrics["los_tags_mean_m"] <= PAPER_LOS_TAGS_M, (seed, robot, metrics)


def test_ground_truth_never_reaches_the_estimate(lap_runs):
    """The same lap with and without its ground truth: the same estimates to the byte; the default
    window given on the command line gives the same results, and run.json records it."""
    for run in lap_runs.values():
        assert run.status == 0, run.stderr
        recorded = {t for t, _s, _d in read_bag(run.output / "results.mcap")}
        timing = "--timing-topic" in run.args
        assert ("/rover/timing" in recorded) == timing
        record = json.loads((run.output / "run.json").read_text())
        assert record["status"] == "complete" and record["reason"] == ""
        assert record["dataset"] == str(run.dataset.resolve()) and record["pipeline"].endswith("pipeline.yaml")
        assert record["command_line"] == {
            "vars": {
                "dataset": str(run.dataset),
                "output": str(run.output),
                **({"timing_topic": "/rover/timing"} if timing else {}),
            },
            "params": {"slam.window": 30},
        }
        assert sorted(record["profile"]) == sorted(record["operators"])
        assert all(record["profile"][op]["handler_s"] > 0 for op in ("aoa", "slam", "preint")), record
    seen, blind = lap_runs["with"].output, lap_runs["without"].output
    for name in ("trajectory.tum", "trajectory_live.tum", "tags.csv"):
        assert (seen / name).read_bytes() == (blind / name).read_bytes(), name
    assert (seen / "metrics.json").exists()
    assert not (blind / "metrics.json").exists()


def test_eval_against_another_runs_truth_warns_and_says_so(lap_runs, tmp_path):
    """`rover eval RUN --truth OTHER.tum` with a truth that is not the ground truth of the run's
    dataset (here the run's own estimate moved 1 m): exit 0, a warning naming both, and metrics.json
    (`--json`) noting it; with the run's own truth, no note. Its figures go beside the run's own
    (`eval-other/`), which stay as they were."""
    run = lap_runs["with"].output
    rows = np.loadtxt(run / "trajectory.tum")
    rows[:, 1] += 1.0
    other = tmp_path / "other.tum"
    np.savetxt(other, rows, fmt="%.9f")
    proc = run_rover("eval", str(run), "--truth", str(other), "--json")
    assert proc.returncode == 0, proc.stderr
    note = f"the truth {other} is not the ground truth of the run's dataset {lap_runs['with'].dataset.resolve()}"
    assert f"rover: WARNING: {run}: {note}" in proc.stderr.splitlines(), proc.stderr
    assert note in json.loads(proc.stdout)["notes"]
    own = run_rover("eval", str(run), "--json", check=True)
    assert "notes" not in json.loads(own.stdout), own.stdout
    copy = tmp_path / "run"  # the shared run's folder stays as it is
    shutil.copytree(run, copy)
    pngs = {p.name: p.read_bytes() for p in copy.glob("*.png")}
    proc = run_rover("eval", str(copy), "--truth", str(other), "--figures")
    assert proc.returncode == 0 and f"in {copy / 'eval-other'}" in proc.stderr, proc.stderr
    assert {p.name: p.read_bytes() for p in copy.glob("*.png")} == pngs, "the run's own figures replaced"
    drawn = {p.name for p in (copy / "eval-other").iterdir()}  # no tag truth in a TUM: no AoA figure
    assert {"trajectory.png", "robot_error.png", "tag_error.png"} <= drawn <= set(pngs)


def test_an_empty_dataset_is_a_clean_run_with_empty_outputs(tmp_path, simulated):
    """A dataset with the rig description and not one message: status 0, one warning, every
    estimate file present and empty, run.json counting nothing."""
    empty = tmp_path / "empty.mcap"
    with BagWriter(empty, metadata={"rover.setup": read_metadata(simulated("paper", 1))["rover.setup"]}):
        pass
    out = tmp_path / "out"
    proc = run_rover("run", "--dataset", str(empty), "--output", str(out), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert (
        f"rover: WARNING: {empty}: no messages on /csi, /imu/data, /odom, /csi/capture: the run's outputs are empty"
        in proc.stderr
    )
    assert "Traceback" not in proc.stderr
    assert (out / "trajectory.tum").read_text() == (out / "trajectory_live.tum").read_text() == ""
    assert (out / "tags.csv").read_text().splitlines() == [",".join(TAG_COLUMNS)]
    assert read_bag(out / "results.mcap") == []
    run = json.loads((out / "run.json").read_text())
    assert (run["status"], run["reason"], run["received"], run["dropped"]) == ("complete", "", 0, 0)


FIRST_CHUNK_BYTES = 100_000
"""The recorder's file passes this size once its first chunk is flushed (a fifth of the run here):
by then epochs have left the SLAM window, so there are final poses and metrics to write."""


def test_an_interrupted_run_finishes_its_estimates_within_2_s(tmp_path, simulated):
    """Stopped while the estimate is flowing, on a dataset with ground truth: the process is gone
    within 2 s of the signal with the estimates and metrics written; the figures, which do not
    fit in the budget, are skipped with a note and `rover eval --figures` draws them later."""
    sig = signal.SIGINT  # SIGTERM takes the same path (tests/test_runtime.py stops a live run with each)
    out = tmp_path / "out"
    proc = popen_rover("run", "--dataset", str(simulated("paper", 1)), "--output", str(out))
    wait_for_file(out / f"{STAGING_PREFIX}{proc.pid}" / ".results.mcap.partial", proc, FIRST_CHUNK_BYTES)
    sent = time.monotonic()
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=30)
    took = time.monotonic() - sent
    assert proc.returncode == 128 + sig, err
    assert took < 2.0, f"took {took:.2f} s to stop"
    assert "Traceback" not in err
    # what was still queued at the stop is dropped by design: at most one line says so (-v lists it)
    assert not [line for line in err.splitlines() if "DROPPED" in line], err
    assert len([line for line in err.splitlines() if line.startswith("rover: WARNING: stopped: ")]) <= 1, err
    run = json.loads((out / "run.json").read_text())
    assert (run["status"], run["reason"]) == ("interrupted", f"stopped by {signal.Signals(sig).name}")
    files = {p.name for p in out.iterdir()}
    assert {"trajectory.tum", "trajectory_live.tum", "tags.csv", "timing.json", "results.mcap"} <= files
    assert not [name for name in files if name.startswith(".")], files
    assert len((out / "trajectory.tum").read_text().splitlines()) > 0
    hint = f"run `rover eval {out} --figures`"
    if "metrics.json" in files:  # the metrics fit in what was left of the budget, the figures never do
        assert [n for n in run["notes"] if "before their tag was found" not in n] == [
            f"figures skipped after the interrupt: {hint}"
        ]
    else:
        assert [n for n in run["notes"] if "before their tag was found" not in n] == [
            f"metrics and figures skipped after the interrupt: {hint}"
        ]
    later = run_rover("eval", str(out), "--figures")
    assert later.returncode == 0, later.stderr
    assert {"trajectory.png", "robot_error.png", "tag_error.png", "aoa_cdf.png"} <= {p.name for p in out.iterdir()}


def corrupt_middle_chunk(source: Path, target: Path) -> None:
    """A copy of `source` with the compressed bytes of its middle chunk scrambled: the summary
    still reads, so a run starts, and fails when the replay reaches that chunk."""
    from mcap.reader import make_reader

    data = bytearray(source.read_bytes())
    with source.open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    middle = chunks[len(chunks) // 2]
    start = middle.chunk_start_offset + middle.chunk_length // 2
    data[start : start + 64] = bytes(64)
    target.write_bytes(bytes(data))


@pytest.mark.parametrize("truth", [True, False], ids=["truth read at the start", "replay in mid-run"])
def test_a_run_failing_on_a_corrupt_chunk_keeps_the_earlier_runs_results(tmp_path, simulated, truth):
    """Status 2 and one line naming the dataset, whether the corrupt chunk is met while reading
    the ground truth before the run or by the replay in mid-run; the folder keeps the earlier run's
    results as they were, and failed-run.json beside them says this run failed and why."""
    dataset = simulated("paper", 1)
    if not truth:
        strip_truth(dataset, tmp_path / "blind.mcap")
        dataset = tmp_path / "blind.mcap"
    corrupt = tmp_path / "corrupt.mcap"
    corrupt_middle_chunk(dataset, corrupt)
    out = tmp_path / "out"
    out.mkdir()
    earlier = {name: f"from an earlier run: {name}" for name in ("trajectory.tum", "tags.csv", "metrics.json")}
    earlier["results.mcap"] = "an earlier run's recording"
    files = '["metrics.json", "results.mcap", "tags.csv", "trajectory.tum"]'  # run.json lists a run's files
    earlier["run.json"] = f'{{"status": "complete", "dataset": "/earlier/run.mcap", "files": {files}}}'
    for name, text in earlier.items():
        (out / name).write_text(text)
    proc = run_rover("run", "--dataset", str(corrupt), "--output", str(out), timeout=600)
    assert proc.returncode == 2, proc.stderr
    # a replay longer than 10 s (a loaded machine) also prints its progress lines: not errors
    errors = [line for line in proc.stderr.splitlines() if "WARNING" not in line and not line.startswith("progress: ")]
    assert len(errors) == 1 and errors[0].startswith(f"rover: error: {corrupt}: "), proc.stderr
    assert "Traceback" not in proc.stderr
    assert sorted(p.name for p in out.iterdir()) == sorted([*earlier, "failed-run.json"])
    assert {name: (out / name).read_text() for name in earlier} == earlier
    run = json.loads((out / "failed-run.json").read_text())
    assert run["status"] == "failed" and run["reason"] == errors[0].removeprefix("rover: error: ")
    assert run["dataset"] == str(corrupt.resolve())


def test_sample_recording_convert_run_eval(tmp_path):
    """The independent generator's recording, delivered as users deliver data."""
    sample = reference_data() / "recording_sample"
    dataset = tmp_path / "sample.mcap"
    run_rover(
        "convert",
        str(sample),
        "-o",
        str(dataset),
        "--truth",
        str(sample / "truth_robot.tum"),
        "--tags",
        str(sample / "truth_tags.csv"),
        check=True,
        timeout=300,
    )
    run_rover("run", "--dataset", str(dataset), "--output", str(tmp_path / "run"), check=True, timeout=600)
    metrics = json.loads(run_rover("eval", str(tmp_path / "run"), "--json", check=True).stdout)
    truth = {
        int(r["stamp_ns"]): math.radians(float(r["aoa_deg"])) for r in csv.DictReader((sample / "truth_csi.csv").open())
    }
    stamps = np.array(sorted(truth))
    errors = []
    for topic, _log, data in read_bag(tmp_path / "run" / "results.mcap"):
        if topic == "/rover/aoa":
            aoa = deserialize(data, "rover_msgs/msg/Aoa")
            s = aoa.header.stamp.sec * 1_000_000_000 + aoa.header.stamp.nanosec
            k = int(np.argmin(np.abs(stamps - s)))
            errors.append(abs(wrap_angle(aoa.angle_rad - truth[int(stamps[k])])))
    assert math.degrees(float(np.median(errors))) <= 10.0
    assert (
        metrics["aoa"]["all"]["within_3_std"] >= 0.95 and 0.3 <= metrics["aoa"]["all"]["error_over_std_median"] <= 1.2
    )
    truth_tags = {
        int(r["id"]): np.array([float(r["x"]), float(r["y"])])
        for r in csv.DictReader((sample / "truth_tags.csv").open())
    }
    last = {}
    for topic, _log, data in read_bag(tmp_path / "run" / "results.mcap"):
        if topic == "/rover/tags":
            for tag in deserialize(data, "rover_msgs/msg/TagArray").tags:
                error = np.array([tag.position.x, tag.position.y]) - truth_tags[tag.id]
                last[tag.id] = (tag.observable, float(np.linalg.norm(error)))
                if tag.observable:
                    mahalanobis = math.sqrt(error @ np.linalg.solve(np.reshape(tag.covariance_xy, (2, 2)), error))
                    assert mahalanobis <= 3.5, f"tag {tag.id} reported {mahalanobis:.1f} sigma from the truth"
    # Tag 3 sits ahead on the straight line, so its bearings barely change: with the card's chain phase
    # jumps possible, places along its rays and a jumped combination's ghost are alike, and it may stay
    # unlocalized (issue 14: never a silent guess); every tag reported localized is right.
    assert sorted(last) == [1, 2, 3] and sum(observable for observable, _ in last.values()) >= 2, last
    assert all(error < 0.5 for observable, error in last.values() if observable), last
    assert metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"] < 0.393


PAIR_ALONG = (
    "receiver.array=positions",
    "receiver.antenna_positions_m=[[0, 0], [0.0258, 0]]",
    "receiver.phase_offsets_rad=[0, 0.9]",
)
"""a 2-antenna card, its axis along the robot's heading (the chains off by pi all run, as `paper` has them)"""


def test_a_two_antenna_card_localizes_every_los_tag_from_its_angles_and_their_mirror_images(simulated, tmp_path):
    """One lap of `paper` (at 0.6 m/s: half the data) with two antennas: each burst's angle and its
    mirror image are candidates (with each jump combination's), the robot's turns tell them apart,
    every LOS tag is localized, and no published estimate is beyond 3 sigma (the figures against
    three antennas: bench/bench_antennas.py)."""
    out = tmp_path / "pair"
    result = run_rover(
        "run",
        "--dataset",
        str(simulated("paper", 1, "trajectory.laps=1", "trajectory.speed_m_s=0.6", *PAIR_ALONG)),
        "--output",
        str(out),
    )
    assert result.returncode == 0, result.stderr
    aoa = [deserialize(d, "rover_msgs/msg/Aoa") for t, _s, d in read_bag(out / "results.mcap") if t == "/rover/aoa"]
    assert np.median([len(a.candidate_angles_rad) for a in aoa]) == 4
    metrics = json.loads((out / "metrics.json").read_text())
    los = [tag for tag in metrics["tags"].values() if not tag["nlos"]]
    assert all(tag["localized"] for tag in los), metrics["tags"]
    assert metrics["published"]["los"]["beyond_3_sigma"] == 0.0 and metrics["published"]["los"]["estimates"] > 0
    assert metrics["published"]["nlos"]["estimates"] == 0 or metrics["published"]["nlos"]["beyond_3_sigma"] == 0.0
