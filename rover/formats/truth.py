"""Ground truth files as users deliver them: trajectories in TUM format, tag positions as CSV."""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import ROUND_HALF_EVEN, Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from rover.errors import BadInput
from rover.formats.text import csv_float, csv_int, excerpt, read_text, tag_rows

TAG_COLUMNS = ("id", "channel", "x", "y", "z", "nlos")
TUM_FIELDS = ("t", "x", "y", "z", "qx", "qy", "qz", "qw")
STAMP_LIMIT_S = 2**31
"""Stamps are seconds since 1970 below 2**31 (2038-01-19): a ROS 2 header holds its seconds as int32."""
STAMP_LIMIT_NS = STAMP_LIMIT_S * 1_000_000_000


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
    """Read a TUM trajectory (comments with #); BadInput names the file and line of a bad row.

    Stamps are parsed exactly (any decimal or exponent notation) and rounded to the nanosecond;
    they must lie in [0, 2**31) seconds, the range of a ROS 2 stamp.
    """
    path = Path(path)
    stamps, rows = [], []
    for number, line in enumerate(read_text(path).splitlines(), 1):
        text = line.split("#", 1)[0].strip()
        if not text:
            continue
        where = f"{path}:{number}"
        parts = text.replace(",", " ").split()
        if len(parts) != len(TUM_FIELDS):
            raise BadInput(f"{where}: a TUM row has 8 numbers (t x y z qx qy qz qw), got {len(parts)}: {excerpt(line)}")
        try:
            values = [float(v) for v in parts[1:]]
        except ValueError:
            raise BadInput(f"{where}: not a TUM row (t x y z qx qy qz qw): {excerpt(line)}") from None
        for name, value, word in zip(TUM_FIELDS[1:], values, parts[1:], strict=True):
            if not math.isfinite(value):
                raise BadInput(f"{where}: {name} has a non-finite value {excerpt(word, 20)}")
        if not any(values[3:]):
            raise BadInput(f"{where}: the quaternion (qx qy qz qw) is zero, not a rotation")
        stamps.append(_seconds_to_ns(parts[0], where))
        rows.append(values)
    if not rows:
        raise BadInput(f"{path}: no poses")
    data = np.array(rows, dtype=np.float64)
    return Trajectory(np.array(stamps, dtype=np.int64), data[:, 0:3], data[:, 3:7])


def _seconds_to_ns(text: str, where: str) -> int:
    """Seconds as written (e.g. `1700000000.010000`, `1.7e9`) to integer nanoseconds, without float
    rounding; BadInput at `where` for a stamp that is not a number or not in [0, 2**31) s."""
    quoted = excerpt(text, 30)
    try:
        seconds = Decimal(text)
    except InvalidOperation:
        raise BadInput(f"{where}: t is not a number: {quoted}") from None
    if not seconds.is_finite():
        raise BadInput(f"{where}: t has a non-finite value {quoted}")
    if seconds < 0:
        raise BadInput(f"{where}: t is negative: {quoted} (stamps are seconds since 1970)")
    if seconds >= STAMP_LIMIT_S or (ns := int(seconds.scaleb(9).to_integral_value(ROUND_HALF_EVEN))) >= STAMP_LIMIT_NS:
        raise BadInput(f"{where}: t is {quoted} s, not before 2**31 s (2038-01-19), the end of a ROS 2 stamp")
    return ns


def read_tags_csv(path: str | Path) -> list[TruthTag]:
    """Read `id,channel,x,y,z,nlos` (nlos optional, 0/1)."""
    return parse_tags_csv(read_text(path), str(path))


def parse_tags_csv(text: str, source: str) -> list[TruthTag]:
    """The tag truth CSV from text (as a dataset's `rover.truth` metadata carries it); BadInput names
    `source` and the line of a missing column or value, a bad number, a repeated id."""
    tags: list[TruthTag] = []
    for where, tag_id, row in tag_rows(text, source, TAG_COLUMNS[:5], "id,channel,x,y,z[,nlos]"):
        nlos = csv_int(row, "nlos", where, 2) if row.get("nlos", "").strip() else 0
        xyz = (csv_float(row, "x", where), csv_float(row, "y", where), csv_float(row, "z", where))
        tags.append(TruthTag(tag_id, csv_int(row, "channel", where, 2**16), xyz, bool(nlos)))
    return tags


def read_dataset_truth(path: str | Path) -> tuple[Trajectory | None, list[TruthTag]]:
    """The ground truth a dataset carries: `/groundtruth/pose` and the tags (metadata `rover.truth`,
    else `/groundtruth/tags`); (None, []) when it has none. BadInput names the file and topic of a
    message of another type, one that does not deserialize or a non-finite pose."""
    from rover.formats.bag import BagReader

    path = Path(path)
    types = {"/groundtruth/pose": "geometry_msgs/msg/PoseStamped", "/groundtruth/tags": "rover_msgs/msg/TagArray"}
    stamps, xyz, quat, tags = [], [], [], []
    with BagReader(path, "cannot read the dataset's ground truth") as bag:
        meta = bag.metadata()
        for message in bag.messages(types, log_time_order=False):
            msg = bag.decode(message, types[message.topic])
            if message.topic == "/groundtruth/tags":
                tags = [TruthTag(t.id, t.channel, (t.position.x, t.position.y, t.position.z), False) for t in msg.tags]
                continue
            p, q = msg.pose.position, msg.pose.orientation
            if not all(math.isfinite(v) for v in (p.x, p.y, p.z, q.x, q.y, q.z, q.w)):
                raise BadInput(f"{path}: topic {message.topic}: a non-finite pose at {message.log_time_ns} ns")
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
