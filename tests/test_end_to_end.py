"""The whole pipeline as users run it: the demo, outputs without ground truth, the sample recording."""

from __future__ import annotations

import csv
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
from conftest import read_bag, reference_data, run_rover

from rover.formats.bag import BagReader, BagWriter
from rover.geometry import wrap_angle
from rover.messages import deserialize


def test_the_demo_beats_the_papers_figures(tmp_path, simulated):
    dataset = simulated("paper", 1)
    cache = tmp_path / "cache"
    cache.mkdir()
    os.link(dataset, cache / "paper-seed1.mcap")
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


def strip_truth(source: Path, target: Path) -> None:
    """The same dataset without /groundtruth/* and without the truth metadata."""
    with BagReader(source) as reader:
        meta = {k: v for k, v in reader.metadata().items() if k not in ("rover.truth", "rover.simulation")}
        with BagWriter(target, metadata=meta) as bag:
            for message in reader.messages(log_time_order=True):
                if not message.topic.startswith("/groundtruth/"):
                    bag.write(message.topic, deserialize(message.data, message.schema), message.log_time_ns)


def test_ground_truth_never_reaches_the_estimate(tmp_path, simulated):
    dataset = simulated("paper", 2, "trajectory.laps=1")
    blind = tmp_path / "blind.mcap"
    strip_truth(dataset, blind)
    for name, path in (("with", dataset), ("without", blind)):
        out = tmp_path / name
        # The default window, given on the command line: the same results, and run.json records it.
        proc = run_rover("run", "--dataset", str(path), "--output", str(out), "--set", "slam.window=30", timeout=600)
        assert proc.returncode == 0, proc.stderr
        run = json.loads((out / "run.json").read_text())
        assert run["dataset"] == str(path.resolve()) and run["pipeline"].endswith("pipeline.yaml")
        assert run["command_line"] == {
            "vars": {"dataset": str(path), "output": str(out)},
            "params": {"slam.window": 30},
        }
    for name in ("trajectory.tum", "trajectory_live.tum", "tags.csv"):
        assert (tmp_path / "with" / name).read_bytes() == (tmp_path / "without" / name).read_bytes(), name
    assert (tmp_path / "with" / "metrics.json").exists()
    assert not (tmp_path / "without" / "metrics.json").exists()


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
    assert sorted(last) == [1, 2, 3] and all(observable and error < 0.5 for observable, error in last.values()), last
    assert metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"] < 0.393
