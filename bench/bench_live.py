"""The live robot without hardware: `pipelines/live.yaml` on three hosts (network namespaces) for
60 s of real time, with an emulated 3DM-GX4-45 and Create 2 on ptys and a CSI Tool log that grows
as `channel_hop` tunes the emulated NIC (tests/live_session.py), recorded on the NUC with
`rover record` and replayed in one process.

Prints how far the estimate trails the robot: for each AoA (computed on the NUC) and each pose
(solved on the laptop), its arrival at an observer on the laptop's machine minus its stamp (the
host time the CSI burst behind it was received; one kernel clock for all namespaces), as
p50/p99/max; the rates the recording got; what came late; and whether the replay of the recording
gives the live trajectory. Needs root (network namespaces); without it, says so and records nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

import yaml  # noqa: E402
from live_session import live_scenario, observe, read_arrivals, run_session  # noqa: E402
from netns import Lab  # noqa: E402

from rover.formats.bag import BagReader  # noqa: E402

LIVE_S = 60.0
SEED = 1


def percentiles(values: list[float]) -> dict[str, float]:
    ordered = sorted(values)
    return {
        "p50_ms": 1e3 * statistics.median(ordered),
        "p99_ms": 1e3 * ordered[min(len(ordered) - 1, int(0.99 * len(ordered)))],
        "max_ms": 1e3 * ordered[-1],
        "count": len(ordered),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--seconds", type=float, default=LIVE_S)
    args = ap.parse_args()
    if os.geteuid() != 0:
        print("bench_live: needs root (network namespaces); nothing measured")
        if args.json:
            Path(args.json).write_text("{}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        scenario = live_scenario(work)
        dataset = work / "live.mcap"
        simulate = [sys.executable, "-m", "rover.cli", "-q", "simulate", "--scenario", str(scenario)]
        subprocess.run([*simulate, "--seed", str(SEED), "-o", str(dataset)], check=True)
        arrivals = work / "arrivals.txt"

        def watch(lab: Lab, _pipeline: Path) -> None:
            observe(lab, arrivals)

        session = run_session(work, dataset, args.seconds, during=watch)
        statuses = {host: status for host, (status, _err) in session.ended.items()}
        latency: dict[str, list[float]] = {"aoa": [], "pose": []}
        for key, arrived, stamp in read_arrivals(arrivals):
            latency["aoa" if key.endswith("/aoa") else "pose"].append((arrived - stamp) / 1e9)
        with BagReader(session.recording) as bag:
            summary = bag.summary()
            record = yaml.safe_load(bag.metadata()["rover.record"]["yaml"])
        assert summary is not None and summary.statistics is not None
        duration_s = (summary.statistics.end_ns - summary.statistics.start_ns) / 1e9
        rates = {c.topic: c.count / duration_s for c in summary.channels} if duration_s else {}
        replay = work / "replay"
        rerun = ["run", "--dataset", str(session.recording), "--output", str(replay)]
        done = subprocess.run([sys.executable, "-m", "rover.cli", "-q", *rerun], capture_output=True, text=True)
        same = (
            done.returncode == 0
            and (replay / "trajectory.tum").read_bytes() == (session.output / "trajectory.tum").read_bytes()
        )
    figures = {
        "live_s": args.seconds,
        "exit_status": statuses,
        "aoa_latency": percentiles(latency["aoa"]) if latency["aoa"] else {},
        "pose_latency": percentiles(latency["pose"]) if latency["pose"] else {},
        "recorded_hz": rates,
        "late": record["late"],
        "replay_equals_live": same,
    }
    print(f"live session: {args.seconds:g} s on three hosts; exit status {statuses}")
    for name in ("aoa", "pose"):
        f = figures[f"{name}_latency"]
        if f:
            print(
                f"{name:>4} latency (stamp -> observer): p50 {f['p50_ms']:.1f} ms, p99 {f['p99_ms']:.1f} ms,"
                f" max {f['max_ms']:.1f} ms over {f['count']}"
            )
    print("recorded: " + ", ".join(f"{topic} {hz:.1f} Hz" for topic, hz in sorted(rates.items())))
    print(f"late messages: {record['late'] or 'none'}; replay equals the live trajectory: {same}")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
