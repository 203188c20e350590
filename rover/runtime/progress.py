"""A progress bar on the terminal for a replay whose sources know their length."""

from __future__ import annotations

import sys

from rover.operator import Source


class ProgressBar:
    """A progress bar on stderr for sources that know their length, only when stderr is a terminal."""

    def __init__(self, sources: list[Source]):
        self.sources = [s for s in sources if s.progress() is not None]
        self.progress = None
        if self.sources and sys.stderr.isatty():
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

            self.progress = Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                transient=True,
            )
            self.ids = [self.progress.add_task("replay", total=(s.progress() or (0, 0))[1]) for s in self.sources]

    def update(self) -> None:
        if self.progress is not None:
            for task_id, source in zip(self.ids, self.sources, strict=True):
                self.progress.update(task_id, completed=(source.progress() or (0, 0))[0])

    def __enter__(self) -> ProgressBar:
        if self.progress is not None:
            self.progress.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        if self.progress is not None:
            self.progress.stop()
