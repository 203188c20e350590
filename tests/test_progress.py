"""A run's progress is the event time its last stages reached, within the span the replay covers."""

from __future__ import annotations

import io
import re
import threading

import pytest
from helpers import T0_NS, write_imu_dataset

from rover.cli.app import main
from rover.drivers.replay import DatasetReplay, ReplayParams
from rover.operator import Emit, Source
from rover.runtime import progress

LINE = re.compile(r"^progress: event time (\d+\.\d) of (\d+\.\d) s \((\d+)%\) after (\d+):(\d\d)$")


class Span(Source):
    def __init__(self, first_ns: int, last_ns: int):
        super().__init__()
        self.first_ns, self.last_ns = first_ns, last_ns

    def span_ns(self) -> tuple[int, int] | None:
        return self.first_ns, self.last_ns


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_not_on_a_terminal_one_line_every_ten_seconds_of_wall_time():
    reached: list[float] = [T0_NS - 5]
    clock, out = Clock(), io.StringIO()
    shown = progress.RunProgress([Span(T0_NS, T0_NS + 80 * 10**9)], lambda: reached[0], stream=out, clock=clock)
    shown.update()
    clock.now += 9.9
    shown.update()
    assert out.getvalue() == "", "nothing before the first 10 s"
    clock.now += 0.2
    reached[0] = T0_NS + 20 * 10**9
    shown.update()
    clock.now += 5.0
    shown.update()
    clock.now += 65.0
    reached[0] = float("inf")
    shown.update()
    assert out.getvalue().splitlines() == [
        "progress: event time 20.0 of 80.0 s (25%) after 0:10",
        "progress: event time 80.0 of 80.0 s (100%) after 1:20",
    ]


def test_sources_without_a_span_show_nothing():
    out = io.StringIO()
    clock = Clock()
    shown = progress.RunProgress([Source()], lambda: 0.0, stream=out, every_s=0.0, clock=clock)
    clock.now += 60
    shown.update()
    assert shown.span is None and out.getvalue() == ""


def test_the_replay_knows_the_span_of_its_dataset(tmp_path):
    path = write_imu_dataset(tmp_path / "d.mcap", 400, imu_hz=200.0, odom_every=0)
    replay = DatasetReplay(ReplayParams(path=str(path)))
    assert replay.span_ns() == (T0_NS, T0_NS + 399 * 5_000_000)
    stamps = [item.stamp_ns for item in replay.run(threading.Event()) if isinstance(item, Emit)]
    assert None not in stamps
    assert (min(stamps), max(stamps)) == replay.span_ns()  # type: ignore[type-var]


def test_a_run_not_on_a_terminal_reports_the_event_time_its_last_stages_reached(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(progress, "LINE_EVERY_S", 0.0)  # a line at every look, not every 10 s
    path = write_imu_dataset(tmp_path / "d.mcap", 4000, imu_hz=200.0, odom_every=10)
    assert main(["run", "--dataset", str(path), "--output", str(tmp_path / "out")]) == 0
    lines = [m for line in capsys.readouterr().err.splitlines() if (m := LINE.match(line))]
    assert lines, "progress lines on stderr"
    done = [float(m[1]) for m in lines]
    assert {m[2] for m in lines} == {"20.0"}, "the span of the dataset: 4000 samples at 200 Hz"
    assert done == sorted(done) and done[0] >= 0.0 and done[-1] <= 20.0
    assert len(set(done)) > 1, "the event time moves during the run"


@pytest.mark.parametrize("share", [0.0, 0.5, 1.0])
def test_the_share_is_the_event_time_reached(share):
    out = io.StringIO()
    clock = Clock()
    span = (T0_NS, T0_NS + 40 * 10**9)
    shown = progress.RunProgress([Span(*span)], lambda: T0_NS + share * 40e9, stream=out, every_s=1.0, clock=clock)
    clock.now += 1.0
    shown.update()
    assert out.getvalue() == f"progress: event time {40 * share:.1f} of 40.0 s ({100 * share:.0f}%) after 0:01\n"


def test_quiet_shows_no_progress(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(progress, "LINE_EVERY_S", 0.0)
    path = write_imu_dataset(tmp_path / "d.mcap", 2000, imu_hz=200.0, odom_every=10)
    assert main(["-q", "run", "--dataset", str(path), "--output", str(tmp_path / "out")]) == 0
    assert "progress:" not in capsys.readouterr().err
