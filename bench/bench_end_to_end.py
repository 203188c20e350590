"""The whole default pipeline on the simulated `paper` run, three repeats: real-time factor as `rover run` runs it
(worker processes, one per core), in one process (`--workers 1`) and with the three-host layout on loopback
(three processes), the run's errors, and where the one-process run's time went per operator (run.json's
`profile`: decoding, handler, encoding, sending, the runtime's share, waiting for input, closing, and the
thread's CPU time). Goals (issue 41): >= 20x real time with workers, >= 8x in one process, three hosts no
slower than one process."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_pipeline import free_port

ROVER = [sys.executable, "-m", "rover.cli", "-q"]


def duration_s(dataset: Path) -> float:
    out = subprocess.run([*ROVER, "info", str(dataset), "--json"], capture_output=True, text=True, check=True).stdout
    return float(json.loads(out)["duration_s"])


def run_one(dataset: Path, out: Path, workers: str) -> float:
    start = time.perf_counter()
    subprocess.run([*ROVER, "run", "--dataset", str(dataset), "--output", str(out), "--workers", workers], check=True)
    return time.perf_counter() - start


def run_three(dataset: Path, out: Path) -> float:
    port = free_port()
    start = time.perf_counter()
    procs = [
        subprocess.Popen(
            [*ROVER, "run", "--host", host, "--dataset", str(dataset), "--output", str(out), "--set", f"port={port}"]
        )
        for host in ("laptop", "base", "nuc")
    ]
    codes = [p.wait() for p in procs]
    if any(codes):
        raise SystemExit(f"three-host run failed: exit codes {codes}")
    return time.perf_counter() - start


def workers_count() -> int:
    """How many workers `rover run --workers auto` starts here (one per available core)."""
    from rover.runtime.workers import available_cores

    return available_cores()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3, help="runs of each layout (the figures' range)")
    ap.add_argument("--json")
    args = ap.parse_args()
    one_s, workers_s, three_s, same = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        dataset = tmp / "paper.mcap"
        subprocess.run(
            [*ROVER, "simulate", "--scenario", "paper", "--seed", str(args.seed), "-o", str(dataset)], check=True
        )
        data_s = duration_s(dataset)
        for i in range(args.repeats):
            workers_s.append(run_one(dataset, tmp / f"workers{i}", "auto"))
            one_s.append(run_one(dataset, tmp / f"one{i}", "1"))
            three_s.append(run_three(dataset, tmp / f"three{i}"))
            names = ("results.mcap", "trajectory.tum", "tags.csv")
            same.append(
                all(
                    (tmp / "one0" / n).read_bytes() == (tmp / f"{layout}{i}" / n).read_bytes()
                    for n in names
                    for layout in ("one", "workers", "three")
                )
            )
        metrics = json.loads((tmp / "one0" / "metrics.json").read_text())
        fastest = min(range(args.repeats), key=lambda i: one_s[i])
        profile = json.loads((tmp / f"one{fastest}" / "run.json").read_text())["profile"]
    figures = {
        "data_s": data_s,
        "workers": workers_count(),
        "workers_s": workers_s,
        "one_process_s": one_s,
        "three_hosts_s": three_s,
        "realtime_factor_workers": [data_s / t for t in workers_s],
        "realtime_factor_one_process": [data_s / t for t in one_s],
        "workers_over_one": [b / a for a, b in zip(one_s, workers_s, strict=True)],
        "realtime_factor_three_hosts": [data_s / t for t in three_s],
        "three_hosts_over_one": [b / a for a, b in zip(one_s, three_s, strict=True)],
        "identical_outputs": all(same),
        "robot_mean_m": metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "los_tags_mean_m": metrics["los_tags_mean_m"],
        "nlos_tags_mean_m": metrics["nlos_tags_mean_m"],
        "profile": profile,
    }

    def span(values: list[float], fmt: str) -> str:
        return f"{min(values):{fmt}}-{max(values):{fmt}}" if len(values) > 1 else f"{values[0]:{fmt}}"

    print(
        f"paper run ({data_s:.0f} s of data), {args.repeats} repeats: {figures['workers']} workers "
        f"{span(workers_s, '.1f')} s ({span(figures['realtime_factor_workers'], '.1f')}x real time; "
        f"{span(figures['workers_over_one'], '.2f')} of one process), one process {span(one_s, '.1f')} s "
        f"({span(figures['realtime_factor_one_process'], '.1f')}x real time), three hosts on loopback "
        f"{span(three_s, '.1f')} s ({span(figures['realtime_factor_three_hosts'], '.1f')}x; "
        f"{span(figures['three_hosts_over_one'], '.2f')} of one process); results.mcap, trajectory.tum and "
        f"tags.csv identical in every run: {all(same)}"
    )
    print(
        f"errors: robot mean {figures['robot_mean_m'] * 100:.1f} cm, "
        f"LOS tags {figures['los_tags_mean_m'] * 100:.1f} cm, NLOS tag {figures['nlos_tags_mean_m'] * 100:.1f} cm"
    )
    print_profile(profile, one_s[fastest])
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


PARTS = ("decode", "handler", "encode", "send", "runtime", "idle", "close", "cpu")


def print_profile(profile: dict[str, dict[str, float]], run_s: float) -> None:
    """Where the one-process run's time went, per operator thread (run.json's `profile`)."""
    print(f"where the fastest one-process run's {run_s:.1f} s went (wall-clock s per operator thread; they overlap)")
    print(f"{'operator':<16}" + "".join(f"{p:>9}" for p in PARTS))
    rows = sorted(profile.items(), key=lambda kv: -kv[1]["handler_s"])
    for name, parts in rows:
        print(f"{name:<16}" + "".join(f"{parts[f'{p}_s']:>9.2f}" for p in PARTS))
    totals = {p: sum(parts[f"{p}_s"] for parts in profile.values()) for p in PARTS}
    print(f"{'all':<16}" + "".join(f"{totals[p]:>9.2f}" for p in PARTS))


if __name__ == "__main__":
    sys.exit(main())
