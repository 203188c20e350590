"""The real `rover` command in a subprocess, with the tests' operators (tests/toyops.py) importable."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

from helpers.paths import TESTS
from helpers.wait import wait_for_file


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]))


def run_rover(
    *args: str,
    cwd: Path | None = None,
    timeout: float = 120,
    check: bool = False,
) -> subprocess.CompletedProcess:
    """`rover ARGS` to its end, its output captured."""
    proc = subprocess.run(
        [sys.executable, "-m", "rover.cli", *args], cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"rover {' '.join(args)} exited {proc.returncode}:\n{proc.stderr}")
    return proc


def popen_rover(*args: str, cwd: Path | None = None, max_file_bytes: int | None = None) -> subprocess.Popen:
    """`rover ARGS` started in a subprocess, its output piped to the test; with `max_file_bytes`,
    writes past that size fail (EFBIG, as on a full disk)."""

    def limit() -> None:
        if max_file_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    return subprocess.Popen(
        [sys.executable, "-m", "rover.cli", *args],
        cwd=cwd,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=limit,
    )


def stop_while_writing(proc: subprocess.Popen, partial: Path, signum: int) -> tuple[int, str]:
    """Send `signum` once the command's `partial` output file exists; (status, stderr) once it ended."""
    wait_for_file(partial, proc)
    proc.send_signal(signum)
    _, stderr = proc.communicate(timeout=60)
    assert "Traceback" not in stderr, stderr
    return proc.returncode, stderr
