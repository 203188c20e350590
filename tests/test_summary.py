"""What `rover run` prints at its end, read back from the output folder."""

from __future__ import annotations

import json

from rover.cli.summary import run_summary


def test_the_summary_says_what_the_files_say(tmp_path):
    (tmp_path / "run.json").write_text(json.dumps({"status": "complete", "received": 12345, "files": ["tags.csv"]}))
    (tmp_path / "trajectory.tum").write_text("".join(f"{100 + t * 0.5:.3f} 0 0 0 0 0 0 1\n" for t in range(21)))
    (tmp_path / "tags.csv").write_text(
        "id,channel,x,y,z,var_x,cov_xy,var_y,observable,first_heard_s,first_localized_s,last_heard_s\n"
        "1,149,1.0,2.0,0,0.01,0,0.01,1,1,2,3\n2,153,,,,,,,0,1,,3\n7,157,,,,,,,0,1,,3\n"
        "9,161,3.0,1.0,0,0.5,0,0.5,0,1,4,5\n"
    )
    (tmp_path / "metrics.json").write_text(
        json.dumps({"robot": {"trajectory.tum": {"unaligned": {"mean_m": 0.021}}}, "los_tags_mean_m": 0.05})
    )
    assert run_summary(tmp_path) == [
        "run complete: 21 poses, 10.0 s, 12,345 messages",
        "tags localized at the end: 1 of 4 heard (never localized: 2, 7; localized earlier, not at the end: 9)",
        "errors against the dataset's truth: robot mean 2.1 cm, LOS tags mean 5.0 cm",
        f"wrote {tmp_path}/ (run.json, tags.csv)",
    ]


def test_a_folder_without_a_run_has_no_summary(tmp_path):
    assert run_summary(tmp_path) == []
