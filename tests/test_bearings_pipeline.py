"""pipelines/bearings.yaml end to end: Rover's map from another front end's bearings (a CSV) and the
robot's IMU and odometry, no CSI: here the bearings are those of conftest's lap run through CSI, as
a front end that knows the chains' phase jumps would give them. The lap's jumps are drawn once per
channel, so each tag's bursts share one jump combination: the one the SLAM chose most for the tag,
and each burst's candidate of it is the bearing."""

from __future__ import annotations

import json
import math
from collections import Counter

import numpy as np
import pytest
from helpers import ROOT, read_bag, run_rover

from rover.messages import deserialize


@pytest.mark.slow
def test_the_slam_runs_from_a_csv_of_bearings_and_localizes_what_the_csi_run_did(lap_runs, tmp_path):
    """Every tag the run through CSI localized is localized from the bearings alone; the robot and the
    tags stay within the run's figures' order (under 10 cm and 50 cm), at most 1% of the published
    estimates beyond 3 sigma (the integrity goal, issue 40), and the bearings file is what the SLAM
    received (one bearing a burst, none dropped)."""
    through_csi = lap_runs["with"]
    assert through_csi.status == 0, through_csi.stderr
    bursts = [
        deserialize(d, "rover_msgs/msg/Aoa")
        for t, _s, d in read_bag(through_csi.output / "results.mcap")
        if t == "/rover/bearings"
    ]
    chosen = [a for a in bursts if a.chosen >= 0]
    combination = {
        tag: Counter(int(a.candidate_jumps[a.chosen]) for a in chosen if a.tag_id == tag).most_common(1)[0][0]
        for tag in {a.tag_id for a in chosen}
    }
    rows = [
        (a, a.candidate_angles_rad[k], a.candidate_stds_rad[k])
        for a in bursts
        if a.tag_id in combination
        for k in np.flatnonzero(np.asarray(a.candidate_jumps) == combination[a.tag_id])[:1]
    ]
    assert {a.tag_id for a, _angle, _std in rows} == set(combination)
    csv = tmp_path / "bearings.csv"
    csv.write_text(
        "time_s,tag,angle_deg,std_deg\n"
        + "".join(
            f"{a.header.stamp.sec + a.header.stamp.nanosec * 1e-9:.9f},{a.tag_id},{math.degrees(angle):.9f},"
            f"{math.degrees(std):.9f}\n"
            for a, angle, std in rows
        )
    )
    from_bearings = tmp_path / "bearings"
    run = run_rover(
        "run", str(ROOT / "pipelines" / "bearings.yaml"), "--dataset", str(through_csi.dataset),
        "--set", f"bearings={csv}", "--output", str(from_bearings),
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    before = json.loads((through_csi.output / "metrics.json").read_text())
    after = json.loads((from_bearings / "metrics.json").read_text())
    localized = {t for t, e in before["tags"].items() if e["localized"]}
    assert localized and {t for t, e in after["tags"].items() if e["localized"]} >= localized
    assert after["robot"]["trajectory.tum"]["unaligned"]["mean_m"] < 0.10
    assert all(e["error_m"] < 0.5 for e in after["tags"].values() if e["localized"])
    assert all(p["beyond_3_sigma"] <= 0.01 for p in after["published"].values() if p.get("estimates"))
    received = json.loads((from_bearings / "run.json").read_text())["operators"]["slam"]["received"]["aoa"]
    assert received == len(rows)
