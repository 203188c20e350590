"""The SLAM from another front end's bearings against the same run through CSI (issue 44's
"bearings from elsewhere"): `paper` seeds 1-6 with the chains on their calibration; the default
pipeline runs through CSI, then pipelines/bearings.yaml runs from a CSV of every burst's no-jump
angle and std (what a front end without chain phase jumps gives), with the same IMU and odometry.
Per seed: robot, LOS and NLOS tag errors of both, their ratios, tags localized, and the share of
published estimates beyond 3 sigma. Goal: the bearings run within 1.1x of the CSI run."""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from rover.messages import deserialize

ROVER = [sys.executable, "-m", "rover.cli", "-q"]
ROOT = Path(__file__).resolve().parent.parent
CALIBRATED = ["--set", "receiver.jumps_per_run=false"]


def bearings_csv(results: Path, out: Path) -> int:
    """Write the run's AoAs (each burst's no-jump angle and std) as a bearings CSV; how many."""
    rows = []
    with results.open("rb") as f:
        for _schema, _channel, message in make_reader(f).iter_messages(topics=["/rover/aoa"]):
            a = deserialize(message.data, "rover_msgs/msg/Aoa")
            t = a.header.stamp.sec + a.header.stamp.nanosec * 1e-9
            rows.append(f"{t:.9f},{a.tag_id},{math.degrees(a.angle_rad):.9f},{math.degrees(a.std_rad):.9f}\n")
    out.write_text("time_s,tag,angle_deg,std_deg\n" + "".join(rows))
    return len(rows)


def figures(out: Path) -> dict[str, Any]:
    m = json.loads((out / "metrics.json").read_text())
    tags = m.get("tags", {})
    published = m.get("published", {})
    return {
        "robot_mean_m": m["robot"]["trajectory.tum"]["unaligned"]["mean_m"],
        "los_tags_mean_m": m.get("los_tags_mean_m"),
        "nlos_tag_m": m.get("nlos_tags_mean_m"),
        "localized": sorted(int(i) for i, t in tags.items() if t.get("localized")),
        "beyond_3_sigma": max((p.get("beyond_3_sigma") or 0.0) for p in published.values()) if published else None,
    }


def run(seed: int, work: Path) -> dict[str, Any]:
    dataset = work / f"paper-{seed}.mcap"
    subprocess.run([*ROVER, "simulate", "--seed", str(seed), *CALIBRATED, "-o", str(dataset)], check=True)
    csi, from_bearings, csv = work / f"csi-{seed}", work / f"bearings-{seed}", work / f"bearings-{seed}.csv"
    subprocess.run([*ROVER, "run", "--dataset", str(dataset), "--output", str(csi)], check=True)
    count = bearings_csv(csi / "results.mcap", csv)
    bearings_yaml = ROOT / "pipelines" / "bearings.yaml"
    subprocess.run(
        [*ROVER, "run", str(bearings_yaml), "--dataset", str(dataset), "--set", f"bearings={csv}", "--output",
         str(from_bearings)],
        check=True,
    )  # fmt: skip
    a, b = figures(csi), figures(from_bearings)
    out: dict[str, Any] = {"bearings": count, "csi": a, "from_bearings": b}
    for key in ("robot_mean_m", "los_tags_mean_m", "nlos_tag_m"):
        out[f"{key.removesuffix('_m')}_ratio"] = b[key] / a[key] if a[key] and b[key] else None
    out["same_tags_localized"] = set(b["localized"]) >= set(a["localized"])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--json", type=Path, help="also write the figures here")
    args = ap.parse_args()
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            results[f"seed{seed}"] = run(seed, Path(tmp))
    print(f"{'seed':<8}{'robot cm csi/bearings':>24}{'LOS cm':>16}{'NLOS cm':>16}  ratios robot/LOS/NLOS  tags")
    for key, r in results.items():
        a, b = r["csi"], r["from_bearings"]

        def pair(k: str, a=a, b=b) -> str:
            return "/".join("-" if v is None else f"{v * 100:.1f}" for v in (a[k], b[k]))

        ratios = "/".join(
            "-" if r[k] is None else f"{r[k]:.2f}"
            for k in ("robot_mean_ratio", "los_tags_mean_ratio", "nlos_tag_ratio")
        )
        tags = f"{','.join(map(str, a['localized']))} / {','.join(map(str, b['localized']))}"
        print(
            f"{key:<8}{pair('robot_mean_m'):>24}{pair('los_tags_mean_m'):>16}{pair('nlos_tag_m'):>16}"
            f"  {ratios:<21}  {tags}"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
