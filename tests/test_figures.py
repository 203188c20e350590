"""What each figure of a run shows (rover.evaluation.figures), read from the drawn figures themselves
(their lines, labels, titles and axes), not from the PNG files' existence: a real run of one lap."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rover.evaluation import figures
from rover.formats.run_dir import load_run, load_truth


@pytest.fixture(scope="module")
def drawn(lap_runs, tmp_path_factory) -> dict[str, Any]:
    """The figures of the lap run with ground truth, by file name, as drawn before saving."""
    run = lap_runs["with"]
    kept: dict[str, Any] = {}

    def keep(fig: Any, path: Path, _plt: Any) -> Path:
        kept[path.name] = fig
        return path

    truth = load_truth(run.dataset)
    assert truth is not None
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(figures, "_save", keep)
        figures.write_figures(load_run(run.output), truth, tmp_path_factory.mktemp("figures"))
    kept["truth"] = truth
    kept["tags.csv"] = list(csv.DictReader((run.output / "tags.csv").open()))
    kept["t0"] = float((run.output / "trajectory.tum").read_text().split()[0])
    return kept


@pytest.mark.slow
def test_the_trajectory_has_its_legend_the_truth_under_the_estimate_and_every_tag_named(drawn):
    ax = drawn["trajectory.png"].axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[:3] == ["ground truth", "live estimate", "final estimate"]
    assert "true tag (red: NLOS)" in labels and "estimated tag, 2-sigma ellipse" in labels
    truth = next(line for line in ax.lines if line.get_label() == "ground truth")
    final = next(line for line in ax.lines if line.get_label() == "final estimate")
    assert truth.get_linewidth() > 3 * final.get_linewidth() and ax.lines.index(truth) < ax.lines.index(final)
    names = {a.get_text() for a in ax.texts}
    for row in drawn["tags.csv"]:  # each tag named where it truly is, with its state at the end of the run
        state = "" if row["observable"] == "1" else ", not localized at the end" if row["x"] else ", never localized"
        nlos = " (NLOS)" if drawn["truth"].tags[int(row["id"])][1] else ""
        assert f"tag {row['id']}{nlos}{state}" in names, names


@pytest.mark.slow
def test_tag_error_marks_when_each_tag_was_first_heard_as_tags_csv_says(drawn):
    ax = drawn["tag_error.png"].axes[0]
    dotted = sorted(line.get_xdata()[0] for line in ax.lines if line.get_linestyle() == ":")
    localized = [r for r in drawn["tags.csv"] if r["first_localized_s"]]
    expected = sorted(float(r["first_heard_s"]) - drawn["t0"] for r in localized)
    assert np.allclose(dotted, expected, atol=1e-6)
    assert ax.get_yscale() == "log"
    ticks = ax.yaxis.get_major_formatter()
    assert [ticks(v, 0) for v in (1, 2, 5, 10, 30, 100)] == ["1", "2", "5", "10", "", "100"]
    assert ax.get_legend().get_bbox_to_anchor().x0 > ax.bbox.x1 - 1  # beside the plot, off the curves


@pytest.mark.slow
def test_robot_error_says_what_final_and_live_mean_and_the_aoa_cdf_goes_to_180(drawn):
    ax = drawn["robot_error.png"].axes[0]
    assert "final: each pose as it left the SLAM window" in ax.get_title()
    assert "live: as estimated at its own time" in ax.get_title()
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["final", "live"]
    assert drawn["aoa_cdf.png"].axes[0].get_xlim() == (0.0, 180.0)
