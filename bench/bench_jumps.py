"""The real NIC's chain phase jumps: the default pipeline on simulated `paper` runs whose chains hold
their calibration (`none`), are off it by a random multiple of pi per channel for the whole run
(`once`, the scenario's default), draw a new multiple at every retune (`retune`), or step by pi at
random moments and stay so, 1 or 3 times a minute (`steps1`, `steps3`), and, with the jump per run,
in a cluttered room whose bearings have heavy, persistent errors (`clutter`: 10 scatterers, the
direct path shadowed by 4 dB; docs/datasets.md), and the same room with one bearing per burst
(`bearings`: chains on their calibration, `aoa.jumps=false`: what another AoA source, or a replay of
real bearings, gives the SLAM, no tag search), same seeds: `paper` seeds 1-6 and `long_hall`
seed 1 (`--seeds 1 2 --hall-seeds` for a quick subset). Per tag: the seconds from its first AoA to
its first localization, to when the geometry first allowed it (`rover eval`'s `geometry_after_s`:
views spanning 30 deg, from its true place along the true path) and the parallax it had been seen
over by then; per seed, the robot from
its odometry alone (`slam.bearings=false`), and each run's robot error over it. Goals
(bench/goals.yaml): tags as good as without jumps, every tag heard localized within 20 s of its
first AoA, and no more than 1% of the published localized estimates beyond 3 sigma of their own
covariance."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

ROVER = [sys.executable, "-m", "rover.cli", "-q"]
CLUTTER = ["--set", "room.scatterers=10", "--set", "room.shadowing_db=4"]
REGIMES = {
    "none": ["--set", "receiver.jumps_per_run=false"],
    "once": [],
    "retune": ["--set", "receiver.jumps_per_retune=1.0"],
    "steps1": ["--set", "receiver.steps_per_minute=1"],
    "steps3": ["--set", "receiver.steps_per_minute=3"],
    "clutter": CLUTTER,
    "bearings": [*CLUTTER, "--set", "receiver.jumps_per_run=false"],
}
"""each regime's `rover simulate` arguments"""
RUN_ARGS = {"bearings": ["--set", "aoa.jumps=false"]}
"""a regime's `rover run` arguments: `bearings` gives the SLAM one bearing per burst, as another AoA
source would (a calibrated card, or an array without jumps), with the cluttered room's heavy errors"""


SCENARIOS = {"paper": "seed", "long_hall": "hall"}
"""each scenario's key prefix in the figures: paper's seed 1 with jumps per retune is `seed1_retune`"""


def run(scenario: str, seed: int, regime: str, work: Path) -> dict[str, Any]:
    dataset = work / f"{scenario}-{seed}-{regime}.mcap"
    subprocess.run(
        [*ROVER, "simulate", "--scenario", scenario, "--seed", str(seed), *REGIMES[regime], "-o", str(dataset)],
        check=True,
    )
    out = work / f"run-{scenario}-{seed}-{regime}"
    subprocess.run(
        [*ROVER, "run", "--dataset", str(dataset), "--output", str(out), *RUN_ARGS.get(regime, [])], check=True
    )
    figures = figures_of(json.loads((out / "metrics.json").read_text()))
    if regime == "none":  # the robot from its odometry alone: the same motion and IMU in every regime
        alone = work / f"odometry-{scenario}-{seed}"
        subprocess.run(
            [*ROVER, "run", "--dataset", str(dataset), "--output", str(alone), "--set", "slam.bearings=false"],
            check=True,
        )
        odometry = json.loads((alone / "metrics.json").read_text())
        figures["robot_odometry_alone_m"] = odometry["robot"]["trajectory.tum"]["unaligned"]["mean_m"]
    return figures


def figures_of(m: dict[str, Any]) -> dict[str, Any]:
    """A run's figures from its metrics.json."""
    tags = m.get("tags", {})
    published = m.get("published", {})
    after = [t["localized_after_s"] for t in tags.values() if isinstance(t, dict) and t.get("localized")]
    waited = [t["localized_after_geometry_s"] for t in tags.values() if "localized_after_geometry_s" in t]
    return {
        "robot_mean_m": m["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "los_tags_mean_m": m.get("los_tags_mean_m"),
        "nlos_tag_m": m.get("nlos_tags_mean_m"),
        "localized": sorted(int(i) for i, t in tags.items() if isinstance(t, dict) and t.get("localized")),
        "aoa_los_median_deg": m.get("aoa", {}).get("los", {}).get("median_deg"),
        "aoa_nlos_median_deg": m.get("aoa", {}).get("nlos", {}).get("median_deg"),
        "heard": len(tags),
        "localized_share": sum(1 for t in tags.values() if isinstance(t, dict) and t.get("localized"))
        / max(len(tags), 1),
        "localized_after_s": {
            int(i): t["localized_after_s"] for i, t in tags.items() if isinstance(t, dict) and t.get("localized")
        },
        "localized_after_median_s": float(np.median(after)) if after else None,
        "parallax_at_localization_deg": {
            int(i): t["parallax_at_localization_deg"]
            for i, t in tags.items()
            if isinstance(t, dict) and t.get("localized")
        },
        "localized_after_max_s": max(after, default=None),
        "geometry_after_s": {int(i): t.get("geometry_after_s") for i, t in tags.items() if isinstance(t, dict)},
        "localized_after_geometry_median_s": float(np.median(waited)) if waited else None,
        "los_beyond_3_sigma": published.get("los", {}).get("beyond_3_sigma"),
        "nlos_beyond_3_sigma": published.get("nlos", {}).get("beyond_3_sigma"),
    }


def cm(v: float | None) -> str:
    return "-" if v is None else f"{v * 100:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6], help="paper's seeds")
    ap.add_argument("--hall-seeds", type=int, nargs="*", default=[1], help="long_hall's seeds (none: skip it)")
    ap.add_argument("--regimes", nargs="+", choices=list(REGIMES), default=list(REGIMES))
    ap.add_argument("--json", type=Path, help="also write the figures here")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="runs at once (each takes about a core)")
    args = ap.parse_args()
    runs = [
        (scenario, seed, regime)
        for scenario, seeds in (("paper", args.seeds), ("long_hall", args.hall_seeds))
        for seed in seeds
        for regime in args.regimes
    ]
    with tempfile.TemporaryDirectory() as tmp, ThreadPoolExecutor(args.jobs) as pool:
        done = pool.map(lambda r: run(r[0], r[1], r[2], Path(tmp)), runs)
        figures = {
            f"{SCENARIOS[scenario]}{seed}_{regime}": f for (scenario, seed, regime), f in zip(runs, done, strict=True)
        }
    for key, f in figures.items():
        alone = figures.get(key.split("_")[0] + "_none", {}).get("robot_odometry_alone_m")
        if alone:
            f["robot_over_odometry_alone"] = f["robot_mean_m"] / alone
    print(
        f"{'run':<14}{'robot cm':>10}{'/odometry':>10}{'LOS tags cm':>13}{'NLOS tag cm':>13}"
        "  localized  AoA LOS/NLOS deg  >3 sigma LOS/NLOS  s to localize  geometry s     deg seen over  ratio to none"
    )
    for key, f in figures.items():
        seed, regime = key.split("_")
        base = figures.get(f"{seed}_none", f)
        ratio = " ".join(
            f"{name} {f[k] / base[k]:.2f}x" if f[k] and base[k] else f"{name} -"
            for name, k in (("robot", "robot_mean_m"), ("LOS", "los_tags_mean_m"))
        )
        aoa = f"{f['aoa_los_median_deg'] or float('nan'):.1f}/{f['aoa_nlos_median_deg'] or float('nan'):.1f}"
        after = ",".join(f"{v:.0f}" for _, v in sorted(f["localized_after_s"].items()) if v is not None) or "-"
        seen = ",".join(f"{v:.0f}" for _, v in sorted(f["parallax_at_localization_deg"].items()) if v is not None)
        geometry = ",".join("-" if v is None else f"{v:.0f}" for _, v in sorted(f["geometry_after_s"].items()))
        odometry = f"{f['robot_over_odometry_alone']:.2f}x" if "robot_over_odometry_alone" in f else "-"
        beyond = "/".join("-" if v is None else f"{v:.0%}" for v in (f["los_beyond_3_sigma"], f["nlos_beyond_3_sigma"]))
        print(
            f"{key:<14}{cm(f['robot_mean_m']):>10}{odometry:>10}{cm(f['los_tags_mean_m']):>13}{cm(f['nlos_tag_m']):>13}"
            f"  {','.join(map(str, f['localized'])):<9}  {aoa:<16}  {beyond:<17}  {after:<14} {geometry:<14} "
            f"{seen or '-':<14} "
            f"{ratio if regime != 'none' else ''}"
        )
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
