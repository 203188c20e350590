"""The run's progress by event time: how far its last stages have got in the span a replay covers.

Counting replayed messages says little: the replay reaches its end while the last stages (the
SLAM, the recorder) still have seconds of event time to go. So progress is the event time the
last stages on this host have finished with, against the first and last stamp of the replayed
files. On a terminal it is a bar on stderr; otherwise one line every `LINE_EVERY_S` of wall time,
so a log of a long run shows it is moving. Live sources know no end, so they show nothing.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable
from typing import TextIO

from rover.operator import Source

LINE_EVERY_S = 10.0
"""wall time between progress lines when stderr is not a terminal"""


class RunProgress:
    """Shows `reached()` (event time, ns; inf once the last stages are done) within the span of the
    sources that know theirs: a bar on a terminal, else a line every `every_s` (default `LINE_EVERY_S`) of wall time."""

    def __init__(
        self,
        sources: list[Source],
        reached: Callable[[], float],
        stream: TextIO | None = None,
        every_s: float | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        spans = [span for s in sources if (span := s.span_ns()) is not None]
        self.span = (min(a for a, _ in spans), max(b for _, b in spans)) if spans else None
        self.reached = reached
        self.stream = sys.stderr if stream is None else stream
        self.every_s = LINE_EVERY_S if every_s is None else every_s
        self.clock = clock
        self.started = clock()
        self.next_line = self.started + self.every_s
        self.bar = None
        if self.span is not None and self.stream.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("event time"),
                BarColumn(),
                TextColumn("{task.completed:.0f} of {task.total:.0f} s"),
                TimeRemainingColumn(),
                console=Console(file=self.stream),
                transient=True,
            )
            self.task_id = self.bar.add_task("run", total=self.total_s)

    @property
    def total_s(self) -> float:
        return 0.0 if self.span is None else (self.span[1] - self.span[0]) / 1e9

    def done_s(self) -> float:
        """Event time the last stages have finished with, in seconds from the start of the span."""
        if self.span is None:
            return 0.0
        reached = self.reached()
        if reached == math.inf:
            return self.total_s
        return min(max(reached - self.span[0], 0.0) / 1e9, self.total_s)

    def update(self) -> None:
        if self.span is None:
            return
        if self.bar is not None:
            self.bar.update(self.task_id, completed=self.done_s())
            return
        now = self.clock()
        if now < self.next_line:
            return
        self.next_line = now + self.every_s
        done, total = self.done_s(), self.total_s
        share = 100.0 * done / total if total > 0 else 100.0
        minutes, seconds = divmod(int(now - self.started), 60)
        line = f"progress: event time {done:.1f} of {total:.1f} s ({share:.0f}%) after {minutes}:{seconds:02d}"
        self.stream.write(line + "\n")
        self.stream.flush()

    def __enter__(self) -> RunProgress:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()
