"""CSI Tool decoding speed: `read_dat(..., scaled=True)` on a log of at least 50,000 real 3x1 records.

The log repeats the Ntx = 1 records of the CSI Tool's own sample capture (Nrx 3, Ntx 1).
Goal (issue 3): at least csiread's ~340,000 records/s on these 2-core machines.
"""

from __future__ import annotations

import argparse
import json
import struct
import tempfile
import time
from pathlib import Path

import numpy as np

from rover.drivers.intel5300 import read_dat

ROOT = Path(__file__).resolve().parents[1]


def one_by_three_records(source: Path) -> list[bytes]:
    data, out, pos = source.read_bytes(), [], 0
    while pos + 2 <= len(data):
        (n,) = struct.unpack_from(">H", data, pos)
        record = data[pos:pos + 2 + n]
        if record[2] == 0xBB and record[3 + 8] == 3 and record[3 + 9] == 1:
            out.append(record)
        pos += 2 + n
    return out


def main() -> None:
    import os

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--records", type=int, default=50_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json")
    args = ap.parse_args()
    data_dir = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data"))
    records = one_by_three_records(data_dir / "csi" / "log.all_csi.6.7.6.dat")
    blob = b"".join(records[i % len(records)] for i in range(args.records))
    figures = {"records": args.records}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.dat"
        path.write_bytes(blob)
        for scaled in (True, False):
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                out = read_dat(path, scaled=scaled)
                times.append(time.perf_counter() - start)
            assert len(out) == args.records
            rate = args.records / float(np.median(times))
            figures["scaled_records_s" if scaled else "raw_records_s"] = rate
            print(f"decode: {rate:,.0f} records/s ({'scaled' if scaled else 'raw'}, {args.records:,} 3x1 records, "
                  f"median of {args.repeats}; goal >= 340,000 scaled)")
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
