"""Starting a run's worker processes (rover.runtime.workers) and seeing them through to one exit status.

Each worker is a `rover run` of its share, in the same process group (Ctrl-C on a terminal reaches
every one of them at once); SIGINT and SIGTERM sent to this process alone are passed on, and each
worker then stops within the run's promise (2 s). A worker says on a pipe when the run has begun
(every worker subscribed); one that exits with an error before that makes the others stop, so a
mistake found while building the operators (a missing dataset) ends the run at once, and the
output folder stays as it was.
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import signal
import subprocess
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from types import FrameType

from rover.errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_PARTIAL
from rover.runtime.workers import WorkerPlan

log = logging.getLogger("rover")

RUNNING = b"r"
"""What a worker writes on its pipe once the run has begun."""
POLL_S = 0.1
SEVERITY = (EXIT_FAILED, EXIT_BAD_INPUT, EXIT_PARTIAL)
"""Which worker's exit status the run's is when several failed: a failure, bad input, partial results."""


@dataclass
class Worker:
    """One worker process and the read end of its pipe."""

    index: int
    operators: tuple[str, ...]
    proc: subprocess.Popen[bytes]
    pipe: int
    running: bool = False
    status: int | None = None
    signalled: set[int] = field(default_factory=set)
    """the signals this process passed on to it"""

    @property
    def killed(self) -> bool:
        """Ended by a signal that this process did not send (kill -9, the kernel's OOM killer)."""
        return self.status is not None and self.status < 0 and -self.status not in self.signalled

    @property
    def name(self) -> str:
        return f"{WorkerPlan.host(self.index)} ({', '.join(self.operators)})"


def supervise(worker_plan: WorkerPlan, command: Callable[[int, int], Sequence[str]]) -> int:
    """Run a process per worker (`command(k, fd)`: worker k's argv, telling it to write RUNNING on
    `fd`) until every one has exited; return the run's exit status."""
    workers: list[Worker] = []
    interrupted: list[int] = []

    def forward(signum: int, _frame: FrameType | None) -> None:
        interrupted.append(signum)
        _signal_all(workers, signum)

    main = threading.current_thread() is threading.main_thread()
    previous = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)} if main else {}
    try:
        for k, group in enumerate(worker_plan.groups):
            read_end, write_end = os.pipe()
            try:
                proc = subprocess.Popen(command(k, write_end), pass_fds=(write_end,), stdin=subprocess.DEVNULL)
            except OSError:
                os.close(read_end)
                raise
            finally:
                os.close(write_end)
            workers.append(Worker(k, group, proc, read_end))
        _wait(workers)
    finally:
        for w in workers:
            if w.status is None:  # only after an error here: do not leave them running
                w.proc.kill()
                w.status = w.proc.wait()
            os.close(w.pipe)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return _status(workers, interrupted)


def _signal_all(workers: Sequence[Worker], signum: int) -> None:
    """Send `signum` to every worker still running (once each: a second one changes nothing)."""
    for w in workers:
        if w.status is None and signum not in w.signalled:
            w.signalled.add(signum)
            w.proc.send_signal(signum)


def _wait(workers: list[Worker]) -> None:
    """Until every worker has exited: note which began the run; stop them all when one fails before."""
    while any(w.status is None for w in workers):
        pipes = [w.pipe for w in workers if not w.running and w.status is None]
        readable, _, _ = select.select(pipes, [], [], POLL_S) if pipes else ([], [], [])
        for w in workers:
            if w.pipe in readable:
                w.running = os.read(w.pipe, 1) == RUNNING or w.running
        began = any(w.running for w in workers)
        for w in workers:
            if w.status is None and (code := w.proc.poll()) is not None:
                w.status = code
                if code != 0 and not began:
                    log.info("%s exited %d before the run began: stopping the others", w.name, code)
                    _signal_all(workers, signal.SIGTERM)
                elif w.killed:
                    log.error("%s was killed by %s", w.name, signal.Signals(-code).name)
        if not readable and not pipes:
            _sleep_on_children(workers)


def _sleep_on_children(workers: list[Worker]) -> None:
    """Wait until a worker exits, or POLL_S."""
    for w in workers:
        if w.status is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                w.proc.wait(POLL_S)
            return


def _status(workers: Sequence[Worker], interrupted: Sequence[int]) -> int:
    """0 when every worker ended well; 128 + the signal passed on; else the most severe worker's."""
    if interrupted:
        return 128 + interrupted[0]
    codes = [w.status or 0 for w in workers]
    if not any(codes):
        return 0
    if any(w.killed for w in workers):  # the others hold partial results
        return EXIT_PARTIAL
    return next((s for s in SEVERITY if s in codes), max(codes))
