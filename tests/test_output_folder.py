"""A run's output folder: taken by one run at a time, written whole at the end or not at all, never
holding the run's input. The lock is tested across real processes (flock is per open file)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from helpers import free_port, popen_rover, read_bag, run_rover, wait_until, write_imu_dataset

from rover.errors import BadInput
from rover.formats.output_folder import LOCK_FILE, STAGING_PREFIX, FolderBusy, claim, refuse_input, release

HOLD = """\
import sys
from rover.formats.output_folder import claim
claim(sys.argv[1])
print("claimed", flush=True)
sys.stdin.read()
"""


def hold(folder) -> subprocess.Popen:
    """Another process holding `folder` until its stdin closes."""
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout is not None and proc.stdout.readline() == "claimed\n"
    return proc


def test_a_claim_creates_the_folder_and_the_last_release_leaves_it_as_found(tmp_path):
    out = tmp_path / "a" / "out"
    first, second = claim(out), claim(out)  # two writers of one process share it
    assert first is second and (out / LOCK_FILE).read_text() == f"{os.getpid()}\n"
    assert first.staging.is_dir() and first.staging.name.startswith(STAGING_PREFIX)
    release(first)
    assert first.staging.is_dir(), "still in use by the second writer"
    release(second)
    assert not out.exists(), "created by the run and left empty: removed"
    assert (tmp_path / "a").is_dir()


def test_a_commit_puts_every_staged_file_in_place_and_removes_the_stale_ones(tmp_path):
    (tmp_path / "old.txt").write_text("an earlier run's")
    (tmp_path / "result.txt").write_text("an earlier result")
    (tmp_path / "notes.txt").write_text("the user's")
    folder = claim(tmp_path)
    folder.stage("result.txt").write_text("this run's")
    assert (tmp_path / "result.txt").read_text() == "an earlier result", "nothing changes before the commit"
    folder.commit(["result.txt"], stale=["result.txt", "old.txt"])
    release(folder)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt", "result.txt"]
    assert (tmp_path / "result.txt").read_text() == "this run's"


def test_a_second_process_is_refused_naming_the_first(tmp_path):
    holder = hold(tmp_path)
    try:
        with pytest.raises(FolderBusy, match=rf"{tmp_path}: another rover run \(pid {holder.pid}\) is writing"):
            claim(tmp_path)
    finally:
        holder.communicate("")
    release(claim(tmp_path))  # free again once the holder is gone


def test_a_run_killed_leaves_a_lock_the_next_run_takes_and_a_staging_folder_it_removes(tmp_path):
    holder = hold(tmp_path)
    holder.kill()
    holder.wait()
    (tmp_path / f"{STAGING_PREFIX}{holder.pid}" / "half.tum").write_text("cut")
    folder = claim(tmp_path)
    assert [p.name for p in tmp_path.glob(f"{STAGING_PREFIX}*")] == [folder.staging.name]
    release(folder)
    assert list(tmp_path.iterdir()) == []


def test_an_input_in_the_output_folder_is_refused(tmp_path):
    refuse_input(tmp_path / "out", [tmp_path / "dataset.mcap"])
    with pytest.raises(BadInput, match=r"dataset\.mcap: the run's input is in its output folder"):
        refuse_input(tmp_path / "out", [tmp_path / "out" / ".." / "out" / "dataset.mcap"])


def test_a_folder_that_cannot_be_written_is_bad_input(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(BadInput, match="not a folder"):
        claim(tmp_path / "file")
    with pytest.raises(BadInput, match="cannot write the output folder"):
        claim("/proc/nope")


# --- the command line ----------------------------------------------------------------------------


def test_a_run_whose_dataset_is_in_its_output_folder_is_refused_and_loses_nothing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dataset = write_imu_dataset(out / "results.mcap", 200)
    before = dataset.read_bytes()
    proc = run_rover("run", "--dataset", str(dataset), "--output", str(out))
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"rover: error: {dataset}: the run's input is in its output folder {out}: "
        "write the results elsewhere (--output)"
    ]
    assert [p.name for p in out.iterdir()] == ["results.mcap"] and dataset.read_bytes() == before


RECORD_ONLY = """\
version: 1
name: record-only
vars: {dataset: "", output: out}
operators:
  replay: {uses: dataset_replay, params: {path: "${dataset}"}}
  record: {uses: recorder, inputs: {imu: replay/imu}, params: {out: "${output}", file: imu.mcap}}
"""
"""a pipeline whose only writer is a recorder of a file named like its input (the README's own-operator
example is one): the run_outputs operator's check of its dataset is not there to help"""


def test_a_recording_never_replaces_a_file_no_earlier_run_wrote(tmp_path):
    """A run whose recording would replace its own input (a file of that name, not an earlier run's)
    is refused before it reads anything: exit 2, one line naming the file, the input as it was and
    nothing left in the folder; a file the recorder wrote in an earlier run is replaced as before."""
    pipeline = tmp_path / "record.yaml"
    pipeline.write_text(RECORD_ONLY)
    out = tmp_path / "out"
    out.mkdir()
    dataset = write_imu_dataset(out / "imu.mcap", 200)
    before = dataset.read_bytes()
    proc = run_rover("run", str(pipeline), "--dataset", str(dataset), "--output", str(out))
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"rover: error: {dataset}: this run would replace it, and no earlier run wrote it (a dataset? this run's "
        "input?): give the run another --output, or move the file away"
    ]
    assert [p.name for p in out.iterdir()] == ["imu.mcap"] and dataset.read_bytes() == before
    other = write_imu_dataset(tmp_path / "other.mcap", 300)
    for samples in (300, 300):  # the second run replaces the first's recording
        proc = run_rover("run", str(pipeline), "--dataset", str(other), "--output", str(out / "again"))
        assert proc.returncode == 0, proc.stderr
        assert len([t for t, _s, _d in read_bag(out / "again" / "imu.mcap") if t == "/imu"]) == samples


@pytest.mark.slow
def test_a_second_run_into_a_busy_folder_is_refused_and_the_first_keeps_its_results(tmp_path):
    """Run A holds its first message until released; run B into the same folder exits 2 naming A's
    pid and writes nothing; A then finishes with every result in place."""
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 400, odom_every=0)
    out, release_file = tmp_path / "out", tmp_path / "release"
    pipeline = tmp_path / "held.yaml"
    pipeline.write_text(f"""\
name: held
hosts:
  robot: {{listen: ["tcp/127.0.0.1:{free_port()}"]}}
operators:
  replay: {{uses: dataset_replay, host: robot, params: {{path: "{dataset}"}}}}
  slow:   {{uses: toyops.Slow, host: robot, inputs: {{imu: replay/imu}},
            params: {{delay_s: 0, release: "{release_file}"}}}}
  record: {{uses: recorder, host: robot, inputs: {{imu: replay/imu}}, params: {{out: "{out}"}}}}
""")
    first = popen_rover("run", str(pipeline))
    try:
        wait_until(
            lambda: (out / LOCK_FILE).exists() and (out / LOCK_FILE).read_text().strip(), "run A's lock", procs=[first]
        )
        second = run_rover("run", "--dataset", str(dataset), "--output", str(out))
    finally:
        release_file.touch()
        _, err = first.communicate(timeout=120)
    assert second.returncode == 2, second.stderr
    assert second.stderr.splitlines() == [
        f"rover: error: {out}: another rover run (pid {first.pid}) is writing into this folder: "
        "wait for it, or give this one another --output"
    ]
    assert first.returncode == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["results.mcap"]
    assert len(read_bag(out / "results.mcap")) == 400


def test_an_output_folder_that_cannot_be_written_is_refused_before_the_run(tmp_path):
    dataset = write_imu_dataset(tmp_path / "imu.mcap", 200)
    proc = run_rover("run", "--dataset", str(dataset), "--output", "/proc/nope")
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("rover: error: /proc/nope: cannot write the output folder"), lines


def test_a_lock_taken_on_a_lock_file_just_unlinked_is_taken_again_on_the_folders_own(tmp_path, monkeypatch):
    """The run before unlinks its lock file as it lets go: a claim that opened that file just before
    and locks it would share the folder with the next run, which creates a new one. It sees the
    file is no longer the folder's and locks the new one instead."""
    import fcntl

    locked: list[int] = []
    flock = fcntl.flock

    def release_meanwhile(fd: int, how: int) -> None:
        if not locked:  # the run before lets go between this claim's open and its lock
            (tmp_path / LOCK_FILE).unlink()
            (tmp_path / LOCK_FILE).write_text("")
        locked.append(fd)
        flock(fd, how)

    monkeypatch.setattr(fcntl, "flock", release_meanwhile)
    claimed = claim(tmp_path)
    assert len(locked) == 2 and os.fstat(claimed.lock_fd).st_ino == os.stat(tmp_path / LOCK_FILE).st_ino
    release(claimed)
