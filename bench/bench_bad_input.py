"""Bad input, every time: each row of the bad-input issue's table run through the real `rover`
command, with its exit status, how many lines it printed, whether a traceback or a hidden
partial file was left, its wall time and its peak memory; then the interrupt promise (seconds
from SIGINT to exit on a run with ground truth, goal < 2 s) and whether two identical runs
write the same results.mcap bytes.

Each command runs in a subprocess limited to 3 GiB of address space, as the issue measured.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

MEMORY_LIMIT_BYTES = 3 * 2**30
STOP_GOAL_S = 2.0
QUICK = ("--set", "trajectory.laps=1", "--set", "trajectory.speed_m_s=1.0")
"""A short simulated run: enough for a run with ground truth, in seconds."""


@dataclass
class Row:
    input: str
    status: int
    lines: int
    traceback: bool
    leftovers: int
    wall_s: float
    peak_mb: float

    HEADER = f"{'input':<40} {'status':>6} {'lines':>5} {'traceback':>9} {'partial':>7} {'wall s':>7} {'peak MB':>8}"

    def line(self) -> str:
        return (
            f"{self.input:<40} {self.status:>6} {self.lines:>5} {'YES' if self.traceback else 'no':>9} "
            f"{self.leftovers:>7} {self.wall_s:>7.2f} {self.peak_mb:>8.0f}"
        )


def rover(
    *args: str, cwd: Path, max_file_bytes: int | None = None, stop_after: Callable[[], bool] | None = None
) -> tuple[int, str, float, float]:
    """Run `rover ARGS`; (status, stderr, wall seconds, peak RSS in MB). With `stop_after`, SIGTERM
    is sent once it returns True."""

    def limits() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))
        if max_file_bytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (max_file_bytes, max_file_bytes))

    started = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover.cli", *args],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=limits,
    )
    if stop_after is not None:
        while proc.poll() is None and not stop_after():
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
    assert proc.stderr is not None
    err = proc.stderr.read()
    _pid, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    code = proc.returncode if proc.returncode >= 0 else 128 - proc.returncode
    return code, err, time.monotonic() - started, usage.ru_maxrss / 1024


def row(name: str, folder: Path, *args: str, **kw) -> Row:
    status, err, wall, peak = rover(*args, cwd=folder, **kw)
    lines = [line for line in err.splitlines() if "WARNING" not in line]
    hidden = [p for p in folder.rglob(".*") if p.is_file()]
    return Row(name, status, len(lines), "Traceback" in err, len(hidden), wall, peak)


def alias_bomb(levels: int) -> str:
    lines = ['a0: &a0 ["x","x","x","x","x","x","x","x","x"]']
    for i in range(1, levels + 1):
        refs = ",".join([f"*a{i - 1}"] * 9)
        lines.append(f"a{i}: &a{i} [{refs}]")
    return "version: 1\nname: bomb\nvars:\n" + "\n".join("  " + line for line in lines) + "\noperators: {}\n"


def table_rows(work: Path, dataset: Path) -> list[Row]:
    rows: list[Row] = []

    def case(name: str, files: dict[str, bytes | str], *args: str, **kw) -> None:
        folder = work / f"case{len(rows)}"
        folder.mkdir()
        for fname, data in files.items():
            (folder / fname).parent.mkdir(parents=True, exist_ok=True)
            (folder / fname).write_bytes(data.encode() if isinstance(data, str) else data)
        rows.append(row(name, folder, *args, **kw))
        shutil.rmtree(folder)
        print(rows[-1].line(), flush=True)

    case("pipeline: alias bomb, 9 levels", {"p.yaml": alias_bomb(9)}, "check", "p.yaml")
    case("pipeline: alias bomb, 7 levels", {"p.yaml": alias_bomb(7)}, "check", "p.yaml")
    case("setup: alias bomb, 9 levels", {"setup.yaml": alias_bomb(9)}, "check", "setup.yaml")
    case("pipeline nested 900 deep", {"p.yaml": "a: " + "[" * 900 + "]" * 900 + "\n"}, "check", "p.yaml")
    case("--set nested 900 deep", {}, "check", str(Path(__file__).parents[1] / "pipeline.yaml"), "--set",
         "x=" + "[" * 900 + "]" * 900)  # fmt: skip
    case("a 50 MB pipeline file", {"p.yaml": "# " + "x" * (50 * 2**20) + "\n"}, "check", "p.yaml")
    good_run: dict[str, bytes | str] = {
        "run/trajectory.tum": "1700000000.0 0 0 0 0 0 0 1\n1700000001.0 1 0 0 0 0 0 1\n"
    }
    for label, text in (
        ("1.7e9 (valid)", "1.7e9 0 0 0 0 0 0 1\n1.700000001e9 1 0 0 0 0 0 1\n"),
        ("...5e0 (valid)", "1700000000.0e0 0 0 0 0 0 0 1\n1700000001.0e0 1 0 0 0 0 0 1\n"),
        ("1e20", "1e20 0 0 0 0 0 0 1\n"),
        ("negative", "-5.0 0 0 0 0 0 0 1\n"),
        ("NaN", "1.0 nan 0 0 0 0 0 1\n"),
    ):
        case(f"TUM truth with stamps {label}", {**good_run, "t.tum": text}, "eval", "run", "--truth", "t.tum")
    case("a binary TUM truth", {**good_run, "t.tum": os.urandom(4096)}, "eval", "run", "--truth", "t.tum")
    case("simulate on a full disk (ulimit -f)", {}, "simulate", *QUICK, "-o", "x.mcap", max_file_bytes=200_000)
    case("simulate -o EXISTING_DIR --force", {"d/keep": ""}, "simulate", *QUICK, "-o", "d", "--force")
    case("convert -o EXISTING_DIR --force", {"d/keep": ""}, "convert", str(dataset), "-o", "d", "--force")
    case("SIGTERM during simulate", {}, "simulate", *QUICK, "-o", "x.mcap",
         stop_after=lambda: any(work.rglob(".x.mcap.partial")))  # fmt: skip
    case("run on a 6-byte text file", {"d.mcap": "hello\n"}, "run", "--dataset", "d.mcap", "--output", "o")
    corrupt = bytearray(dataset.read_bytes())
    middle = len(corrupt) // 2
    corrupt[middle : middle + 64] = bytes(64)
    case("run on an MCAP with a corrupt chunk", {"d.mcap": bytes(corrupt)}, "run", "--dataset", "d.mcap",
         "--output", "o")  # fmt: skip
    case("info on a 6-byte file", {"d.mcap": "hello\n"}, "info", "d.mcap")
    case("info on a corrupt chunk", {"d.mcap": bytes(corrupt)}, "info", "d.mcap")
    eval_cases: tuple[tuple[str, dict[str, bytes | str]], ...] = (
        ("a binary trajectory", {"run/trajectory.tum": os.urandom(2048)}),
        ("1.7e9 stamps (valid)", {"run/trajectory.tum": "1.7e9 0 0 0 0 0 0 1\n1.700000001e9 1 0 0 0 0 0 1\n"}),
        ("run.json = []", {**good_run, "run/run.json": "[]"}),
        ('run.json = {"dataset": 5}', {**good_run, "run/run.json": '{"dataset": 5}'}),
        ("a 3-byte results.mcap", {**good_run, "run/results.mcap": "abc"}),
        ("a binary tags.csv", {**good_run, "run/tags.csv": os.urandom(2048)}),
    )
    for label, files in eval_cases:
        case(f"eval on {label}", {**files, "t.tum": good_run["run/trajectory.tum"]}, "eval", "run", "--truth", "t.tum")
    case("eval with a 3-byte --truth", {**good_run, "t.mcap": "abc"}, "eval", "run", "--truth", "t.mcap")
    return rows


def stop_time(work: Path, dataset: Path) -> dict[str, float | int | bool]:
    """Seconds from SIGINT to exit, on a run with ground truth that is well under way: replayed at
    real time, stopped at its first progress line (10 s in), every worker process with it."""
    out = work / "stopped"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rover.cli", "run", "--dataset", str(dataset), "--output", str(out), "--speed", "1"],
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    for line in proc.stderr:
        if line.startswith("progress:"):
            break
    else:
        raise SystemExit(f"the run ended (status {proc.wait()}) before its first progress line")
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.stderr.read()
    status = proc.wait()
    took = time.monotonic() - sent
    run = json.loads((out / "run.json").read_text())
    return {
        "status": status,
        "stop_s": took,
        "estimates_written": "trajectory.tum" in run["files"],
        "metrics_written": "metrics.json" in run["files"],
    }


def identical_runs(work: Path, dataset: Path) -> bool:
    results = []
    for name in ("first", "second"):
        subprocess.run(
            [sys.executable, "-m", "rover.cli", "-q", "run", "--dataset", str(dataset), "--output", str(work / name)],
            check=True,
        )
        results.append((work / name / "results.mcap").read_bytes())
    return results[0] == results[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", help="write the figures here (bench/run_all.py)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        dataset = work / "quick.mcap"
        subprocess.run([sys.executable, "-m", "rover.cli", "-q", "simulate", *QUICK, "-o", str(dataset)], check=True)
        print(Row.HEADER)
        rows = table_rows(work, dataset)
        paper = work / "paper.mcap"  # the paper's 180 s run: long enough to stop in the middle
        subprocess.run(
            [sys.executable, "-m", "rover.cli", "-q", "simulate", "--seed", "1", "-o", str(paper)], check=True
        )
        stop = stop_time(work, paper)
        print(
            f"SIGINT during a run with ground truth: status {stop['status']}, exit after {stop['stop_s']:.2f} s "
            f"(goal < {STOP_GOAL_S:g} s), estimates written: {stop['estimates_written']}, "
            f"metrics written: {stop['metrics_written']}"
        )
        same = identical_runs(work, dataset)
        print(f"two identical runs, results.mcap byte-identical: {same}")
    if args.json:
        figures = {"rows": [asdict(r) for r in rows], "interrupt": stop, "identical_results_mcap": same}
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
