"""The whole default pipeline on the simulated `paper` run: real-time factor in one process and with
the three-host layout on loopback (three processes), the run's errors, and where the one-process
run's time went per operator (run.json's `profile`: decoding, handler, encoding, sending, the
runtime's share, waiting for input, closing, and the thread's CPU time).
Goals (issue 7): >= 20x faster than real time; three hosts within 20% of one process."""

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


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        dataset = tmp / "paper.mcap"
        subprocess.run(
            [*ROVER, "simulate", "--scenario", "paper", "--seed", str(args.seed), "-o", str(dataset)], check=True
        )
        data_s = duration_s(dataset)
        start = time.perf_counter()
        subprocess.run([*ROVER, "run", "--dataset", str(dataset), "--output", str(tmp / "one")], check=True)
        one_s = time.perf_counter() - start
        port = free_port()
        start = time.perf_counter()
        procs = [
            subprocess.Popen(
                [
                    *ROVER,
                    "run",
                    "--host",
                    host,
                    "--dataset",
                    str(dataset),
                    "--output",
                    str(tmp / "three"),
                    "--set",
                    f"port={port}",
                ]
            )
            for host in ("laptop", "base", "nuc")
        ]
        codes = [p.wait() for p in procs]
        three_s = time.perf_counter() - start
        if any(codes):
            raise SystemExit(f"three-host run failed: exit codes {codes}")
        metrics = json.loads((tmp / "one" / "metrics.json").read_text())
        profile = json.loads((tmp / "one" / "run.json").read_text())["profile"]
        same = all(
            (tmp / "one" / n).read_bytes() == (tmp / "three" / n).read_bytes() for n in ("trajectory.tum", "tags.csv")
        )
    figures = {
        "data_s": data_s,
        "one_process_s": one_s,
        "three_hosts_s": three_s,
        "realtime_factor_one_process": data_s / one_s,
        "realtime_factor_three_hosts": data_s / three_s,
        "three_hosts_over_one": three_s / one_s,
        "identical_outputs": same,
        "robot_mean_m": metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "los_tags_mean_m": metrics["los_tags_mean_m"],
        "nlos_tags_mean_m": metrics["nlos_tags_mean_m"],
        "profile": profile,
    }
    print(
        f"paper run ({data_s:.0f} s of data): one process {one_s:.1f} s ({data_s / one_s:.1f}x real time), "
        f"three hosts on loopback {three_s:.1f} s ({data_s / three_s:.1f}x; {three_s / one_s:.2f} of one process); "
        f"trajectory.tum and tags.csv identical: {same}"
    )
    print(
        f"errors: robot mean {figures['robot_mean_m'] * 100:.1f} cm, "
        f"LOS tags {figures['los_tags_mean_m'] * 100:.1f} cm, NLOS tag {figures['nlos_tags_mean_m'] * 100:.1f} cm"
    )
    print_profile(profile, one_s)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


PARTS = ("decode", "handler", "encode", "send", "runtime", "idle", "close", "cpu")


def print_profile(profile: dict[str, dict[str, float]], run_s: float) -> None:
    """Where the one-process run's time went, per operator thread (run.json's `profile`)."""
    print(f"where the one-process run's {run_s:.1f} s went (wall-clock s per operator thread; threads overlap)")
    print(f"{'operator':<16}" + "".join(f"{p:>9}" for p in PARTS))
    rows = sorted(profile.items(), key=lambda kv: -kv[1]["handler_s"])
    for name, parts in rows:
        print(f"{name:<16}" + "".join(f"{parts[f'{p}_s']:>9.2f}" for p in PARTS))
    totals = {p: sum(parts[f"{p}_s"] for parts in profile.values()) for p in PARTS}
    print(f"{'all':<16}" + "".join(f"{totals[p]:>9.2f}" for p in PARTS))


if __name__ == "__main__":
    sys.exit(main())
