"""Phase calibration on the 50 real LGTM captures (../shared/data/csi/lgtm/): a transmitter 1 m from a
laptop's 3-antenna NIC at 0, +-10 and +-20 degrees, ten repeats each, channel 64, calibrated with
the labelled angle and LGTM's stated array (a 0.10 m linear array; robot frame: antennas at y = 0,
-0.1, -0.2 m, so a positive angle puts antenna 1 nearest).

Per labelled angle: the reduced offsets (modulo pi) of the repeats, their mean and spread across
the repeats; per repeat the within-capture spread and the jumps relative to repeat 1 (a digit
per chain: 1 = shifted by pi) with the residual left once they are removed. Then how the per-angle means agree with
each other, and the calibration's speed. Figures are measured, nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from rover.formats.intel5300 import read_dat
from rover.operators.aoa.calibration import Calibration, compare, estimate_offsets

ROOT = Path(__file__).resolve().parents[1]
ULA = np.array([[0.0, 0.0], [0.0, -0.1], [0.0, -0.2]])
CHANNEL = 64
ANGLES_DEG = (-20, -10, 0, 10, 20)
REPEATS = range(1, 11)


def capture(folder: Path, angle_deg: int, test: int) -> Path:
    label = f"neg-{-angle_deg}" if angle_deg < 0 else str(angle_deg)
    return folder / f"lgtm-monitor.dat--1m-{label}-degrees--laptop-1--test-{test}.dat"


def mean_and_spread_modulo(values_rad: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Circular mean and standard deviation (deg) over axis 0 of angles known modulo `step`."""
    z = np.exp(1j * values_rad * 2 * math.pi / step).mean(axis=0)
    scale = step / (2 * math.pi)
    spread = np.sqrt(np.maximum(-2 * np.log(np.clip(np.abs(z), 1e-300, 1.0)), 0.0)) * scale
    return np.degrees(np.angle(z) * scale), np.degrees(spread) + 0.0


def degrees(values: np.ndarray, digits: int = 1) -> str:
    return " ".join(f"{v:7.{digits}f}" for v in values)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", help="write the figures here (bench/run_all.py)")
    args = ap.parse_args()
    data_dir = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data"))
    folder = data_dir / "csi" / "lgtm"
    if not folder.is_dir():
        sys.exit(
            f"reference data not found at {data_dir}: it is the shared/data folder beside this repository "
            "(set ROVER_TEST_DATA to point at it)"
        )
    figures: dict[str, object] = {}
    means, packets, seconds = [], 0, 0.0
    for angle in ANGLES_DEG:
        cals: list[Calibration] = []
        for test in REPEATS:
            records = read_dat(capture(folder, angle, test))
            start = time.perf_counter()
            cals.append(estimate_offsets(records.csi[:, :, :3, 0], ULA, CHANNEL, math.radians(angle)))
            seconds += time.perf_counter() - start
            packets += cals[-1].packets + cals[-1].outliers
        step = cals[0].jump_step_rad
        mean, spread = mean_and_spread_modulo(np.array([c.reduced_rad for c in cals]), step)
        means.append(np.radians(mean))
        print(
            f"{angle:+d} deg: reduced offsets (chains 1-3, modulo 180 deg) mean {degrees(mean)}, "
            f"spread across repeats {degrees(spread, 2)}"
        )
        print(
            "  test  packets  outliers  capture spread (deg)     reduced (deg)            "
            "jumps vs test 1  residual (deg)"
        )
        rows = []
        for test, c in zip(REPEATS, cals, strict=True):
            jumps = compare(c, cals[0])
            shifted = "".join(str(int(n)) for n in jumps.multiples)
            print(
                f"  {test:4d}  {c.packets:7d}  {c.outliers:8d}  {degrees(c.spread_deg, 2)}  "
                f"{degrees(np.degrees(c.reduced_rad))}"
                f"  {shifted:>15}  {degrees(np.degrees(jumps.residual_rad), 2)}"
            )
            rows.append(
                {
                    "test": test,
                    "packets": c.packets,
                    "outliers": c.outliers,
                    "capture_spread_deg": np.round(c.spread_deg, 3).tolist(),
                    "reduced_deg": np.round(np.degrees(c.reduced_rad), 3).tolist(),
                    "jumps_vs_test_1": jumps.multiples.tolist(),
                    "residual_deg": np.round(np.degrees(jumps.residual_rad), 3).tolist(),
                }
            )
        figures[f"angle_{angle}"] = {
            "reduced_mean_deg": np.round(mean, 3).tolist(),
            "spread_across_repeats_deg": np.round(spread, 3).tolist(),
            "repeats_with_a_jump": sum(1 for r in rows[1:] if any(r["jumps_vs_test_1"])),
            "repeats": rows,
        }
    _, across = mean_and_spread_modulo(np.array(means), math.pi)
    print(f"across the labelled angles: spread of the per-angle means {degrees(across, 2)} deg (modulo 180 deg)")
    rate = packets / seconds
    print(f"speed: {rate:,.0f} packets/s ({packets:,} packets, decoding excluded)")
    figures["spread_across_angles_deg"] = np.round(across, 3).tolist()
    figures["packets_s"] = round(rate)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
