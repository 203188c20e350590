"""CSI Tool decoding speed, side by side with csiread, on every kind of real log.

Kinds (each a log of at least 50,000 beamforming records, written to a temporary directory by
repeating real records of ../shared/data/csi/ in their order):
  3x1     the Nrx 3 x Ntx 1 records of the CSI Tool's sample log.all_csi.6.7.6 (pure 0xBB);
  3x2     sample_0x1_ap.dat (pure 0xBB, the larger records);
  mixed   an LGTM capture (lgtm/), whose 0xBB records alternate with 0xC1 records.
And the real files as they are: the 50 LGTM captures (1,025 records each) and the two samples.

Each figure is the median over repeats of whole-file decoding, reading the file included:
`read_dat` scaled (as get_scaled_csi) and raw, `StreamDecoder` fed 64 KiB chunks (scaled), and
csiread's `Intel(...).read()` (raw) plus `get_scaled_csi()` (scaled), timed in turn within each
repeat so load on the machine falls on both alike. The project's goal (issue 19): read_dat at
least as fast as csiread on every kind, scaled and raw.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from rover.formats.intel5300 import StreamDecoder, read_dat

ROOT = Path(__file__).resolve().parents[1]
CHUNK_BYTES = 64 * 1024
"""what a growing log or a socket hands the stream decoder at a time"""

try:
    import csiread  # type: ignore[import-untyped,import-not-found,unused-ignore]
except ImportError:  # an optional bench dependency: `make bench` installs it
    csiread = None


def records_of(log: Path) -> list[bytes]:
    """The log's records, each with its length prefix (a naive framing: the logs are intact)."""
    data, out, pos = log.read_bytes(), [], 0
    while pos + 2 <= len(data):
        (length,) = struct.unpack_from(">H", data, pos)
        out.append(data[pos : pos + 2 + length])
        pos += 2 + length
    return out


def repeated(records: list[bytes], bfee_count: int) -> bytes:
    """Whole passes over `records`, in order, until `bfee_count` beamforming records are in."""
    per_pass = sum(r[2] == 0xBB for r in records)
    return b"".join(records * -(-bfee_count // per_pass))


def streamed(path: Path) -> int:
    dec = StreamDecoder(scaled=True)
    n = 0
    with path.open("rb") as f:
        while chunk := f.read(CHUNK_BYTES):
            n += len(dec.feed(chunk))
    return n + len(dec.close())


def csiread_read(path: Path, scaled: bool) -> int:
    assert csiread is not None
    log = csiread.Intel(str(path), nrxnum=3, ntxnum=3, if_report=False)
    log.read()
    if scaled:
        log.get_scaled_csi()
    return int(log.count)


def rates(paths: list[Path], repeats: int) -> dict[str, float]:
    """Records per second of each decoder over `paths`, median over `repeats`."""
    count = sum(len(read_dat(p, scaled=False)) for p in paths)
    ways: dict[str, Callable[[Path], int]] = {
        "scaled": lambda p: len(read_dat(p, scaled=True)),
        "raw": lambda p: len(read_dat(p, scaled=False)),
        "stream": streamed,
    }
    if csiread is not None:
        ways["csiread_scaled"] = lambda p: csiread_read(p, True)
        ways["csiread_raw"] = lambda p: csiread_read(p, False)
    times: dict[str, list[float]] = {name: [] for name in ways}
    for _ in range(repeats):
        for name, way in ways.items():
            start = time.perf_counter()
            got = sum(way(p) for p in paths)
            times[name].append(time.perf_counter() - start)
            if got != count:
                raise SystemExit(f"{name} decoded {got} of {count} records in {', '.join(map(str, paths))}")
    out = {name: count / float(np.median(t)) for name, t in times.items()}
    out["records"] = count
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=50_000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--json", help="write the figures here (bench/run_all.py)")
    args = ap.parse_args()
    csi = Path(os.environ.get("ROVER_TEST_DATA", ROOT.parent / "shared" / "data")) / "csi"
    lgtm = sorted((csi / "lgtm").glob("*.dat"))
    if not lgtm:
        sys.exit(
            f"reference data not found at {csi.parent}: it is the shared/data folder beside this repository "
            "(set ROVER_TEST_DATA to point at it)"
        )
    if csiread is None:
        print("csiread is not installed (pip install csiread, or `make bench`): rover's figures only")
    sample = [r for r in records_of(csi / "log.all_csi.6.7.6.dat") if r[2] == 0xBB and r[3 + 9] == 1]
    kinds = {"3x1": sample, "3x2": records_of(csi / "sample_0x1_ap.dat"), "mixed": records_of(lgtm[0])}
    figures: dict[str, dict[str, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind, records in kinds.items():
            path = Path(tmp) / f"{kind}.dat"
            path.write_bytes(repeated(records, args.records))
            figures[kind] = rates([path], args.repeats)
    figures["lgtm_files"] = rates(lgtm, args.repeats)
    figures["sample_files"] = rates([csi / "log.all_csi.6.7.6.dat", csi / "sample_0x1_ap.dat"], args.repeats)
    print(f"{'log':<14}{'records':>9}{'scaled/s':>11}{'raw/s':>11}{'stream/s':>11}   vs csiread: scaled   raw")
    missed = []
    for kind, f in figures.items():
        line = f"{kind:<14}{f['records']:>9,.0f}{f['scaled']:>11,.0f}{f['raw']:>11,.0f}{f['stream']:>11,.0f}"
        if "csiread_raw" in f:
            f["ratio_scaled"] = f["scaled"] / f["csiread_scaled"]
            f["ratio_raw"] = f["raw"] / f["csiread_raw"]
            f["ratio_stream"] = f["stream"] / f["csiread_scaled"]
            line += f"   {f['ratio_scaled']:>15.2f}x {f['ratio_raw']:>5.2f}x  (stream {f['ratio_stream']:.2f}x)"
            missed += [f"{kind} {w}" for w in ("scaled", "raw") if f[f"ratio_{w}"] < 1.0 and kind in kinds]
        print(line)
    if csiread is not None:
        print(
            "read_dat >= csiread on every kind" if not missed else f"read_dat slower than csiread: {', '.join(missed)}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
