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
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise BadInput(f"{path}: cannot read: {exc.strerror or exc}") from None
    return parse_tags_csv(text, str(path))


def parse_tags_csv(text: str, source: str) -> list[TruthTag]:
    """The tag truth CSV from text (as a dataset's `rover.truth` metadata carries it)."""
    reader = csv.DictReader(text.splitlines())
    missing = [c for c in TAG_COLUMNS[:5] if c not in (reader.fieldnames or [])]
    if missing:
        raise BadInput(f"{source}:1: missing column(s) {', '.join(missing)} (expected {','.join(TAG_COLUMNS)})")
    tags = []
    for row in reader:
        try:
            tags.append(
                TruthTag(
                    int(row["id"]),
                    int(row["channel"]),
                    (float(row["x"]), float(row["y"]), float(row["z"])),
                    bool(int(row.get("nlos") or 0)),
                )
            )
        except (TypeError, ValueError):
            raise BadInput(f"{source}:{reader.line_num}: bad tag row {row}") from None
    return tags


def read_dataset_truth(path: str | Path) -> tuple[Trajectory | None, list[TruthTag]]:
    """The ground truth a dataset carries: `/groundtruth/pose` and the tags (metadata `rover.truth`,
    else `/groundtruth/tags`); (None, []) when it has none."""
    from rover.formats.bag import BagReader
    from rover.messages import deserialize

    path = Path(path)
    stamps, xyz, quat, tags = [], [], [], []
    with BagReader(path, "cannot read the dataset's ground truth") as bag:
        meta = bag.metadata()
        for message in bag.messages(["/groundtruth/pose", "/groundtruth/tags"], log_time_order=False):
            msg = deserialize(message.data, message.schema)
            if message.topic == "/groundtruth/tags":
                tags = [TruthTag(t.id, t.channel, (t.position.x, t.position.y, t.position.z), False) for t in msg.tags]
                continue
            p, q = msg.pose.position, msg.pose.orientation
            stamps.append(msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec)
            xyz.append((p.x, p.y, p.z))
            quat.append((q.x, q.y, q.z, q.w))
    if "tags_csv" in meta.get("rover.truth", {}):
        tags = parse_tags_csv(meta["rover.truth"]["tags_csv"], f"{path} (metadata rover.truth)")
    order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
    trajectory = (
        Trajectory(np.array(stamps, dtype=np.int64)[order], np.array(xyz)[order], np.array(quat)[order])
        if stamps
        else None
    )
    return trajectory, tags
