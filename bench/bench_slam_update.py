"""The SLAM update's cost against the number of tags: the `slam` operator alone (window 30, the
shipped params) re-run three times on the recorded AoAs and preintegrations of `paper` (seed 1, 4
tags) and of `long_hall` with 4, 8 and 15 tags along its walls (bench_scale.hall_with_tags). Each
row: the update's time per epoch (the window's `update`, as the operator's `slam.update` Timing
reports it; in one quiet process it is its CPU) as p50, p90, p99 and max over the repeats' updates,
the range of the repeats' medians, and the operator's whole CPU per epoch (tag searches, outputs
and marginalization included). Goals (issue 41): median <= 2 ms and p99 <= 8 ms with 4 tags."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from bench_scale import hall_with_tags
from bench_slam import front_end, inputs, run_slam, stage_ms

from rover.operators.slam.operator import SlamParams

ROVER = [sys.executable, "-m", "rover.cli", "-q"]
REPEATS = 3
WINDOW_EPOCHS = 30


def case(tmp: Path, name: str, scenario: str) -> dict:
    """Simulate, run the front end once, then the slam operator alone REPEATS times."""
    dataset = tmp / f"{name.replace(' ', '_')}.mcap"
    subprocess.run([*ROVER, "simulate", "--scenario", scenario, "--seed", "1", "-o", str(dataset)], check=True)
    items = inputs(front_end(dataset, tmp / f"front-{name.replace(' ', '_')}"), dataset)
    updates: list[np.ndarray] = []
    cpu_per_epoch_ms: list[float] = []
    tags = 0
    for _ in range(REPEATS):
        out, cpu_s, op, _latency = run_slam(items, SlamParams(window=WINDOW_EPOCHS))
        ms = stage_ms(out, "slam.update")
        updates.append(ms)
        cpu_per_epoch_ms.append(1e3 * cpu_s / max(len(ms), 1))
        tags = len(op.window.tag_ids)
    every = np.concatenate(updates)
    p50, p90, p99 = np.percentile(every, [50, 90, 99])
    medians = [float(np.median(u)) for u in updates]
    return {
        "case": name,
        "tags": tags,
        "updates": len(updates[0]),
        "p50_ms": float(p50),
        "p90_ms": float(p90),
        "p99_ms": float(p99),
        "max_ms": float(every.max()),
        "median_range_ms": [min(medians), max(medians)],
        "cpu_per_epoch_ms": float(np.median(cpu_per_epoch_ms)),
        "cpu_per_epoch_range_ms": [min(cpu_per_epoch_ms), max(cpu_per_epoch_ms)],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        rows.append(case(tmp, "paper 4 tags", "paper"))
        for count in (4, 8, 15):
            rows.append(case(tmp, f"long_hall {count} tags", str(hall_with_tags(count, tmp))))
    print(f"{'case':<20}{'tags':>5}{'updates':>9}{'p50':>8}{'p90':>8}{'p99':>8}{'max':>8}  medians      CPU/epoch")
    for r in rows:
        low, high = r["median_range_ms"]
        cpu_low, cpu_high = r["cpu_per_epoch_range_ms"]
        print(
            f"{r['case']:<20}{r['tags']:>5}{r['updates']:>9,}{r['p50_ms']:>6.2f}ms{r['p90_ms']:>6.2f}ms"
            f"{r['p99_ms']:>6.2f}ms{r['max_ms']:>6.1f}ms  {low:.2f}-{high:.2f} ms  {cpu_low:.2f}-{cpu_high:.2f} ms"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
