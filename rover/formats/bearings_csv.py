"""Bearings from another AoA front end, as a CSV file the SLAM can run from (issue 44's "bearings
from elsewhere"): one row per bearing, `time_s,tag,angle_deg,std_deg`.

- `time_s`: the bearing's time on the dataset's clock (seconds, as TUM files and ROS stamps: the
  same clock as the IMU and odometry it is replayed with);
- `tag`: the tag's (or transmitter's) id, a non-negative integer;
- `angle_deg`: the direction of the tag seen from the robot, in the robot's frame (`base_link`: x
  forward, y left, counterclockwise), degrees;
- `std_deg`: its standard deviation, degrees, positive.

Rows may come in any order (they are sorted by time). A row that breaks these is refused naming
its line: a bearing silently dropped would bend the map without a trace."""

from __future__ import annotations

import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rover.errors import BadInput

HEADER = "time_s,tag,angle_deg,std_deg"
MAX_TAG_ID = 2**32 - 1


@dataclass(frozen=True)
class Bearings:
    """Bearings in time order."""

    stamp_ns: np.ndarray
    tag: np.ndarray
    angle_rad: np.ndarray
    std_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.stamp_ns)


def _bad_line(path: Path, lines: list[str]) -> str:
    """The first data line that does not hold four numbers as the format says, and why (the error
    path only: the file was already refused as a whole)."""
    for number, line in enumerate(lines[1:], 2):
        fields = line.split(",")
        if not line.strip():
            continue
        if len(fields) != 4:
            return f"{path}, line {number}: {len(fields)} fields, expected 4 ({HEADER})"
        try:
            t, tag, angle, std = (float(f) for f in fields)
        except ValueError:
            return f"{path}, line {number}: not a number in {line.strip()!r}"
        if not all(math.isfinite(v) for v in (t, tag, angle, std)):
            return f"{path}, line {number}: a value that is not finite"
        if tag != int(tag) or not 0 <= tag <= MAX_TAG_ID:
            return f"{path}, line {number}: tag {fields[1].strip()} is not a non-negative integer id"
        if std <= 0:
            return f"{path}, line {number}: std_deg {fields[3].strip()} is not positive"
        if t < 0:
            return f"{path}, line {number}: time_s {fields[0].strip()} is before 1970"
    return f"{path}: not a bearings CSV ({HEADER})"


def stamps_ns(column: np.ndarray, seconds: np.ndarray) -> np.ndarray:
    """The rows' times (`column`, as written) in integer nanoseconds, digit for digit where written
    as plain decimals (a float holds 1.7e9 s only to about 120 ns, so a bearing could land on the
    wrong side of the dataset message it shares a stamp with); as the float `seconds` rounds them
    where written otherwise."""
    parts = np.char.partition(column, ".")
    whole, fraction = parts[:, 0], parts[:, 2]
    plain = np.char.isdigit(whole) & (np.char.isdigit(fraction) | (np.char.str_len(fraction) == 0))
    exact = np.zeros(len(column), dtype=np.int64)
    if plain.any():
        nanos = np.char.ljust(fraction[plain], 9, "0").astype("U9").astype(np.int64)  # U9: the first 9 digits
        exact[plain] = whole[plain].astype(np.int64) * 1_000_000_000 + nanos
    rounded = np.round(seconds * 1e9).astype(np.int64)
    return np.where(plain, exact, rounded)


def read_bearings(path: str | Path) -> Bearings:
    """The file's bearings, sorted by time; BadInput naming the line that breaks the format."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a BOM: a CSV saved by a spreadsheet
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: cannot read bearings: {getattr(exc, 'strerror', None) or exc}") from None
    lines = text.splitlines()
    if not lines or lines[0].strip().replace(" ", "") != HEADER:
        raise BadInput(f"{path}, line 1: the header must be {HEADER}")
    if not any(line.strip() for line in lines[1:]):
        raise BadInput(f"{path}: no bearings after the header")
    try:
        cells = np.char.strip(np.loadtxt(io.StringIO(text), delimiter=",", skiprows=1, ndmin=2, dtype=str))
        rows = cells.astype(np.float64)
    except ValueError:
        raise BadInput(_bad_line(path, lines)) from None
    if rows.shape[1] != 4 or not np.isfinite(rows).all():
        raise BadInput(_bad_line(path, lines))
    t, tag, angle, std = rows.T
    if (tag != np.round(tag)).any() or (tag < 0).any() or (tag > MAX_TAG_ID).any() or (std <= 0).any() or (t < 0).any():
        raise BadInput(_bad_line(path, lines))
    stamps = stamps_ns(cells[:, 0], t)
    order = np.argsort(stamps, kind="stable")
    return Bearings(
        stamp_ns=stamps[order],
        tag=tag[order].astype(np.int64),
        angle_rad=np.radians(angle[order]),
        std_rad=np.radians(std[order]),
    )
