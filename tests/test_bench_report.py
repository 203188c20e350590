"""bench/report.py: docs/benchmarks.md is what results.json and goals.yaml give, never edited by hand."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


def load_report():
    spec = importlib.util.spec_from_file_location("bench_report", ROOT / "bench" / "report.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is made
    spec.loader.exec_module(module)
    return module


report = load_report()


def test_the_page_is_up_to_date_with_the_results_and_goals():
    expected = report.render(json.loads(report.RESULTS.read_text()), yaml.safe_load(report.GOALS.read_text()))
    assert report.PAGE.read_text() == expected, "docs/benchmarks.md is stale: run bench/report.py"


def test_every_section_says_when_and_where_it_was_measured():
    results = json.loads(report.RESULTS.read_text())
    goals = yaml.safe_load(report.GOALS.read_text())
    for name in goals["sections"]:
        stamp = results["measured"][name]
        assert stamp["date"] and stamp["machine"], name


RESULTS = {
    "measured": {"slam": {"date": "2030-01-02", "machine": "test box", "commit": "abc1234"}},
    "slam": {
        "runs": [
            {"scenario": "paper", "robot_mean_m": 0.10, "ok": True},
            {"scenario": "paper", "robot_mean_m": 0.30, "ok": True},
            {"scenario": "hall", "robot_mean_m": 0.50, "ok": False},
        ]
    },
}


def goals(*rows: dict) -> dict:
    return {"sections": {"slam": {"title": "SLAM", "what": "what it measures", "rows": list(rows)}}}


def test_a_range_meets_its_goal_only_when_its_worst_value_does():
    met = {"figure": "robot", "at": ["runs", {"scenario": "paper"}, "robot_mean_m"], "unit": "cm", "goal": {"max": 30}}
    missed = {**met, "goal": {"max": 20}}
    page = report.render(RESULTS, goals(met, missed))
    assert "| robot | 10.0-30.0 cm | <= 30 cm | met |" in page
    assert "| robot | 10.0-30.0 cm | <= 20 cm | **not met** |" in page
    assert "measured 2030-01-02 on test box at commit `abc1234`" in page


def test_each_value_a_mean_and_a_boolean():
    page = report.render(
        RESULTS,
        goals(
            {"figure": "each", "at": ["runs", "*", "robot_mean_m"], "unit": "cm", "show": "each"},
            {"figure": "mean", "at": ["runs", "*", "robot_mean_m"], "unit": "cm", "show": "range_mean"},
            {"figure": "all ok", "at": ["runs", "*", "ok"], "unit": "bool"},
        ),
    )
    assert "| each | 10.0 / 30.0 / 50.0 cm |" in page
    assert "| mean | 10.0-50.0 cm (mean 30.0) |" in page
    assert "| all ok | no (1 of 3) |" in page


def test_a_path_the_results_do_not_have_is_named():
    with pytest.raises(report.ReportError, match="goals.yaml: slam: robot: results.json has no 'robot_m'"):
        report.render(RESULTS, goals({"figure": "robot", "at": ["runs", 0, "robot_m"], "unit": "cm"}))
    with pytest.raises(report.ReportError, match="no item with scenario = 'lab'"):
        report.render(RESULTS, goals({"figure": "robot", "at": ["runs", {"scenario": "lab"}, "robot_mean_m"]}))
    with pytest.raises(report.ReportError, match="unknown unit 'furlong'"):
        report.render(RESULTS, goals({"figure": "robot", "at": ["runs", 0, "robot_mean_m"], "unit": "furlong"}))
