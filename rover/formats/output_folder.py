"""A run's output folder, taken for the run and written as a whole or not at all.

A run takes the folder exclusively: `.rover.lock` in it, locked with flock(2) for as long as the
run lasts and holding its process id, so a second run into the same folder is refused at once
(`FolderBusy`, naming the first run's pid) instead of the two mixing or deleting each other's
files. The kernel drops the lock when the process dies, however it dies.

The run writes into a fresh staging folder inside it, `.rover-run-<pid>`, and only when it ended
with results (complete, partial, interrupted) are its files renamed into place, one rename each,
replacing an earlier run's files of the same names (`commit`). A failed run renames nothing: the
earlier run's results stay as they were. Nothing is removed before the run has its own results to
put in their place, so a run never removes its input, and the folder is refused when it holds one
(`refuse_input`).

Several writers of one process (the recorder, the run's outputs) share one claim, counted.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import shutil
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from rover.errors import BadInput, OutputFailed

LOCK_FILE = ".rover.lock"
STAGING_PREFIX = ".rover-run-"
LOCK_ATTEMPTS = 10
"""times a claim locks again when the lock file it locked was unlinked by the run that held it"""


class FolderBusy(BadInput):
    """Another run holds the output folder."""


@dataclass
class OutputFolder:
    """One process's claim on an output folder (from `claim`; give it back with `release`)."""

    path: Path
    staging: Path
    lock_fd: int
    created: bool
    """the folder did not exist before this run: removed again when the run leaves nothing in it"""
    users: int = 1
    committed: set[str] = field(default_factory=set)

    def stage(self, name: str) -> Path:
        """Where this run writes the file `name` until it is committed."""
        return self.staging / name

    def commit(self, names: Iterable[str], stale: Iterable[str] = ()) -> list[Path]:
        """Rename the staged files `names` into the folder (each replaces an earlier run's file of that
        name), then remove the `stale` files an earlier run wrote that this run did not; returns the
        committed paths."""
        names = [name for name in names if self.stage(name).exists()]
        for name in names:  # before any rename: a run's files go in all together or not at all
            if (self.path / name).is_dir():
                raise OutputFailed(f"{self.path / name}: cannot write: a folder is in the way")
        done = []
        for name in names:
            staged = self.stage(name)
            target = self.path / name
            try:
                staged.replace(target)
            except OSError as exc:
                raise OutputFailed(f"{target}: cannot write: {exc.strerror or exc}") from None
            self.committed.add(name)
            done.append(target)
        for name in stale:
            if name in self.committed:
                continue
            try:
                (self.path / name).unlink(missing_ok=True)
            except OSError as exc:
                why = exc.strerror or exc
                raise OutputFailed(f"{self.path / name}: cannot remove an earlier run's file: {why}") from None
        return done

    def discard(self, names: Iterable[str]) -> None:
        """Drop the staged files `names` (the run failed): the folder keeps what it held."""
        for name in names:
            self.stage(name).unlink(missing_ok=True)


_claims: dict[Path, OutputFolder] = {}
_claims_lock = threading.Lock()


def refuse_input(folder: str | Path, inputs: Iterable[str | Path]) -> None:
    """BadInput when one of the run's input files lies in its output folder: a run's results would
    replace files there, and an input must never be among them."""
    out = Path(folder).resolve()
    for source in inputs:
        path = Path(source).resolve()
        if path.parent == out:
            raise BadInput(
                f"{source}: the run's input is in its output folder {folder}: write the results elsewhere (--output)"
            )


def claim(folder: str | Path) -> OutputFolder:
    """Take `folder` for this run: create it (and its parents), lock it, and make a fresh staging
    folder. BadInput when it cannot be created or written, FolderBusy when another run has it."""
    path = Path(folder)
    key = path.resolve()
    with _claims_lock:
        if key in _claims:
            _claims[key].users += 1
            return _claims[key]
        if path.exists() and not path.is_dir():
            raise BadInput(f"{path}: not a folder (the output of a run is a folder)")
        created = not path.exists()
        fd = _lock(path)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        for stale in path.glob(f"{STAGING_PREFIX}*"):  # a run killed before it could clean up
            shutil.rmtree(stale, ignore_errors=True)
        staging = path / f"{STAGING_PREFIX}{os.getpid()}"
        try:
            staging.mkdir()
        except OSError as exc:
            os.close(fd)
            raise BadInput(f"{path}: cannot write the output folder: {exc.strerror or exc}") from None
        _claims[key] = OutputFolder(path, staging, fd, created)
        return _claims[key]


def _lock(path: Path) -> int:
    """Create the folder (and its parents) and take its lock file, exclusively; the file descriptor.
    The last user of a claim unlinks the lock file while holding it, so a lock taken on a file that
    is no longer the folder's (opened just before that unlink) is let go and taken again on the new one."""
    for _attempt in range(LOCK_ATTEMPTS):
        try:
            path.mkdir(parents=True, exist_ok=True)
            fd = os.open(path / LOCK_FILE, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise BadInput(f"{path}: cannot write the output folder: {exc.strerror or exc}") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "unknown"
            os.close(fd)
            if exc.errno in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise FolderBusy(
                    f"{path}: another rover run (pid {holder}) is writing into this folder: "
                    "wait for it, or give this one another --output"
                ) from None
            raise BadInput(f"{path}: cannot lock the output folder: {exc.strerror or exc}") from None
        try:
            current = os.stat(path / LOCK_FILE).st_ino
        except FileNotFoundError:
            current = -1
        if current == os.fstat(fd).st_ino:
            return fd
        os.close(fd)  # the file we locked was unlinked by the run before: lock the folder's own
    raise BadInput(f"{path}: cannot lock the output folder: its lock file keeps being replaced")


def release(claimed: OutputFolder) -> None:
    """Give the claim back; the last user removes the staging folder and the lock (and the folder
    itself when this run created it and left nothing in it)."""
    with _claims_lock:
        claimed.users -= 1
        if claimed.users > 0:
            return
        _claims.pop(claimed.path.resolve(), None)
        shutil.rmtree(claimed.staging, ignore_errors=True)
        (claimed.path / LOCK_FILE).unlink(missing_ok=True)
        os.close(claimed.lock_fd)
        if claimed.created:
            with contextlib.suppress(OSError):  # not empty: the user's files stay
                claimed.path.rmdir()
