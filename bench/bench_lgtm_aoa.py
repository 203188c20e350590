"""`rover aoa` on the 50 real LGTM captures (a transmitter 1 m from a laptop's 3-antenna ULA, 0.10 m
spacing, at labelled angles), beside LGTM's own top AoAs where its MATLAB output covers the capture
(shown as given). Uncalibrated: the chains' offsets, and their pi jumps between repeats, are unknown,
so every jump combination's candidate is listed; the 0.10 m spacing also aliases each of them
(20 deg looks like -12.8, -51.7 and 64.9 deg), which no estimator on this array can undo."""

from __future__ import annotations

import argparse
import json
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from rover.formats.intel5300 import read_dat
from rover.formats.rig import rig_from_text
from rover.operators.aoa.bare_log import log_bursts

ROOT = Path(os.environ.get("ROVER_TEST_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
LGTM = ROOT / "csi" / "lgtm"
RIG = "receiver:\n  antenna_positions_m: [[0, 0], [0, -0.1], [0, -0.2]]\n  channel: 64\n"
NAME = re.compile(r"--1m-(neg-)?(\d+)-degrees--laptop-1--test-(\d+)\.dat$")


def lgtm_outputs(folder: Path) -> dict[str, list[float]]:
    """LGTM's top AoAs per capture name, from its MATLAB logs."""
    found: dict[str, list[float]] = {}
    for path in sorted(folder.glob("*.out")):
        name: str | None = None
        values: list[float] = []
        reading = False
        for line in path.read_text(errors="replace").splitlines():
            text = line.strip()
            if text.startswith("Running on data file:"):
                name, values, reading = text.split(":", 1)[1].strip(), [], False
            elif text.startswith("output_top_aoas ="):
                reading = True
            elif reading and re.fullmatch(r"-?\d+(\.\d+)?", text):
                values.append(float(text))
            elif reading and values:
                if name:
                    found[name] = values
                reading = False
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if not LGTM.is_dir():
        print(f"no LGTM captures at {LGTM} (set ROVER_TEST_DATA; ../shared/data/README.md says where they come from)")
        return
    rig = rig_from_text(RIG, "LGTM rig")
    theirs = lgtm_outputs(LGTM / "outputs")
    rows: list[dict[str, Any]] = []
    for path in sorted(LGTM.glob("*.dat")):
        match = NAME.search(path.name)
        if not match:
            continue
        label = (-1 if match.group(1) else 1) * int(match.group(2))
        records = read_dat(path)
        burst = log_bursts(records, rig, 64, len(records.nrx))[0]
        rows.append(
            {
                "label_deg": label,
                "test": int(match.group(3)),
                "no_jump_deg": math.degrees(burst.angle_rad),
                "candidates_deg": [round(math.degrees(a), 1) for a in burst.candidate_angles_rad],
                "lgtm_top_deg": theirs.get(path.name.removesuffix(".dat")),
            }
        )
    rows.sort(key=lambda r: (r["label_deg"], r["test"]))
    print(f"{'label':>6} {'test':>4}  {'Rover candidates deg (no-jump first)':<38} LGTM's top AoAs deg (as given)")
    for r in rows:
        cands = " ".join(f"{c:6.1f}" for c in r["candidates_deg"])
        lgtm = "-" if r["lgtm_top_deg"] is None else " ".join(f"{v:.1f}" for v in r["lgtm_top_deg"])
        print(f"{r['label_deg']:>6} {r['test']:>4}  {cands:<38} {lgtm}")
    near = [min(abs(c - r["label_deg"]) for c in r["candidates_deg"]) for r in rows if r["candidates_deg"]]
    print(
        f"{len(rows)} captures, all decoded; a candidate within 10 deg of the label in "
        f"{np.mean(np.array(near) <= 10):.0%} of them (uncalibrated; aliases not counted)"
    )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
