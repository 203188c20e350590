"""`run_outputs`: the run's files appear whole or not at all, a new run replaces an old one's,
and run.json says how every run ended."""

from __future__ import annotations

import json
import time

import pytest
from helpers import T0_NS

from rover.drivers.run_outputs import RUN_FILES, RunOutputs, RunOutputsParams
from rover.errors import OutputFailed
from rover.messages import header, make
from rover.operator import OperatorCounts, RunOutcome
from rover.testing import run_operator


def pose(i: int):
    return make("geometry_msgs/msg/PoseStamped", header=header(T0_NS + i * 10**8, "world"))


def timing(i: int, wall_s: float):
    return make("rover_msgs/msg/Timing", header=header(T0_NS + i * 10**8, "world"), stage="slam.update", wall_s=wall_s)


def outputs(tmp_path) -> RunOutputs:
    op = RunOutputs(RunOutputsParams(out=str(tmp_path / "out")))
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
    op.start()
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


def test_a_new_run_first_removes_what_an_earlier_run_left(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    for name in RUN_FILES:
        (out / name).write_text("from the earlier run")
    (out / ".trajectory.tum.partial").write_text("half")
    (out / "notes.txt").write_text("the user's own file")
    RunOutputs(RunOutputsParams(out=str(out))).start()
    assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_an_output_that_cannot_be_written_fails_and_the_failed_run_keeps_only_run_json(tmp_path):
    op = outputs(tmp_path)
    out = tmp_path / "out"
    (out / "tags.csv").mkdir(parents=True)  # a folder in the way of the third file
    (out / "tags.csv" / "x").write_text("")
    with pytest.raises(OutputFailed, match=r"tags\.csv: cannot write: (Is a directory|Directory not empty)"):
        op.close()
    op.report(RunOutcome("failed", "operator 'outputs': tags.csv: cannot write"))
    assert sorted(p.name for p in out.iterdir()) == ["run.json", "tags.csv"]  # the folder is the user's
    run = json.loads((out / "run.json").read_text())
    assert run["status"] == "failed" and run["files"] == []


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
