"""Robustness of the whole: the `paper` scenario with other seeds and two scenarios of our own
(`out_and_back`, a straight leg out and back; `long_hall`, 6 tags in a 16 m hall), each through
the default pipeline and `rover eval`, compared with the `paper` seed-1 run.
Goal (issue 7): every run within 1.5x of the `paper` run's errors."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROVER = [sys.executable, "-m", "rover.cli", "-q"]


def run_case(tmp: Path, scenario: str, seed: int) -> dict:
    dataset = tmp / f"{scenario}-{seed}.mcap"
    subprocess.run([*ROVER, "simulate", "--scenario", scenario, "--seed", str(seed), "-o", str(dataset)], check=True)
    out = tmp / f"run-{scenario}-{seed}"
    subprocess.run([*ROVER, "run", "--dataset", str(dataset), "--output", str(out)], check=True)
    m = json.loads((out / "metrics.json").read_text())
    return {
        "scenario": scenario,
        "seed": seed,
        "robot_mean_m": m["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "robot_aligned_mean_m": m["robot"]["trajectory.tum"]["aligned"]["mean_m"],
        "los_tags_mean_m": m["los_tags_mean_m"],
        "nlos_tags_mean_m": m["nlos_tags_mean_m"],
        "never_localized": [k for k, t in m["tags"].items() if not t["localized"]],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[2, 3, 4, 5, 6])
    ap.add_argument("--json")
    args = ap.parse_args()
    cases = [("paper", 1)] + [("paper", s) for s in args.seeds] + [("out_and_back", 1), ("long_hall", 1)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for scenario, seed in cases:
            rows.append(run_case(Path(tmp), scenario, seed))
    base = rows[0]

    def cm(v: float | None) -> str:
        return "-" if v is None else f"{v * 100:.1f} cm"

    print(f"{'case':<18}{'robot':>10}{'aligned':>10}{'LOS tags':>10}{'NLOS':>10}  worst ratio to paper seed 1")
    for r in rows:
        ratios = [
            r[k] / base[k]
            for k in ("robot_mean_m", "los_tags_mean_m", "nlos_tags_mean_m")
            if r[k] is not None and base[k]
        ]
        r["worst_ratio"] = max(ratios) if ratios else None
        missing = f"; never localized: {', '.join(r['never_localized'])}" if r["never_localized"] else ""
        print(
            f"{r['scenario'] + ' ' + str(r['seed']):<18}{cm(r['robot_mean_m']):>10}{cm(r['robot_aligned_mean_m']):>10}"
            f"{cm(r['los_tags_mean_m']):>10}{cm(r['nlos_tags_mean_m']):>10}  {r['worst_ratio']:.2f}x{missing}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
