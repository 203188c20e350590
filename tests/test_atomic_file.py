"""Output files appear whole or not at all, whatever stops the writing."""

from __future__ import annotations

from pathlib import Path

import pytest

from rover.errors import OutputFailed
from rover.formats.atomic_file import partial_path, remove_outputs, write_aside


def test_the_file_appears_only_when_written_whole(tmp_path):
    seen = []

    def write(partial: Path) -> None:
        partial.write_text("done\n")
        seen.append(sorted(p.name for p in tmp_path.iterdir()))

    write_aside(tmp_path / "a.txt", write)
    assert seen == [[".a.txt.partial"]]
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]


def test_a_failed_write_names_the_file_and_leaves_nothing(tmp_path):
    (tmp_path / "a.txt").mkdir()
    (tmp_path / "a.txt" / "x").write_text("")  # a non-empty folder where the file should go
    with pytest.raises(OutputFailed, match=r"a\.txt: cannot write: "):
        write_aside(tmp_path / "a.txt", lambda partial: partial.write_text("done\n"))
    assert not partial_path(tmp_path / "a.txt").exists()


def test_an_interrupt_while_writing_leaves_nothing(tmp_path):
    def write(partial: Path) -> None:
        partial.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_aside(tmp_path / "a.txt", write)
    assert list(tmp_path.iterdir()) == []


def test_an_earlier_runs_files_and_partial_files_are_removed(tmp_path):
    for name in ("a.txt", ".a.txt.partial", "b.txt", "keep.txt"):
        (tmp_path / name).write_text("old")
    remove_outputs([tmp_path / "a.txt", tmp_path / "b.txt", tmp_path / "never-written.txt"])
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
