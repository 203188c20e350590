"""Output files that appear whole or not at all: written aside under a hidden partial name and
renamed into place, the partial file removed on every failure, an interrupt included."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path

from rover.errors import OutputFailed


def partial_path(path: Path) -> Path:
    """Where `path` is written until it is complete: `.NAME.partial` beside it."""
    return path.with_name(f".{path.name}.partial")


def write_aside(path: Path, write: Callable[[Path], object]) -> Path:
    """`write(partial_path(path))`, then rename the partial file to `path`; OutputFailed naming `path`
    when that fails (nothing is left behind)."""
    partial = partial_path(path)
    try:
        write(partial)
        partial.replace(path)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise OutputFailed(f"{path}: cannot write: {exc.strerror or exc}") from None
    except BaseException:
        partial.unlink(missing_ok=True)
        raise
    return path


def remove_outputs(paths: Iterable[Path]) -> None:
    """Remove files an earlier run wrote (and their leftover partial files) before a new run writes them."""
    for path in paths:
        for old in (path, partial_path(path)):
            try:
                old.unlink(missing_ok=True)
            except OSError as exc:
                raise OutputFailed(f"{old}: cannot remove the previous run's file: {exc.strerror or exc}") from None
