"""CSI Tool decoding speed: `read_dat` on a log of at least 50,000 real Nrx 3 x Ntx 1 records.

The log, written to a temporary directory, repeats the Ntx = 1 records of the CSI Tool's own
sample capture (log.all_csi.6.7.6: Nrx 3, Ntx 1, two antenna permutations). The figure is the
median over repeats of whole-file decoding, reading the file included. Goal (the project's
issue): at least csiread's ~340,000 records/s scaled. A second log repeating sample_0x1_ap.dat
(3 x 2 records) shows the cost of the larger records.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from rover.formats.intel5300 import read_dat

ROOT = Path(__file__).resolve().parents[1]
GOAL_RECORDS_S = 340_000


def records_of(log: Path, nrx: int, ntx: int) -> list[bytes]:
    """The log's beamforming records of one shape, each with its length prefix."""
    data, out, pos = log.read_bytes(), [], 0
    while pos + 2 <= len(data):
        (length,) = struct.unpack_from(">H", data, pos)
        record = data[pos : pos + 2 + length]
        if record[2] == 0xBB and (record[3 + 8], record[3 + 9]) == (nrx, ntx):
            out.append(record)
        pos += 2 + length
    return out


def median_rate(path: Path, count: int, scaled: bool, repeats: int) -> float:
    """Records per second of read_dat(path), median over `repeats` runs."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = read_dat(path, scaled=scaled)
        times.append(time.perf_counter() - start)
        if len(out) != count or out.n_corrupt or out.n_garbage_bytes:
            raise SystemExit(f"decoded {len(out)} of {count} records ({out.n_corrupt} corrupt)")
    return count / float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--records", type=int, default=50_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", help="write the figures here (bench/run_all.py)")
    args = ap.parse_args()
    data_dir = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data"))
    if not (data_dir / "csi").is_dir():
        sys.exit(
            f"reference data not found at {data_dir}: it is the shared/data folder beside this repository "
            "(set ROVER_TEST_DATA to point at it)"
        )
    logs = {
        "3x1": records_of(data_dir / "csi" / "log.all_csi.6.7.6.dat", 3, 1),
        "3x2": records_of(data_dir / "csi" / "sample_0x1_ap.dat", 3, 2),
    }
    figures: dict[str, float | int] = {"records": args.records}
    with tempfile.TemporaryDirectory() as tmp:
        for shape, records in logs.items():
            path = Path(tmp) / f"{shape}.dat"
            path.write_bytes(b"".join(records[i % len(records)] for i in range(args.records)))
            for scaled in (True, False):
                rate = median_rate(path, args.records, scaled, args.repeats)
                kind = "scaled" if scaled else "raw"
                figures[f"{kind}_records_s" if shape == "3x1" else f"{shape}_{kind}_records_s"] = rate
                print(
                    f"decode: {rate:,.0f} records/s ({kind}; {args.records:,} {shape} records, "
                    f"{path.stat().st_size / 1e6:.1f} MB, median of {args.repeats})"
                )
    verdict = "meets" if figures["scaled_records_s"] >= GOAL_RECORDS_S else "MISSES"
    print(f"3x1 scaled {verdict} the goal of {GOAL_RECORDS_S:,} records/s")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
