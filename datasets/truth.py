"""Ground truth files as users deliver them: trajectories in TUM format, tag positions as CSV."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rover.errors import BadInput

TAG_COLUMNS = ("id", "channel", "x", "y", "z", "nlos")


@dataclass(frozen=True)
class Trajectory:
    """Poses `t x y z qx qy qz qw`, t in nanoseconds."""

    stamp_ns: np.ndarray
    xyz: np.ndarray
    quat_xyzw: np.ndarray


@dataclass(frozen=True)
class TruthTag:
    id: int
    channel: int
    xyz: tuple[float, float, float]
    nlos: bool


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory (comments with #); BadInput names the file and line of a bad row."""
    path = Path(path)
    rows = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    for number, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        parts = text.replace(",", " ").split()
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise BadInput(f"{path}:{number}: not a TUM row (t x y z qx qy qz qw): {line.strip()!r}") from None
        if len(values) != 8 or not np.all(np.isfinite(values)):
            raise BadInput(f"{path}:{number}: a TUM row has 8 finite numbers (t x y z qx qy qz qw), got {len(values)}")
        rows.append((parts[0], values))
    if not rows:
        raise BadInput(f"{path}: no poses")
    stamps = np.array([_seconds_to_ns(text) for text, _ in rows], dtype=np.int64)
    data = np.array([v for _, v in rows])
    return Trajectory(stamps, data[:, 1:4], data[:, 4:8])


def _seconds_to_ns(text: str) -> int:
    """Seconds as written (e.g. `1700000000.010000`) to integer nanoseconds, without float rounding."""
    whole, _, frac = text.partition(".")
    return int(whole) * 1_000_000_000 + int((frac + "000000000")[:9]) * (-1 if whole.startswith("-") else 1)


def read_tags_csv(path: str | Path) -> list[TruthTag]:
    """Read `id,channel,x,y,z,nlos` (nlos optional, 0/1)."""
    path = Path(path)
    try:
        with path.open(newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            missing = [c for c in TAG_COLUMNS[:5] if c not in (reader.fieldnames or [])]
            if missing:
                raise BadInput(f"{path}:1: missing column(s) {', '.join(missing)} (expected {','.join(TAG_COLUMNS)})")
            tags = []
            for row in reader:
                try:
                    tags.append(TruthTag(int(row["id"]), int(row["channel"]),
                                         (float(row["x"]), float(row["y"]), float(row["z"])),
                                         bool(int(row.get("nlos") or 0))))
                except (TypeError, ValueError):
                    raise BadInput(f"{path}:{reader.line_num}: bad tag row {row}") from None
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    return tags
