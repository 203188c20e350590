"""`run_outputs`: the run's files appear whole or not at all, a new run replaces an old one's,
and run.json says how every run ended."""

from __future__ import annotations

import csv
import json
import time

import numpy as np
import pytest
from helpers import T0_NS

from rover.cli.summary import run_summary
from rover.drivers.run_outputs import RUN_FILES, RunOutputs, RunOutputsParams
from rover.errors import OutputFailed
from rover.formats.run_dir import FAILED_RUN_FILE
from rover.messages import header, make
from rover.operator import COMPLETE, OperatorCounts, RunOutcome
from rover.testing import run_operator


def pose(i: int):
    return make("geometry_msgs/msg/PoseStamped", header=header(T0_NS + i * 10**8, "world"))


def timing(i: int, wall_s: float):
    return make("rover_msgs/msg/Timing", header=header(T0_NS + i * 10**8, "world"), stage="slam.update", wall_s=wall_s)


def outputs(tmp_path) -> RunOutputs:
    op = RunOutputs(RunOutputsParams(out=str(tmp_path / "out")))
    op.start()
    run_operator(
        op,
        {
            "trajectory": [pose(i) for i in range(3)],
            "pose": [pose(i) for i in range(4)],
            "tags": [make("rover_msgs/msg/TagArray", header=header(T0_NS, "world"))],
            "timing": [timing(i, w) for i, w in enumerate((0.01, 0.03, 0.02))],
        },
    )
    return op


def test_a_complete_run_writes_its_files_and_run_json_counts_what_was_processed(tmp_path):
    op = outputs(tmp_path)
    op.close()
    counts = {"slam": OperatorCounts({"aoa": 40}, {"pose": 4}, {"AoAs without an IMU epoch": 2})}
    op.report(RunOutcome("complete", "", counts))
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["trajectory.tum", "trajectory_live.tum", "tags.csv", "timing.json", "run.json"]
    )
    assert len((out / "trajectory.tum").read_text().splitlines()) == 3
    summary = json.loads((out / "timing.json").read_text())["slam.update"]
    assert summary["count"] == 3 and summary["median_s"] == pytest.approx(0.02) and summary["max_s"] == 0.03
    run = json.loads((out / "run.json").read_text())
    assert (run["status"], run["reason"], run["received"], run["dropped"]) == ("complete", "", 40, 2)
    assert run["operators"]["slam"]["dropped"] == {"AoAs without an IMU epoch": 2}


def test_a_run_replaces_what_an_earlier_run_left_only_once_it_has_its_results(tmp_path):
    """Nothing goes at the start; at the end this run's files replace the earlier run's, those it did not
    write (metrics, figures of a run with truth) go with them, and the user's own file stays."""
    out = tmp_path / "out"
    out.mkdir()
    for name in RUN_FILES:
        (out / name).write_text("from the earlier run")
    (out / FAILED_RUN_FILE).write_text("{}")
    (out / "notes.txt").write_text("the user's own file")
    op = outputs(tmp_path)
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == sorted(
        [*RUN_FILES, FAILED_RUN_FILE, "notes.txt"]
    )
    op.close()
    op.report(COMPLETE)
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["notes.txt", "run.json", "tags.csv", "timing.json", "trajectory.tum", "trajectory_live.tum"]
    )
    assert (out / "trajectory.tum").read_text() != "from the earlier run"


def test_a_failed_run_keeps_the_earlier_results_and_says_why_beside_them(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for name in RUN_FILES:
        (out / name).write_text("from the earlier run")
    op = outputs(tmp_path)
    op.close(RunOutcome("failed", "operator 'slam' failed: boom"))
    op.report(RunOutcome("failed", "operator 'slam' failed: boom"))
    assert sorted(p.name for p in out.iterdir()) == sorted([*RUN_FILES, FAILED_RUN_FILE])
    assert all((out / name).read_text() == "from the earlier run" for name in RUN_FILES)
    failed = json.loads((out / FAILED_RUN_FILE).read_text())
    assert failed["status"] == "failed" and failed["reason"] == "operator 'slam' failed: boom" and failed["files"] == []


def test_files_that_cannot_be_put_in_place_fail_the_run_and_none_goes_in(tmp_path):
    op = outputs(tmp_path)
    out = tmp_path / "out"
    (out / "tags.csv").mkdir(parents=True)  # a folder in the way of the third file
    (out / "tags.csv" / "x").write_text("")
    op.close()
    with pytest.raises(OutputFailed, match=r"tags\.csv: cannot write: a folder is in the way"):
        op.report(COMPLETE)
    assert sorted(p.name for p in out.iterdir()) == [FAILED_RUN_FILE, "tags.csv"]  # the folder is the user's
    failed = json.loads((out / FAILED_RUN_FILE).read_text())
    assert failed["status"] == "failed" and "a folder is in the way" in failed["reason"]


@pytest.mark.slow
def test_an_interrupt_with_no_time_left_skips_the_metrics_with_a_note(tmp_path, simulated):
    op = RunOutputs(RunOutputsParams(out=str(tmp_path / "out"), dataset=str(simulated("paper", 1))))
    op.start()
    assert op.truth is not None, "the truth is read before the run, not in the time budget"
    run_operator(op, {"trajectory": [pose(0)], "pose": [pose(0)], "tags": []})
    op.close(RunOutcome("interrupted", "stopped by SIGINT", deadline=time.monotonic()))
    op.report(RunOutcome("interrupted", "stopped by SIGINT"))
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["status"] == "interrupted" and "metrics.json" not in run["files"]
    assert run["notes"] == [f"metrics and figures skipped after the interrupt: run `rover eval {op.out} --figures`"]


@pytest.mark.slow
def test_metrics_that_cannot_be_computed_leave_the_run_complete_with_a_note(tmp_path, simulated):
    """The estimate starts 1,000 s after the dataset's 180 s of truth ends (its stamps are made up
    here): no metrics.json, a note saying why, and the estimates stay."""
    op = RunOutputs(RunOutputsParams(out=str(tmp_path / "out"), dataset=str(simulated("paper", 1))))
    op.start()
    later = [pose(10_000 + i) for i in range(3)]
    run_operator(op, {"trajectory": later, "pose": later, "tags": []})
    op.close()
    op.report(RunOutcome())
    run = json.loads((tmp_path / "out" / "run.json").read_text())
    assert run["status"] == "complete" and "trajectory.tum" in run["files"] and "metrics.json" not in run["files"]
    assert len(run["notes"]) == 1 and run["notes"][0].startswith("no metrics: ")
    assert "do not overlap in time" in run["notes"][0]


def test_tags_csv_says_each_tags_latest_status_and_why_and_the_summary_repeats_it(tmp_path):
    """A tag's last TagStatus goes into tags.csv (its reason quoted: it has commas and quotes), and
    the summary `rover run` prints names each tag not localized with it."""

    def status(tag_id: int, state: int, reason: str):
        return make("rover_msgs/msg/TagStatus", header=header(T0_NS, "world"), id=tag_id, state=state, reason=reason)

    def tag(tag_id: int, observable: bool):
        return make("rover_msgs/msg/Tag", id=tag_id, observable=observable, covariance_xy=np.eye(2).ravel() * 0.01)

    ambiguous = 'the search\'s best place (1.00, 2.00) m is not clear: another "place" fits'
    tags = [tag(1, True), tag(2, False)]
    op = RunOutputs(RunOutputsParams(out=str(tmp_path / "out")))
    op.start()
    run_operator(
        op,
        {
            "trajectory": [pose(i) for i in range(3)],
            "pose": [pose(i) for i in range(3)],
            "tags": [make("rover_msgs/msg/TagArray", header=header(T0_NS, "world"), tags=tags)],
            "status": [status(1, 2, "judging"), status(1, 5, "std 0.1 m"), status(2, 1, ambiguous)],
        },
    )
    op.close()
    op.report(RunOutcome("complete", "", {}))
    with (tmp_path / "out" / "tags.csv").open(newline="") as f:
        rows = {r["id"]: r for r in csv.DictReader(f)}
    assert (rows["1"]["status"], rows["1"]["reason"]) == ("localized", "std 0.1 m")
    assert (rows["2"]["status"], rows["2"]["reason"]) == ("ambiguous", ambiguous)
    assert f"  tag 2: ambiguous: {ambiguous}" in run_summary(tmp_path / "out")
    assert not [line for line in run_summary(tmp_path / "out") if line.startswith("  tag 1")]
