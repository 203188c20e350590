"""The one way a test waits: poll a condition with a deadline, failing early when a process it
depends on has ended. Never a bare sleep to synchronize."""

from __future__ import annotations

import contextlib
import os
import select
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path

POLL_S = 0.002


def wait_until(
    condition: Callable[[], object],
    what: str,
    *,
    procs: Sequence[subprocess.Popen] = (),
    timeout_s: float = 60.0,
    poll_s: float = POLL_S,
) -> None:
    """Poll `condition` until it holds; fail naming `what` after `timeout_s`, or as soon as one of
    `procs` has ended (with its stderr)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        for proc in procs:
            if proc.poll() is not None:
                _out, err = proc.communicate()
                command = " ".join(map(str, proc.args)) if isinstance(proc.args, list) else str(proc.args)
                raise AssertionError(f"{command} ended ({proc.returncode}) before {what}:\n{err}")
        assert time.monotonic() < deadline, f"not {what} after {timeout_s:g} s"
        time.sleep(poll_s)


def wait_for_file(path: Path, proc: subprocess.Popen, min_bytes: int = 0, timeout_s: float = 300.0) -> None:
    """Poll until `path` exists with at least `min_bytes`; fail if the process ends first or time runs out."""

    def written() -> bool:
        with contextlib.suppress(FileNotFoundError):
            return path.stat().st_size >= min_bytes
        return False

    wait_until(written, f"{path} of {min_bytes} bytes", procs=[proc], timeout_s=timeout_s)


def wait_for_line(proc: subprocess.Popen, text: str, timeout_s: float = 120.0) -> str:
    """Read the process's stderr (a text pipe) until a line holds `text`; return what was read, which
    its `communicate` no longer returns. Fail when it ends first or time runs out."""
    assert proc.stderr is not None, "started without stderr=PIPE"
    fd = proc.stderr.fileno()
    read = b""
    deadline = time.monotonic() + timeout_s
    while text.encode() not in read:
        left = deadline - time.monotonic()
        assert left > 0, f"no line with {text!r} after {timeout_s:g} s:\n{read.decode(errors='replace')}"
        ready, _, _ = select.select([fd], [], [], left)
        chunk = os.read(fd, 65536) if ready else b""
        if ready and not chunk:
            proc.wait()
            raise AssertionError(f"ended ({proc.returncode}) before a line with {text!r}:\n{read.decode()}")
        read += chunk
    return read.decode(errors="replace")
