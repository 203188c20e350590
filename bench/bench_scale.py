"""Cost against scale: the default pipeline's run time against the dataset's length (3, 10 and 30
minutes of the `paper` scenario: 2, 7 and 20 laps) and against the number of tags (4, 8 and 15
along the walls of `long_hall`; 15 is what channel 165's excitation allows, `channel_plan.max_tags`),
so users see how the cost grows. Each case runs in one process (`--workers 1`) and then in the
workers `rover run` chooses for this machine (their outputs are the same: tests/test_workers.py).
Each row: simulated seconds, the wall-clock seconds of each run (`rover run`, outputs and figures
included) and their real-time factors, seconds of run per minute of data, the SLAM's and the AoA's
CPU and the SLAM updates (the one-process run's run.json and timing.json), and the errors."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from importlib import resources
from pathlib import Path

import yaml

from rover.operators.channel_sweep.channel_plan import max_tags

ROVER = [sys.executable, "-m", "rover.cli", "-q"]
PAPER_LAPS = {"3 min": 2, "10 min": 7, "30 min": 20}
"""the paper scenario's laps for each length (a lap is about 90 s)"""
HALL_TAGS = (4, 8, 15)
WALL_GAP_M = 0.3
"""how far the tags sit from the hall's walls"""


def hall_with_tags(count: int, folder: Path) -> Path:
    """`long_hall` with `count` tags spread evenly along its walls (every third NLOS, as two of its
    six are), on channels that conflict with neither the excitation nor each other."""
    text = resources.files("rover.datasets").joinpath("scenarios", "long_hall.yaml").read_text(encoding="utf-8")
    base = yaml.safe_load(text)
    width, depth = base["room"]["size_m"]
    inner_w, inner_d = width - 2 * WALL_GAP_M, depth - 2 * WALL_GAP_M
    perimeter = 2 * (inner_w + inner_d)
    channels = max_tags(base["access_point"]["channel"])[:count]
    tags = []
    for i, channel in enumerate(channels):
        d = (i + 0.5) * perimeter / count
        if d < inner_w:
            x, y = d, 0.0
        elif d < inner_w + inner_d:
            x, y = inner_w, d - inner_w
        elif d < 2 * inner_w + inner_d:
            x, y = inner_w - (d - inner_w - inner_d), inner_d
        else:
            x, y = 0.0, inner_d - (d - 2 * inner_w - inner_d)
        tag = {"id": i + 1, "channel": channel, "position_m": [round(x + WALL_GAP_M, 2), round(y + WALL_GAP_M, 2)]}
        if i % 3 == 2:
            tag["nlos"] = True
        tags.append(tag)
    base["tags"] = tags
    path = folder / f"long_hall_{count}_tags.yaml"
    path.write_text(yaml.safe_dump(base, sort_keys=False))
    return path


def timed_run(dataset: Path, out: Path, workers: list[str]) -> float:
    """Wall-clock seconds of `rover run` on `dataset` (workers from `workers`, else its own choice)."""
    env = {k: v for k, v in os.environ.items() if k != "ROVER_WORKERS"}
    start = time.perf_counter()
    subprocess.run([*ROVER, "run", "--dataset", str(dataset), "--output", str(out), *workers], check=True, env=env)
    return time.perf_counter() - start


def run_case(tmp: Path, name: str, scenario: str, sets: list[str]) -> dict:
    dataset = tmp / f"{name.replace(' ', '_')}.mcap"
    args = [*ROVER, "simulate", "--scenario", scenario, "--seed", "1", "-o", str(dataset)]
    subprocess.run([*args, *(a for s in sets for a in ("--set", s))], check=True)
    info = subprocess.run([*ROVER, "info", str(dataset), "--json"], capture_output=True, text=True, check=True)
    data_s = float(json.loads(info.stdout)["duration_s"])
    out = tmp / f"run-{name.replace(' ', '_')}"
    run_s = timed_run(dataset, out, ["--workers", "1"])
    workers_s = timed_run(dataset, tmp / f"workers-{name.replace(' ', '_')}", [])
    metrics = json.loads((out / "metrics.json").read_text())
    profile = json.loads((out / "run.json").read_text())["profile"]
    updates = json.loads((out / "timing.json").read_text())["slam.update"]
    dataset.unlink()
    return {
        "case": name,
        "data_s": data_s,
        "run_s": run_s,
        "realtime_factor": data_s / run_s,
        "run_s_per_data_min": run_s / (data_s / 60),
        "workers_run_s": workers_s,
        "workers_realtime_factor": data_s / workers_s,
        "slam_cpu_s": profile["slam"]["cpu_s"],
        "aoa_cpu_s": profile["aoa"]["cpu_s"],
        "slam_updates": updates["count"],
        "slam_update_median_ms": updates["median_s"] * 1e3,
        "robot_mean_m": metrics["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "los_tags_mean_m": metrics["los_tags_mean_m"],
        "tags_localized": sum(t["localized"] for t in metrics["tags"].values()),
        "tags": len(metrics["tags"]),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for name, laps in PAPER_LAPS.items():
            rows.append(run_case(tmp, f"paper {name}", "paper", [f"trajectory.laps={laps}"]))
        for count in HALL_TAGS:
            rows.append(run_case(tmp, f"long_hall {count} tags", str(hall_with_tags(count, tmp)), []))
    print(
        f"{'case':<20}{'data':>8}{'run':>8}{'x real':>8}{'s/min':>7}{'workers':>9}{'x real':>8}"
        f"{'SLAM cpu':>10}{'AoA cpu':>9}"
        f"{'updates':>9}{'median':>8}{'robot':>8}{'LOS':>7}  tags"
    )
    for r in rows:
        print(
            f"{r['case']:<20}{r['data_s']:>7.0f}s{r['run_s']:>7.1f}s{r['realtime_factor']:>7.1f}x"
            f"{r['run_s_per_data_min']:>7.1f}{r['workers_run_s']:>8.1f}s{r['workers_realtime_factor']:>7.1f}x"
            f"{r['slam_cpu_s']:>9.1f}s{r['aoa_cpu_s']:>8.1f}s{r['slam_updates']:>9,}"
            f"{r['slam_update_median_ms']:>6.1f}ms{r['robot_mean_m'] * 100:>6.1f}cm{r['los_tags_mean_m'] * 100:>5.1f}cm"
            f"  {r['tags_localized']}/{r['tags']} localized"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
